"""The whole-tissue maps of a session under way: every level the loop records is kept, and the maps are
stitched again (:mod:`session.stitch`, the same placement, overlap averaging and coverage as the reviewer
and the exported maps) when someone asks for them after a new level arrived."""

from __future__ import annotations

import numpy as np

from control.messages import LevelRecord
from hardware.interfaces import TactileConstraints
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
        self._dirty = False

    def add(self, record: LevelRecord) -> None:
        self._rows.append(level_row(record))
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
            self._result = stitch(levels, self._sensor.pitch_m, self._sensor.element_area_m2, self._params,
                                  self._min_indentation_m)
        return self._result

    @property
    def level_count(self) -> int:
        return len(self._rows)

    @property
    def region_count(self) -> int:
        return len(self._regions)
