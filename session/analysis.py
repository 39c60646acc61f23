"""One analysis of a recorded session, the same for the ``stitch`` command, the reviewer and the report:
take the probe's own pattern out of every level record (the contrast, :mod:`session.flatfield`), find the
tumours in the stiffness map and in the force map (:mod:`session.detect`), stitch the raw and contrast maps
into whole-tissue maps (:mod:`session.stitch`), and, for a simulated session, score what was found against
the phantom's ground truth.

The physics of the expected pattern (a homogeneous block pressed by the face, :mod:`session.physics`) and the
model-based depth (:mod:`session.depth`) are given to it; without physics the analysis still runs, with the
face's pattern left to the session's own baseline, and says so. Nothing here writes to the session file:
an analysis is derived data, recomputable from the file alone with other parameters (:class:`AnalysisParams`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from session.depth import DepthModel
from session.detect import (
    SOURCES,
    DepthParams,
    DetectParams,
    TruthMatch,
    Tumour,
    detect,
    explained_away,
    match_ground_truth,
    over_each_other,
)
from session.flatfield import Contrast, Reference, contrast
from session.physics import HomogeneousTissue, Pattern, Progress
from session.reader import Session
from session.stitch import StitchParams, StitchResult, stitch_session
from tissue.mechanics.progress import stage

CONTRAST_MAPS = {"stiffness": "stiffness_contrast", "force": "force_contrast"}


@dataclass(frozen=True)
class AnalysisParams:
    stitch: StitchParams = field(default_factory=StitchParams)
    detect: DetectParams = field(default_factory=DetectParams)
    depth: DepthParams = field(default_factory=DepthParams)


@dataclass
class SessionAnalysis:
    """The contrasts, the tumours found (stiffness map first, then the force map), the stitched maps (raw
    quantities and ``stiffness_contrast``/``force_contrast``) and, when the session knows its ground truth,
    each true tumour matched per map and the false positives per map."""

    session: Session
    params: AnalysisParams
    stitched: StitchResult
    contrasts: dict[str, Contrast]
    tumours: list[Tumour]
    flat_field: str  # how the expected pattern was obtained, in words
    matches: list[TruthMatch] = field(default_factory=list)
    false_positives: dict[str, int] = field(default_factory=dict)

    @classmethod
    def run(cls, session: Session, params: AnalysisParams | None = None, physics: HomogeneousTissue | None = None,
            reference: Reference | None = None, depth_model: DepthModel | None = None) -> SessionAnalysis:
        params = params or AnalysisParams()
        levels = session.levels
        contrasts = {}
        patterns = expected_patterns(physics, levels) if physics is not None and len(levels) else {}
        for source in SOURCES:
            share = sigma = modes = None
            if source in patterns:
                share, sigma, modes = patterns[source].share, patterns[source].sigma, patterns[source].modes
            contrasts[source] = contrast(levels, source, share, sigma, reference, params.detect.accuracy,
                                         physics.description if physics is not None else "", modes)
        tumours = [t for source in SOURCES for t in detect(levels, contrasts[source], session.pitch_m, params.detect)]
        if depth_model is not None:
            depth_model = depth_model.with_params(params.depth)

            def fitted(tumour, seen, records):
                return depth_model.signature(tumour, levels, seen, records)

            def signature(tumour, records):
                return fitted(tumour, contrasts["stiffness"], records)

            tumours = [t for source in SOURCES
                       for t in explained_away([t for t in tumours if t.source == source], levels, contrasts[source],
                                               session.pitch_m, params.detect, signature)]
            # where each now lies (each is placed over the others' far fields), from what stands out over
            # the others' spheres (each fitted over the rest), for the model explains one; the stiffness
            # contrast for either map's tumours: Eq. 1 has taken the surface's relief out of it
            face_length = levels.dtype["pressure_pa"].shape[0] * session.pitch_m  # the estimate reads half that
            tumours = [t.with_depth_model(*depth_model.estimate(t, levels, seen)) for t, seen in
                       zip(tumours, over_each_other(tumours, levels, contrasts["stiffness"], fitted, face_length))]
        stitched = stitch_session(session, params.stitch,
                                  {CONTRAST_MAPS[s]: contrasts[s].contrast for s in SOURCES} if len(levels) else None)
        analysis = cls(session, params, stitched, contrasts, tumours, contrasts["stiffness"].description)
        if _truth_known(session):
            analysis.matches, analysis.false_positives = match_ground_truth(tumours, session.ground_truth, levels,
                                                                            session.pitch_m)
        return analysis

    @property
    def has_ground_truth(self) -> bool:
        return _truth_known(self.session)

    def found_count(self) -> dict[str, int]:
        """True tumours found, per map."""
        return {source: sum(1 for m in self.matches if m.source == source and m.found) for source in SOURCES}

    def palpated_count(self) -> int:
        """True tumours under some palpated area."""
        return sum(1 for m in self.matches if m.source == SOURCES[0] and m.palpated)

    def truth_of(self, detection: int) -> TruthMatch | None:
        """The true tumour a detection (index into :attr:`tumours`) was matched to, if any."""
        return next((m for m in self.matches if m.found and m.detection == detection), None)


def expected_patterns(physics: HomogeneousTissue, levels: np.ndarray, progress: Progress | None = None
                      ) -> dict[str, Pattern]:
    """What homogeneous tissue gives each map on every record: the stiffness map is compared with the surface
    the onsets measured, the force map with a flat one (the face's own pattern); ``progress(fraction, message)``
    after each record of each map."""
    return {source: physics.pattern(levels, measured_surface=source == "stiffness",
                                    progress=stage(progress, i / len(SOURCES), (i + 1) / len(SOURCES)))
            for i, source in enumerate(SOURCES)}


def _truth_known(session: Session) -> bool:
    """Whether the session knows where every tumour is: a simulated phantom's list is its whole truth, so a
    phantom without tumours makes every detection a false positive (a real session's list is empty)."""
    return bool(session.ground_truth) or (session.simulated and session.phantom is not None)
