"""Tumours in the stitched maps, their position, the force level where they first show, and their depth.

The rule (written down once, here):

* **Candidates at one level.** The map's baseline is its median over every cell with a value (healthy
  tissue covers most of a palpated area). A cell is suspicious when its value rises above the baseline by
  at least ``threshold`` (0.2 = 20 %). Suspicious cells that touch (8-neighbourhood) form a spot; spots
  smaller than ``min_area_m2`` are noise. A spot's position is its centroid weighted by the rise.
* **Across levels.** Spots at successive force levels within ``merge_radius_m`` of each other are the
  same tumour. A tumour's **first level** is the lowest force from which it shows at every higher level
  palpated there (a spot that comes and goes is noise, not a tumour becoming palpable); spots that do not
  last up to the highest force are dropped.
* **Depth**, by the paper's rule (Section IV-B): the TSI indentation depth of the record, at the first
  level, whose footprint holds the tumour (the nearest TSI centre if several overlap).
* The same is done on the stiffness map (Eq. 1, which accounts for how much the tissue was deformed) and,
  separately, on the force map (the tactile pressure alone), to show the paper's contrast between them.
* The reported position is that of the spot with the strongest rise along the tumour's levels.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

from session.stitch import StitchResult, element_offsets_m

SOURCES = ("stiffness", "force")
_MAP_OF = {"stiffness": "stiffness_pa", "force": "pressure_pa"}


class DetectError(ValueError):
    """Invalid detection parameters; the message names the parameter."""


@dataclass(frozen=True)
class DetectParams:
    threshold: float = 0.2  # relative rise over the map's median
    min_area_m2: float = 8e-6  # two sensor elements
    merge_radius_m: float = 4e-3  # half the TSI width

    def __post_init__(self):
        if not (math.isfinite(self.threshold) and 0.0 < self.threshold <= 10.0):
            raise DetectError(f"threshold must be a relative rise within (0, 10] (0.2 = 20 %), got {self.threshold!r}")
        if not (math.isfinite(self.min_area_m2) and self.min_area_m2 >= 0.0):
            raise DetectError(f"minimum spot area must be >= 0 m^2, got {self.min_area_m2!r}")
        if not (math.isfinite(self.merge_radius_m) and self.merge_radius_m > 0.0):
            raise DetectError(f"merge radius must be > 0 m, got {self.merge_radius_m!r}")


@dataclass(frozen=True)
class Spot:
    level_index: int
    force_N: float
    x_m: float
    y_m: float
    area_m2: float
    peak_rise: float  # (max value - baseline) / baseline


@dataclass(frozen=True)
class Tumour:
    x_m: float
    y_m: float
    depth_m: float  # TSI indentation at the first level (NaN if no record there holds the position)
    first_level_N: float
    source: str  # "stiffness" | "force"
    peak_rise: float
    area_m2: float
    levels_N: tuple[float, ...]  # every force level it shows at, from the first

    def to_json(self) -> dict:
        d = asdict(self)
        d["levels_N"] = list(self.levels_N)
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


def spots(values: np.ndarray, stitched: StitchResult, level_index: int, params: DetectParams) -> list[Spot]:
    """The suspicious spots of one map (shaped like the grid) at one level."""
    grid = stitched.grid
    finite = np.isfinite(values)
    if not finite.any():
        return []
    baseline = float(np.median(values[finite]))
    if not baseline > 0:
        return []
    rise = np.where(finite, values / baseline - 1.0, -np.inf)
    labels, n = ndimage.label(rise >= params.threshold, structure=np.ones((3, 3), dtype=bool))
    if n == 0:
        return []
    cell_area = grid.cell_m * grid.cell_m
    xs, ys = grid.x_centres_m(), grid.y_centres_m()
    out = []
    force = stitched.levels[level_index].force_N
    for label in range(1, n + 1):
        ii, jj = np.nonzero(labels == label)
        area = len(ii) * cell_area
        if area + 1e-15 < params.min_area_m2:
            continue
        w = rise[ii, jj]
        x, y = float(np.sum(w * xs[ii]) / np.sum(w)), float(np.sum(w * ys[jj]) / np.sum(w))
        out.append(Spot(level_index, force, x, y, area, float(w.max())))
    return out


def _depth_at(levels: np.ndarray, records: np.ndarray, x_m: float, y_m: float, pitch_m: float) -> float:
    """Indentation of the record (among ``records``) whose TSI footprint holds (x, y), nearest centre first."""
    rows, cols = levels.dtype["pressure_pa"].shape
    offsets = element_offsets_m(rows, cols, pitch_m)
    half_x = offsets[..., 0].max() + pitch_m / 2
    half_y = offsets[..., 1].max() + pitch_m / 2
    pos = levels["tsi_position_m"][records]
    dx, dy = x_m - pos[:, 0], y_m - pos[:, 1]
    inside = (np.abs(dx) <= half_x) & (np.abs(dy) <= half_y)
    if not inside.any():
        return math.nan
    candidates = np.flatnonzero(inside)
    best = candidates[np.argmin(np.hypot(dx[candidates], dy[candidates]))]
    return float(levels["indentation_m"][records[best]])


def detect(stitched: StitchResult, levels: np.ndarray, pitch_m: float, source: str = "stiffness",
           params: DetectParams | None = None) -> list[Tumour]:
    """Tumours in the ``source`` map ("stiffness" or "force") of a stitched session, ordered along x."""
    if source not in SOURCES:
        raise DetectError(f"unknown map {source!r} to detect in (known: {', '.join(SOURCES)})")
    params = params or DetectParams()
    tracks: list[list[Spot]] = []
    for lm in stitched.levels:
        found = spots(lm.quantity(_MAP_OF[source]), stitched, lm.index, params)
        claimed: set[int] = set()
        for spot in sorted(found, key=lambda s: -s.peak_rise):
            best, best_d = None, params.merge_radius_m
            for t, track in enumerate(tracks):
                last = track[-1]
                d = math.hypot(spot.x_m - last.x_m, spot.y_m - last.y_m)
                if t not in claimed and last.level_index < lm.index and d <= best_d:
                    best, best_d = t, d
            if best is None:
                tracks.append([spot])
                claimed.add(len(tracks) - 1)
            else:
                tracks[best].append(spot)
                claimed.add(best)

    tumours = []
    for track in tracks:
        top = _highest_level_covering(stitched, track[-1].x_m, track[-1].y_m)
        # the unbroken run of levels that ends at the highest level palpated at this place
        by_level = {s.level_index: s for s in track}
        if top is None or top not in by_level:
            continue
        first = top
        while first - 1 in by_level:
            first -= 1
        run = [by_level[k] for k in range(first, top + 1)]
        strongest = max(run, key=lambda s: s.peak_rise)
        first_map = stitched.levels[first]
        depth = _depth_at(levels, first_map.records, strongest.x_m, strongest.y_m, pitch_m)
        tumours.append(Tumour(x_m=strongest.x_m, y_m=strongest.y_m, depth_m=depth, first_level_N=first_map.force_N,
                              source=source, peak_rise=strongest.peak_rise, area_m2=strongest.area_m2,
                              levels_N=tuple(stitched.levels[s.level_index].force_N for s in run)))
    return sorted(tumours, key=lambda t: (t.x_m, t.y_m))


def _highest_level_covering(stitched: StitchResult, x_m: float, y_m: float) -> int | None:
    cell = stitched.grid.cell_of(x_m, y_m)
    if cell is None:
        return None
    for lm in reversed(stitched.levels):
        if lm.coverage[cell] > 0.5:
            return lm.index
    return None


def detect_session(session, stitched: StitchResult, params: DetectParams | None = None) -> list[Tumour]:
    """Both sources, stiffness first."""
    return [t for source in SOURCES for t in detect(stitched, session.levels, session.pitch_m, source, params)]


@dataclass(frozen=True)
class TruthMatch:
    """One ground-truth tumour of a simulated phantom against what one map found."""

    truth_index: int
    x_m: float
    y_m: float
    depth_m: float
    source: str
    found: bool
    error_xy_m: float  # NaN when not found
    depth_estimate_m: float
    first_level_N: float
    detection: int  # index of the matched detection in the list given, -1 when not found
    palpated: bool  # whether the session palpated the place at all (True when not known)


def match_ground_truth(tumours: list[Tumour], ground_truth: list[dict], match_radius_m: float = 6e-3,
                       stitched: StitchResult | None = None) -> tuple[list[TruthMatch], dict[str, int]]:
    """Pair each true tumour with the nearest detection (per source) within ``match_radius_m``.

    Returns the matches and, per source, the number of detections that matched no true tumour (false
    positives). With ``stitched``, a true tumour nobody palpated over is marked ``palpated=False``.
    """
    matches: list[TruthMatch] = []
    false_positives: dict[str, int] = {}
    for source in SOURCES:
        found = [(k, t) for k, t in enumerate(tumours) if t.source == source]
        used: set[int] = set()
        for i, truth in enumerate(ground_truth):
            tx, ty = float(truth["x_m"]), float(truth["y_m"])
            best, best_d = None, match_radius_m
            for k, t in found:
                d = math.hypot(t.x_m - tx, t.y_m - ty)
                if k not in used and d <= best_d:
                    best, best_d = k, d
            depth = float(truth.get("depth_m", math.nan))
            palpated = stitched is None or _highest_level_covering(stitched, tx, ty) is not None
            if best is None:
                matches.append(TruthMatch(i, tx, ty, depth, source, False, math.nan, math.nan, math.nan, -1, palpated))
            else:
                used.add(best)
                t = tumours[best]
                matches.append(TruthMatch(i, tx, ty, depth, source, True, best_d, t.depth_m, t.first_level_N, best,
                                          palpated))
        false_positives[source] = len(found) - len(used)
    return matches, false_positives
