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
from session.physics import HomogeneousTissue, Pattern
from session.reader import Session
from session.stitch import StitchParams, StitchResult, stitch_session
from tissue.mechanics.progress import Progress, stage

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
            reference: Reference | None = None, depth_model: DepthModel | None = None,
            progress: Progress | None = None) -> SessionAnalysis:
        """``progress(fraction, message)`` as it goes, before each record of the flat field's pattern, each tumour
        the depth model takes in turn and each finite-element solve it needs; a ``progress`` that raises stops
        the analysis there (what the depth model has solved stays in its cache and the tissue model's)."""
        params = params or AnalysisParams()
        levels = session.levels
        contrasts = {}
        with_physics = physics is not None and len(levels)
        told = _Told(progress, {part: share for part, share in _PARTS.items()
                                if (part != "pattern" or with_physics)
                                and (depth_model is not None or part in _WITHOUT_DEPTH_MODEL)})
        patterns = expected_patterns(physics, levels, told.part("pattern", "the flat field: ")) if with_physics else {}
        for source in SOURCES:
            share = sigma = modes = None
            if source in patterns:
                share, sigma, modes = patterns[source].share, patterns[source].sigma, patterns[source].modes
            contrasts[source] = contrast(levels, source, share, sigma, reference, params.detect.accuracy,
                                         physics.description if physics is not None else "", modes)
        told.part("detect")(0.0, "finding the tumours")
        tumours = [t for source in SOURCES for t in detect(levels, contrasts[source], session.pitch_m, params.detect)]
        if depth_model is not None:
            # the layer's sides as the flat field's tissue has them (free where no model of the tissue says)
            sides = physics.sides if physics is not None else "free"
            depth_model = depth_model.with_params(params.depth).with_sides(sides)

            def fitted(tumour, seen, records):
                return depth_model.signature(tumour, levels, seen, records, told.solving)

            def signature(tumour, records):
                return fitted(tumour, contrasts["stiffness"], records)

            tumours = [t for source in SOURCES
                       for t in explained_away([t for t in tumours if t.source == source], levels, contrasts[source],
                                               session.pitch_m, params.detect, signature,
                                               told.part(source, f"depth model, {source} map: "))]
            # where each now lies (each is placed over the others' far fields), from what stands out over
            # the others' spheres (each fitted over the rest), for the model explains one; the stiffness
            # contrast for either map's tumours: Eq. 1 has taken the surface's relief out of it
            face_length = levels.dtype["pressure_pa"].shape[0] * session.pitch_m  # the estimate reads half that
            seen = over_each_other(tumours, levels, contrasts["stiffness"], fitted, face_length,
                                   told.part("over", "depth model: "))
            told.part("estimate")(0.0, "depth model: the depths")
            tumours = [t.with_depth_model(*depth_model.estimate(t, levels, over)) for t, over in zip(tumours, seen)]
        told.part("stitch")(0.0, "stitching the maps")
        stitched = stitch_session(session, params.stitch,
                                  {CONTRAST_MAPS[s]: contrasts[s].contrast for s in SOURCES} if len(levels) else None)
        analysis = cls(session, params, stitched, contrasts, tumours, contrasts["stiffness"].description)
        if _truth_known(session):
            analysis.matches, analysis.false_positives = match_ground_truth(
                tumours, session.ground_truth, levels, session.pitch_m, contrasts=contrasts, params=params.detect)
        told.part("stitch")(1.0, "analysed")
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


# Each part's share of the progress, about its share of a first analysis of a realistic study session (nothing
# cached: the flat field's pattern 12 %, the depth model's 21 finite-element solves the rest, a quarter each
# testing the stiffness map's and the force map's tumours, a third with the tumours over each other)
_PARTS = {"pattern": 0.13, "detect": 0.01, "stiffness": 0.25, "force": 0.24, "over": 0.33, "estimate": 0.02,
          "stitch": 0.02}
_WITHOUT_DEPTH_MODEL = ("pattern", "detect", "stitch")  # the parts an analysis without it has


class _Told:
    """An analysis's ``progress`` (none: nothing is told), its parts (name -> share, in order) one after
    another, and the depth model's finite-element solves told as they start, numbered, within the step the
    analysis is at: how many a session needs is not known before the fits that ask for them are made."""

    def __init__(self, progress: Progress | None, parts: dict[str, float]):
        self._progress = progress
        total, start = sum(parts.values()), 0.0
        self._spans = {}
        for part, share in parts.items():
            self._spans[part] = (start / total, (start + share) / total)
            start += share
        self._at = (0.0, "")
        self._solves = 0

    def part(self, name: str, prefix: str = "") -> Progress:
        """A callback for one part: its own 0..1 onto the part's span, its message after ``prefix``."""
        start, end = self._spans[name]

        def report(fraction: float, message: str) -> None:
            self._at = (start + (end - start) * min(1.0, max(0.0, fraction)), prefix + message)
            if self._progress is not None:
                self._progress(*self._at)

        return report

    def solving(self, what: str) -> None:
        self._solves += 1
        if self._progress is not None:
            fraction, step = self._at
            # what is solved first: a narrow terminal keeps the start of the line
            self._progress(fraction, f"finite-element solve {self._solves}: {what}; {step}")


def _truth_known(session: Session) -> bool:
    """Whether the session knows where every tumour is: a simulated phantom's list is its whole truth, so a
    phantom without tumours makes every detection a false positive (a real session's list is empty)."""
    return bool(session.ground_truth) or (session.simulated and session.phantom is not None)
