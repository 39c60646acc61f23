"""One analysis of a recorded session, the same for the ``stitch`` command, the reviewer and the report:
stitch its levels into whole-tissue maps, find the tumours in them, and, for a simulated session, score
what was found against the phantom's ground truth.

Nothing here writes to the session file: an analysis is derived data, recomputable from the file alone
with other parameters (:class:`AnalysisParams`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from session.detect import SOURCES, DetectParams, Tumour, TruthMatch, detect_session, match_ground_truth
from session.reader import Session
from session.stitch import StitchParams, StitchResult, stitch_session


@dataclass(frozen=True)
class AnalysisParams:
    stitch: StitchParams = field(default_factory=StitchParams)
    detect: DetectParams = field(default_factory=DetectParams)


@dataclass
class SessionAnalysis:
    """The stitched maps, the tumours found (stiffness map first, then the force map) and, when the session
    knows its ground truth, each true tumour matched per map and the false positives per map."""

    session: Session
    params: AnalysisParams
    stitched: StitchResult
    tumours: list[Tumour]
    matches: list[TruthMatch] = field(default_factory=list)
    false_positives: dict[str, int] = field(default_factory=dict)

    @classmethod
    def run(cls, session: Session, params: AnalysisParams | None = None) -> SessionAnalysis:
        params = params or AnalysisParams()
        stitched = stitch_session(session, params.stitch)
        tumours = detect_session(session, stitched, params.detect)
        analysis = cls(session, params, stitched, tumours)
        if session.ground_truth:
            analysis.matches, analysis.false_positives = match_ground_truth(tumours, session.ground_truth,
                                                                            stitched=stitched)
        return analysis

    @property
    def has_ground_truth(self) -> bool:
        return bool(self.session.ground_truth)

    def found_count(self) -> dict[str, int]:
        """True tumours found, per map."""
        return {source: sum(1 for m in self.matches if m.source == source and m.found) for source in SOURCES}

    def palpated_count(self) -> int:
        """True tumours under some palpated area."""
        return sum(1 for m in self.matches if m.source == SOURCES[0] and m.palpated)

    def truth_of(self, detection: int) -> TruthMatch | None:
        """The true tumour a detection (index into :attr:`tumours`) was matched to, if any."""
        return next((m for m in self.matches if m.found and m.detection == detection), None)
