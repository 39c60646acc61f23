"""The whole-tissue maps of a session under way: every level the loop records is kept, and the maps are
stitched again (:mod:`session.stitch`, the same placement, overlap averaging and coverage as the reviewer
and the exported maps) when someone asks for them after a new level arrived.

With them come the contrast maps and the tumours found so far, by the same flat field and detection as
the reviewer (:mod:`session.flatfield`, :mod:`session.detect`). Live there is no finite-element physics
(it would be rebuilt for every new area); the face's pattern comes from a reference palpation when one is
loaded, else from the other areas palpated at the same level, which needs ``MIN_VOUCHING`` + 1 areas
before it says anything (:meth:`LiveMaps.flat_field_ready`)."""

from __future__ import annotations

import numpy as np

from control.messages import LevelRecord
from hardware.interfaces import TactileConstraints
from session.analysis import CONTRAST_MAPS
from session.detect import SOURCES, DetectParams, Tumour, detect
from session.flatfield import MIN_VOUCHING, FlatFieldError, Reference, contrast
from session.format import LEVEL_DTYPE, level_row
from session.stitch import StitchParams, StitchResult, stitch


class LiveMaps:
    """Levels added with :meth:`add` (as ``LevelRecorded`` events arrive); :meth:`stitched` is cheap when
    nothing was added since the last call."""

    def __init__(self, sensor: TactileConstraints, min_indentation_m: float, cell_m: float = 1e-3):
        self._sensor = sensor
        self._min_indentation_m = min_indentation_m
        self._params = StitchParams(cell_m=cell_m)
        self._rows: list[tuple] = []
        self._regions: set[int] = set()
        self._result: StitchResult | None = None
        self._tumours: list[Tumour] = []
        self._dirty = False
        self.reference: Reference | None = None
        self.detect_params = DetectParams()

    def add(self, record: LevelRecord) -> None:
        self._rows.append(level_row(record))  # [1] is the region
        self._regions.add(record.region)
        self._dirty = True

    @property
    def changed(self) -> bool:
        """Levels were added since the maps were last stitched."""
        return self._dirty

    def stitched(self) -> StitchResult | None:
        """The maps of every level recorded so far; None before the first."""
        if self._dirty:
            self._dirty = False
            levels = np.array(self._rows, dtype=LEVEL_DTYPE)
            extra = None
            self._tumours = []
            if self.flat_field_ready():
                contrasts = {s: contrast(levels, s, reference=self.reference, accuracy=self.detect_params.accuracy)
                             for s in SOURCES}
                extra = {CONTRAST_MAPS[s]: c.contrast for s, c in contrasts.items()}
                self._tumours = [t for s in SOURCES
                                 for t in detect(levels, contrasts[s], self._sensor.pitch_m, self.detect_params)]
            self._result = stitch(levels, self._sensor.pitch_m, self._sensor.element_area_m2, self._params,
                                  self._min_indentation_m, extra)
        return self._result

    def flat_field_ready(self) -> bool:
        """Whether the probe's pattern can be taken out yet: a reference is loaded, or enough areas were
        palpated for each one's baseline to come from the others."""
        return self.reference is not None or len(self._regions) > MIN_VOUCHING

    def tumours(self) -> list[Tumour]:
        """The tumours found so far (as of the last :meth:`stitched`)."""
        self.stitched()
        return list(self._tumours)

    def findings_in(self, region: int) -> list[Tumour]:
        """The tumours found so far that area ``region`` saw (one of their spots lies in its records)."""
        self.stitched()
        return [t for t in self._tumours if any(self._rows[spot.record][1] == region for spot in t.spots)]

    def set_reference(self, reference: Reference | None) -> None:
        """Raises FlatFieldError for a reference made over physics (the live maps have none)."""
        if reference is not None:
            reference.check_usable(with_physics=False)
        self.reference = reference
        self._dirty = True

    def reference_from_levels(self, description: str) -> Reference:
        """The levels recorded so far as a reference palpation of tumour-free tissue (the face's whole
        pattern, no physics); raises FlatFieldError before the first level."""
        if not self._rows:
            raise FlatFieldError("no level recorded yet: palpate tumour-free tissue first")
        levels = np.array(self._rows, dtype=LEVEL_DTYPE)
        ones = np.ones(levels["pressure_pa"].shape)
        return Reference.from_levels(levels, ones, np.zeros_like(ones), description, physics=False)

    @property
    def level_count(self) -> int:
        return len(self._rows)

    @property
    def region_count(self) -> int:
        return len(self._regions)
