"""Whole-tissue maps: every recorded level of every region placed on one grid, one map per force level.

How (written down once, here):

* **Placement.** Element (i, j) of a record covers a ``pitch`` x ``pitch`` square centred at the recorded
  TSI position plus the element's offset (the convention of :mod:`hardware.interfaces`: rows along x,
  columns along y). Nothing else is assumed about where the operator put the TSI.
* **Grid.** Square cells of ``cell_m`` in the tissue frame, anchored at multiples of ``cell_m`` from the
  origin (so maps made with the same cell size always line up), spanning every footprint recorded.
  Arrays are shaped (nx, ny): first index along x, like the sensor's rows.
* **Splatting and overlaps.** Each element contributes to every cell its square overlaps, weighted by the
  overlap area; a cell's value is the weighted mean of the contributions, so regions that overlap are
  averaged and a cell smaller than an element shows the element's value. Elements without a value (NaN:
  no contact, stiffness below the minimum indentation) contribute nothing to the value.
* **Coverage** of a cell is the area of all footprints over it divided by its own area: 0 = never
  palpated at that level, 1 = covered once, 2 = two regions overlap there.
* **Levels.** Records are grouped by their desired force (to the nearest mN), lowest first, so a
  session whose ramp changed halfway gets one map per force actually used.
* **Re-analysis.** Stiffness is recomputed from the recorded element force, L0 and dL by Eq. 1
  (E = F L0 / (A dL)) with the chosen source of L0: ``element`` (each element's own onset height, what
  the loop recorded), ``region`` (one thickness per palpated area: the mean over its elements, which
  evens out onset noise), or ``fixed`` (a thickness known otherwise, e.g. from pre-operative imaging).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

from tissue.face import element_offsets_m, stiffness_pa

QUANTITIES = ("pressure_pa", "stiffness_pa", "indentation_m")


class L0Source(enum.Enum):
    ELEMENT = "element"
    REGION = "region"
    FIXED = "fixed"


class StitchError(ValueError):
    """Invalid stitching parameters; the message names the parameter."""


@dataclass(frozen=True)
class StitchParams:
    cell_m: float = 1e-3
    l0_source: L0Source = L0Source.ELEMENT
    l0_fixed_m: float | None = None  # required when l0_source is FIXED
    min_indentation_m: float | None = None  # None: the recording's own contact.min_indentation_m

    def __post_init__(self):
        object.__setattr__(self, "l0_source", _l0_source(self.l0_source))
        cell = self.cell_m
        if not (isinstance(cell, (int, float)) and math.isfinite(cell) and 0.1e-3 <= cell <= 20e-3):
            raise StitchError(f"cell size must be between 0.1 and 20 mm, got {_mm(self.cell_m)}")
        if self.l0_source is L0Source.FIXED:
            if self.l0_fixed_m is None or not (math.isfinite(self.l0_fixed_m) and self.l0_fixed_m > 0):
                raise StitchError(f"L0 source 'fixed' needs a tissue thickness > 0, got {_mm(self.l0_fixed_m)}")
        if self.min_indentation_m is not None and not (math.isfinite(self.min_indentation_m)
                                                       and self.min_indentation_m > 0):
            raise StitchError(f"minimum indentation must be > 0, got {_mm(self.min_indentation_m)}")


def _mm(value) -> str:
    try:
        return f"{float(value) * 1e3:g} mm"
    except (TypeError, ValueError):
        return repr(value)


def _l0_source(value) -> L0Source:
    if isinstance(value, L0Source):
        return value
    try:
        return L0Source(str(value).lower())
    except ValueError:
        known = ", ".join(s.value for s in L0Source)
        raise StitchError(f"unknown L0 source {value!r} (known: {known})") from None


@dataclass(frozen=True)
class Grid:
    x0_m: float  # lower edge of the first cell along x
    y0_m: float
    cell_m: float
    nx: int
    ny: int

    @property
    def shape(self) -> tuple[int, int]:
        return (self.nx, self.ny)

    def x_centres_m(self) -> np.ndarray:
        return self.x0_m + (np.arange(self.nx) + 0.5) * self.cell_m

    def y_centres_m(self) -> np.ndarray:
        return self.y0_m + (np.arange(self.ny) + 0.5) * self.cell_m

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the grid's outer edges."""
        return (self.x0_m, self.x0_m + self.nx * self.cell_m, self.y0_m, self.y0_m + self.ny * self.cell_m)

    def cell_of(self, x_m: float, y_m: float) -> tuple[int, int] | None:
        i = int(math.floor((x_m - self.x0_m) / self.cell_m))
        j = int(math.floor((y_m - self.y0_m) / self.cell_m))
        return (i, j) if 0 <= i < self.nx and 0 <= j < self.ny else None


@dataclass
class LevelMap:
    """The stitched maps at one force level; arrays shaped grid.shape, NaN where there is no value."""

    force_N: float
    index: int  # 0 = lowest force in the session
    records: np.ndarray  # indices of the /levels rows stitched into it
    pressure_pa: np.ndarray
    stiffness_pa: np.ndarray
    indentation_m: np.ndarray  # per-element dL
    coverage: np.ndarray
    tsi_indentation_m: float  # mean TSI indentation depth of its records
    extra: dict[str, np.ndarray] = field(default_factory=dict)  # other per-element values stitched (contrasts)

    def quantity(self, name: str) -> np.ndarray:
        if name == "coverage":
            return self.coverage
        if name in self.extra:
            return self.extra[name]
        if name not in QUANTITIES:
            known = ", ".join((*QUANTITIES, *self.extra, "coverage"))
            raise KeyError(f"unknown map {name!r} (known: {known})")
        return getattr(self, name)


@dataclass
class StitchResult:
    grid: Grid
    params: StitchParams
    levels: list[LevelMap] = field(default_factory=list)
    stiffness_pa: np.ndarray | None = None  # (n_records, rows, cols) the Eq. 1 values used

    def level_forces_N(self) -> list[float]:
        return [lm.force_N for lm in self.levels]

    def covered_fraction(self, index: int = -1, extent_m: tuple[float, float, float, float] | None = None) -> float:
        """Share palpated at that level (the last by default) of ``extent_m`` (x_min, x_max, y_min, y_max: the
        tissue, where it is known), or of the grid's bounding box, which is only what was palpated."""
        if not self.levels:
            return 0.0
        covered = self.levels[index].coverage > 0.5
        if extent_m is None:
            return float(np.count_nonzero(covered)) / covered.size
        x0, x1, y0, y1 = extent_m
        inside = ((self.grid.x_centres_m()[:, None] >= x0) & (self.grid.x_centres_m()[:, None] <= x1)
                  & (self.grid.y_centres_m()[None, :] >= y0) & (self.grid.y_centres_m()[None, :] <= y1))
        cell_area = self.grid.cell_m**2
        return min(1.0, float(np.count_nonzero(covered & inside)) * cell_area / ((x1 - x0) * (y1 - y0)))

    def coverage_text(self, extent_m: tuple[float, float, float, float] | None, index: int = -1) -> str:
        """'72 % of the tissue (72 x 30 mm)' at level ``index`` (the last by default), or, where the tissue's
        size is not recorded, of what was palpated."""
        share = self.covered_fraction(index, extent_m) * 100
        if extent_m is None:
            return f"{share:.0f} % of the palpated extent covered (the tissue's size is not recorded)"
        x0, x1, y0, y1 = extent_m
        return f"{share:.0f} % of the tissue ({(x1 - x0) * 1e3:g} x {(y1 - y0) * 1e3:g} mm) covered"


def recompute_stiffness(levels: np.ndarray, element_area_m2: float, params: StitchParams,
                        default_min_indentation_m: float) -> np.ndarray:
    """Eq. 1 for every element of every record with the chosen L0 source: (n, rows, cols), NaN where not usable."""
    force = levels["element_force_N"]
    dL = levels["dL_m"]
    if params.l0_source is L0Source.ELEMENT:
        L0 = levels["L0_m"]
    elif params.l0_source is L0Source.REGION:
        recorded = levels["L0_m"]
        finite = np.isfinite(recorded)
        count = finite.sum(axis=(1, 2))
        total = np.where(finite, recorded, 0.0).sum(axis=(1, 2))
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
        L0 = np.broadcast_to(mean[:, None, None], recorded.shape)
    else:
        L0 = np.full(dL.shape, float(params.l0_fixed_m))
    min_dL = params.min_indentation_m if params.min_indentation_m is not None else default_min_indentation_m
    return stiffness_pa(force, L0, dL, element_area_m2, min_dL)


# Cells over all force levels: each level keeps half a dozen maps of float64, so 20 million cells is about
# 1 GB. A session's palpated extent is only that large at a cell size nobody can see, or when it is damaged.
MAX_STITCHED_CELLS = 20_000_000


def _grid_for(centres: np.ndarray, pitch_m: float, cell_m: float) -> Grid:
    half = pitch_m / 2.0
    lo = centres.min(axis=0) - half
    hi = centres.max(axis=0) + half
    eps = 1e-9
    x0 = math.floor(lo[0] / cell_m + eps) * cell_m
    y0 = math.floor(lo[1] / cell_m + eps) * cell_m
    nx = max(1, math.ceil((hi[0] - x0) / cell_m - eps))
    ny = max(1, math.ceil((hi[1] - y0) / cell_m - eps))
    return Grid(x0, y0, cell_m, nx, ny)


class _Splat:
    """Overlap weights of square element footprints with the grid's cells, computed once per stitch."""

    def __init__(self, centres: np.ndarray, pitch_m: float, grid: Grid):
        half = pitch_m / 2.0
        k = int(math.ceil(pitch_m / grid.cell_m)) + 1  # most cells a footprint can touch along an axis
        self.n = len(centres)
        self.size = grid.nx * grid.ny
        ix, wx = self._axis(centres[:, 0] - half, centres[:, 0] + half, grid.x0_m, grid.cell_m, grid.nx, k)
        iy, wy = self._axis(centres[:, 1] - half, centres[:, 1] + half, grid.y0_m, grid.cell_m, grid.ny, k)
        self.flat = (ix[:, :, None] * grid.ny + iy[:, None, :]).reshape(self.n, -1)
        self.weight = (wx[:, :, None] * wy[:, None, :]).reshape(self.n, -1) / (grid.cell_m * grid.cell_m)

    @staticmethod
    def _axis(a: np.ndarray, b: np.ndarray, origin: float, cell: float, count: int, k: int):
        first = np.floor((a - origin) / cell + 1e-9).astype(np.int64)
        index = first[:, None] + np.arange(k)[None, :]
        lo = origin + index * cell
        overlap = np.clip(np.minimum(b[:, None], lo + cell) - np.maximum(a[:, None], lo), 0.0, None)
        inside = (index >= 0) & (index < count)
        return np.where(inside, index, 0), np.where(inside, overlap, 0.0)

    def coverage(self, select: np.ndarray) -> np.ndarray:
        return np.bincount(self.flat[select].ravel(), self.weight[select].ravel(), minlength=self.size)

    def mean(self, values: np.ndarray, select: np.ndarray) -> np.ndarray:
        v = values[select]
        finite = np.isfinite(v)
        w = np.where(finite[:, None], self.weight[select], 0.0)
        total_w = np.bincount(self.flat[select].ravel(), w.ravel(), minlength=self.size)
        total = np.bincount(self.flat[select].ravel(), (w * np.where(finite, v, 0.0)[:, None]).ravel(),
                            minlength=self.size)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(total_w > 1e-12, total / np.where(total_w > 1e-12, total_w, 1.0), np.nan)


def level_groups(levels: np.ndarray) -> list[tuple[float, np.ndarray]]:
    """(force_N, record indices) per distinct desired force, lowest first."""
    if not len(levels):
        return []
    keys = np.round(levels["force_desired_N"] * 1000.0).astype(np.int64)
    return [(float(k) / 1000.0, np.flatnonzero(keys == k)) for k in np.unique(keys)]


def stitch(levels: np.ndarray, pitch_m: float, element_area_m2: float, params: StitchParams | None = None,
           default_min_indentation_m: float = 0.2e-3, extra: dict[str, np.ndarray] | None = None) -> StitchResult:
    """Stitch LEVEL_DTYPE records (a session's ``levels``) into one set of maps per force level; ``extra``
    names other per-element values, (records, rows, cols) each, stitched the same way (``LevelMap.extra``)."""
    params = params or StitchParams()
    if not len(levels):
        return StitchResult(Grid(0.0, 0.0, params.cell_m, 0, 0), params, [], np.empty((0,) + _shape(levels)))
    rows, cols = _shape(levels)
    offsets = element_offsets_m(rows, cols, pitch_m)  # (rows, cols, 2)
    tsi = levels["tsi_position_m"][:, :2]
    centres = (tsi[:, None, None, :] + offsets[None]).reshape(-1, 2)  # record-major, then row, then column
    grid = _grid_for(centres, pitch_m, params.cell_m)
    groups = level_groups(levels)
    if grid.nx * grid.ny * len(groups) > MAX_STITCHED_CELLS:
        raise StitchError(f"the palpated areas span {grid.nx * grid.cell_m * 1e3:.0f} x "
                          f"{grid.ny * grid.cell_m * 1e3:.0f} mm: {len(groups)} levels of {grid.nx * grid.ny:,} cells "
                          f"of {_mm(grid.cell_m)} exceed the {MAX_STITCHED_CELLS:,} cells a stitch may use; choose "
                          "larger cells")
    splat = _Splat(centres, pitch_m, grid)
    stiffness = recompute_stiffness(levels, element_area_m2, params, default_min_indentation_m)
    per_element = {
        "pressure_pa": levels["pressure_pa"].reshape(-1),
        "stiffness_pa": stiffness.reshape(-1),
        "indentation_m": levels["dL_m"].reshape(-1),
    }
    n_el = rows * cols
    result = StitchResult(grid, params, [], stiffness)
    for index, (force, records) in enumerate(groups):
        select = (records[:, None] * n_el + np.arange(n_el)[None, :]).ravel()
        maps = {name: splat.mean(values, select).reshape(grid.shape) for name, values in per_element.items()}
        stitched_extra = {name: splat.mean(np.asarray(values, float).reshape(-1), select).reshape(grid.shape)
                          for name, values in (extra or {}).items()}
        depth = levels["indentation_m"][records]
        finite = depth[np.isfinite(depth)]
        result.levels.append(LevelMap(
            force_N=force, index=index, records=records, coverage=splat.coverage(select).reshape(grid.shape),
            tsi_indentation_m=float(finite.mean()) if finite.size else math.nan, extra=stitched_extra, **maps))
    return result


def _shape(levels: np.ndarray) -> tuple[int, int]:
    return tuple(levels.dtype["pressure_pa"].shape)  # type: ignore[return-value]


def stitch_session(session, params: StitchParams | None = None, extra: dict[str, np.ndarray] | None = None
                   ) -> StitchResult:
    """:func:`stitch` with the geometry and settings a :class:`session.reader.Session` recorded."""
    return stitch(session.levels, session.pitch_m, session.element_area_m2, params, session.min_indentation_m,
                  extra)
