"""The whole-tissue maps of a session under way: every level the loop records is kept, and the maps are
stitched again (:mod:`session.stitch`, the same placement, overlap averaging and coverage as the reviewer
and the exported maps) when someone asks for them after a new level arrived.

With them come the contrast maps and the tumours found so far, by the same flat field and detection as
the reviewer (:mod:`session.flatfield`, :mod:`session.detect`). The face's pattern comes from a reference
palpation when one is loaded, else from the other areas palpated at the same level, which needs
``MIN_VOUCHING`` + 1 areas before it says anything (:meth:`LiveMaps.flat_field_ready`). Where the
composition root can compute the physics (the homogeneous block rebuilt from the areas palpated so far,
14-20 s of finite elements, in the background after each area), it says so (:attr:`LiveMaps.physics_expected`)
and the maps wait for it (:meth:`LiveMaps.set_physics`): without it the other areas' pattern does not hold
where the tissue ends, and on the paper's flat phantom the corners of the areas at its ends read as six
tumours with scores of 5 to 15. Contrast and findings then come from the records the physics covers; an area palpated
since is analysed when its physics arrives (:meth:`LiveMaps.pending`).

The same pattern flat-fields the live frames (:meth:`LiveMaps.frame_contrast`): a frame is compared with
the pattern of the recorded level nearest its force (the reference's, or the median over the areas
palpated at that level), and its significant spots are found by the same matched filter and threshold as
a level record's. A single frame is noisier than a level's settled mean; its uncertainty counts the
frame-to-frame scatter the records measured, so a spot that shows in a frame is as unlikely in healthy
tissue as one in a record. What stays is decided on the records, not the frames.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from control.messages import LevelRecord
from hardware.interfaces import TactileConstraints
from session.analysis import CONTRAST_MAPS, DepthModel
from session.detect import SOURCES, DetectParams, Tumour, detect, evidence_by_width, significant_peaks, threshold
from session.flatfield import MIN_VOUCHING, Contrast, FlatFieldError, Reference, contrast
from session.format import LEVEL_DTYPE, level_row
from session.physics import Pattern
from session.stitch import StitchParams, StitchResult, level_groups, stitch

# the level field whose pattern flat-fields each live map
FRAME_QUANTITY = {"force": "pressure_pa", "stiffness": "stiffness_pa"}


@dataclass(frozen=True)
class FrameContrast:
    """One live frame of a map, flat-fielded."""

    contrast: np.ndarray  # (rows, cols) measured / expected - 1; NaN where the element is not in contact
    z: np.ndarray  # (rows, cols) the matched-filter statistic (session.detect.evidence)
    spots: tuple[tuple[int, int], ...]  # elements (row, col) where a significant spot peaks
    level_N: float  # the recorded level whose pattern it was compared with
    sigma: np.ndarray  # (rows, cols) the contrast's relative uncertainty (healthy tissue's scatter and the frame's)


@dataclass(frozen=True)
class _FramePattern:
    forces_N: np.ndarray  # (levels,)
    baseline: np.ndarray  # (levels, rows, cols) each element's share of the map at that level, median 1
    scatter: np.ndarray  # (levels, rows, cols) relative: healthy tissue's and a frame's scatter together


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
        self._stiffness: tuple[np.ndarray, Contrast] | None = None  # the levels and contrast they were found in
        self._frame_patterns: dict[str, _FramePattern] = {}
        self._dirty = False
        self.reference: Reference | None = None
        self.detect_params = DetectParams()
        self.depth_model: DepthModel | None = None  # gives findings_in its model-based depths
        self.physics_expected = False  # the contrast waits for set_physics (module docstring)
        self._physics: tuple[int, dict[str, Pattern], str] | None = None  # records covered, pattern per map, how

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
            levels = self.levels()
            extra = None
            self._tumours = []
            self._stiffness = None
            self._frame_patterns = {}
            analysed = self._analysed()
            if analysed:
                some = levels[:analysed]
                contrasts = {s: self._contrast(some, s) for s in SOURCES}
                later = np.full((len(levels) - analysed,) + levels.dtype["pressure_pa"].shape, np.nan)
                extra = {CONTRAST_MAPS[s]: np.concatenate([c.contrast, later]) for s, c in contrasts.items()}
                self._tumours = [t for s in SOURCES
                                 for t in detect(some, contrasts[s], self._sensor.pitch_m, self.detect_params)]
                self._stiffness = some, contrasts["stiffness"]
                self._frame_patterns = {s: self._frame_pattern(levels, s) for s in SOURCES}
            self._result = stitch(levels, self._sensor.pitch_m, self._sensor.element_area_m2, self._params,
                                  self._min_indentation_m, extra)
        return self._result

    def frame_contrast(self, values: np.ndarray, map_name: str, force_N: float) -> FrameContrast | None:
        """A live frame of the ``map_name`` map ("force": pressure in Pa, "stiffness": Eq. 1 in Pa; NaN where
        an element is not in contact) pressed with ``force_N``, against the pattern of the nearest recorded
        level; None until the flat field can be had. A frame with too little in contact to scale it has no
        contrast (all NaN)."""
        self.stitched()
        pattern = self._frame_patterns.get(map_name)
        if pattern is None:
            return None
        values = np.asarray(values, dtype=float)
        touching = np.isfinite(values) & (values > 0)
        if not math.isfinite(force_N) or touching.sum() < MIN_VOUCHING:
            nothing = np.full(values.shape, np.nan)
            return FrameContrast(nothing, nothing, (), math.nan, nothing)
        k = int(np.argmin(np.abs(pattern.forces_N - force_N)))
        base, scatter = pattern.baseline[k], pattern.scatter[k]
        ratio = np.where(touching, values, np.nan) / base
        with np.errstate(invalid="ignore", divide="ignore"):
            c = ratio / np.nanmedian(ratio) - 1.0
        params = self.detect_params
        sigma = np.maximum(np.nan_to_num(scatter, nan=0.0), params.accuracy)
        c = np.where(np.isfinite(c), c, np.nan)
        # elements without contrast are left out
        by_width = evidence_by_width(c, sigma, self._sensor.pitch_m, params.kernel_widths_m)
        limit = threshold(params.false_alarm_per_area, c.shape, self._sensor.pitch_m, params.kernel_widths_m)
        peaks = significant_peaks(by_width, limit, c)
        z = np.max(by_width, axis=0)
        return FrameContrast(c, z, tuple((int(i), int(j)) for i, j in zip(*np.nonzero(peaks))),
                             float(pattern.forces_N[k]), sigma)

    def _frame_pattern(self, levels: np.ndarray, map_name: str) -> _FramePattern:
        """Each recorded level's pattern of the map (the reference's when one is loaded, else the median over
        the areas at that level) and its scatter: healthy tissue's between areas, and a frame's own noise
        (the records' frame-to-frame scatter, relative)."""
        quantity = FRAME_QUANTITY[map_name]
        groups = level_groups(levels)
        forces = np.array([force for force, _ in groups])
        with np.errstate(invalid="ignore", divide="ignore"):
            frame_noise = np.stack([np.nanmedian(levels["pressure_std_pa"][records] / levels["pressure_pa"][records],
                                                 axis=0) for _, records in groups])
        if self.reference is not None:  # a reference without physics: the face's whole pattern, per level
            pairs = [self.reference.at(force) for force in forces]
            baseline, scatter = np.stack([b for b, _ in pairs]), np.stack([sc for _, sc in pairs])
        else:
            ones = np.ones(levels["pressure_pa"].shape)
            own = Reference.from_levels(levels, ones, np.zeros_like(ones), "", physics=False, quantity=quantity)
            baseline, scatter = own.baseline, own.scatter
        scatter = np.sqrt(np.nan_to_num(scatter, nan=0.0) ** 2 + np.nan_to_num(frame_noise, nan=0.0) ** 2)
        return _FramePattern(forces, baseline, scatter)

    def _contrast(self, levels: np.ndarray, map_name: str) -> Contrast:
        accuracy = self.detect_params.accuracy
        if self._physics is None or self.reference is not None:  # a live reference holds the whole pattern
            return contrast(levels, map_name, reference=self.reference, accuracy=accuracy)
        _, patterns, description = self._physics
        n, pattern = len(levels), patterns[map_name]
        modes = None if pattern.modes is None else pattern.modes[:n]
        return contrast(levels, map_name, pattern.share[:n], pattern.sigma[:n], None, accuracy, description, modes)

    def _analysed(self) -> int:
        """How many records (the first ones) the contrast and the findings come from; 0: none yet."""
        if self.reference is not None:
            return len(self._rows)
        if not self.physics_expected:
            return len(self._rows) if len(self._regions) > MIN_VOUCHING else 0
        if self._physics is None:
            return 0
        covered = self._physics[0]
        return covered if len({row[1] for row in self._rows[:covered]}) > MIN_VOUCHING else 0

    def set_physics(self, records: int, patterns: dict[str, Pattern], description: str) -> None:
        """The pattern homogeneous tissue gives each map (``patterns[map]``,
        :meth:`session.physics.HomogeneousTissue.pattern`)
        on the first ``records`` level records, as computed from them (``description`` says how)."""
        if not 0 < records <= len(self._rows) or set(patterns) != set(SOURCES):
            raise ValueError(f"physics for {records} records of {len(self._rows)}, maps {sorted(patterns)}")
        if any(len(p.share) != records for p in patterns.values()):
            raise ValueError(f"physics patterns do not cover the {records} records they are for")
        self._physics = (records, patterns, description)
        self._dirty = True

    def drop_physics(self) -> None:
        """No physics after all (it could not be computed): the pattern comes from the areas alone."""
        self.physics_expected = False
        self._physics = None
        self._dirty = True

    def pending(self, region: int) -> bool:
        """Whether area ``region``'s records wait for their physics to be analysed."""
        if not self.physics_expected or self.reference is not None:
            return False
        return any(row[1] == region for row in self._rows[self._analysed():])

    def flat_field_ready(self) -> bool:
        """Whether the probe's pattern can be taken out yet: a reference is loaded, or enough areas were
        palpated for each one's baseline to come from the others (and, where it is expected, their physics
        was computed)."""
        return self._analysed() > 0

    def tumours(self) -> list[Tumour]:
        """The tumours found so far (as of the last :meth:`stitched`)."""
        self.stitched()
        return list(self._tumours)

    def findings_in(self, region: int, told: Sequence[Tumour] = ()) -> list[Tumour]:
        """The tumours found so far that area ``region`` saw (one of their spots lies in its records), with
        their model-based depth when a :attr:`depth_model` is set (as the reviewer's analysis does it: from
        the stiffness contrast, which has the surface's relief taken out). Those ``told`` of already (the
        same map's, within the merge radius) are left out."""
        self.stitched()
        radius = self.detect_params.merge_radius_m
        seen = [t for t in self._tumours if any(self._rows[spot.record][1] == region for spot in t.spots)
                and not any(k.source == t.source and math.dist((k.x_m, k.y_m), (t.x_m, t.y_m)) < radius
                            for k in told)]
        if self.depth_model is None or self._stiffness is None:
            return seen
        levels, stiffness = self._stiffness
        return [t.with_depth_model(*self.depth_model.estimate(t, levels, stiffness)) for t in seen]

    def set_reference(self, reference: Reference | None) -> None:
        """Raises FlatFieldError for a reference made over physics (the live maps have none)."""
        if reference is not None:
            reference.check_usable(with_physics=False)
        self.reference = reference
        self._dirty = True

    def levels(self) -> np.ndarray:
        """Every level recorded so far (``session.format.LEVEL_DTYPE``)."""
        return np.array(self._rows, dtype=LEVEL_DTYPE)

    def reference_from_levels(self, description: str) -> Reference:
        """The levels recorded so far as a reference palpation of tumour-free tissue (the face's whole
        pattern, no physics); raises FlatFieldError before the first level."""
        if not self._rows:
            raise FlatFieldError("no level recorded yet: palpate tumour-free tissue first")
        levels = self.levels()
        ones = np.ones(levels["pressure_pa"].shape)
        return Reference.from_levels(levels, ones, np.zeros_like(ones), description, physics=False)

    @property
    def level_count(self) -> int:
        return len(self._rows)

    @property
    def region_count(self) -> int:
        return len(self._regions)
