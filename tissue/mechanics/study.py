"""A noise-free palpation study of a phantom, as the paper's flowchart runs it (Section III-B, Fig. 4).

For every region and force level the face is lowered until the total force equals the level; each
element's contact onset is the face height at which it first carries force, and from it follow, as in
control/analysis.py, the element's L0 (onset height above the table), its indentation dL = onset - z,
its stiffness by Eq. 1 (E = F L0 / (A dL)), and the TSI indentation (mean dL over elements in contact).
These are the quantities the paper reports; computing them straight from the tissue model, without a
robot, a sensor or noise, isolates what the physics predicts.

A tumour's *contrast* in a map is the mean over the elements within one tumour radius of it divided by
the mean over the same elements when the same phantom without its tumours is palpated to the same force
level, minus one: the pattern a rigid face produces on its own (edge peaks, bumps, the phantom's free
ends) cancels, and what is left is the tumour.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from tissue.face import Face, stiffness_pa
from tissue.phantom import Phantom, parse_phantom

MIN_INDENTATION_M = 0.2e-3  # as ContactSettings.min_indentation_m: below it Eq. 1 is noise-dominated


@dataclass
class RegionLevel:
    region: tuple[float, float]
    force_N: float
    face_height_m: float
    forces_N: np.ndarray  # (rows, cols)
    onset_m: np.ndarray  # (rows, cols), NaN for elements not touching
    indentation_m: np.ndarray  # dL, NaN where not touching
    stiffness_pa: np.ndarray  # Eq. 1, NaN where not touching or dL < MIN_INDENTATION_M

    @property
    def tsi_indentation_m(self) -> float:
        touching = ~np.isnan(self.indentation_m)
        return float(self.indentation_m[touching].mean()) if touching.any() else float("nan")


def element_onsets(tissue, x_m: float, y_m: float, step_m: float = 5e-6, depth_m: float = 0.02) -> np.ndarray:
    """Face height at which each element first carries force (NaN if not within ``depth_m`` of first touch)."""
    sensor: Face = getattr(tissue, "sensor", Face())
    off = sensor.element_offsets_m()
    ph = tissue.phantom
    top = float(ph.surface_height_m(np.clip(x_m + off[..., 0], 0, ph.length_m),
                                    np.clip(y_m + off[..., 1], 0, ph.width_m)).max()) + 1e-3
    onset = np.full(sensor.shape, np.nan)
    for z in np.arange(top, top - depth_m - 1e-3, -step_m):
        touching = tissue.element_forces_N(x_m, y_m, z) > 0
        new = touching & np.isnan(onset)
        onset[new] = z + step_m / 2  # first touch lies within the last step
        if not np.isnan(onset).any():
            break
    return onset


def height_for_force(tissue, x_m: float, y_m: float, force_N: float, tol_m: float = 1e-14) -> float:
    """Face height at which the total force reaches ``force_N``, to ``tol_m`` (bisection: the force falls
    monotonically as the face rises); NaN if even a face down at the table does not push that hard."""
    def total(z_m: float) -> float:
        return float(tissue.element_forces_N(x_m, y_m, z_m).sum())

    lo = 0.0
    if not total(lo) >= force_N:  # a NaN force too
        return float("nan")
    hi = float(tissue.phantom.surface_height_m(x_m, y_m)) + 0.02
    while total(hi) > max(force_N, 0.0):  # the surface under the face's edge may stand higher than at its centre
        hi += 0.01
    while hi - lo > tol_m:
        mid = 0.5 * (lo + hi)
        if total(mid) >= force_N:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def palpate(tissue, levels_N, regions=None) -> list[list[RegionLevel]]:
    """``result[r][k]``: region r (default: the phantom's regions) at force level k."""
    sensor: Face = getattr(tissue, "sensor", Face())
    regions = regions if regions is not None else tissue.phantom.palpation_regions()
    out = []
    for x, y in regions:
        onset = element_onsets(tissue, x, y)
        rows = []
        for level in levels_N:
            z = height_for_force(tissue, x, y, level)
            if np.isnan(z):
                nan = np.full(sensor.shape, np.nan)
                rows.append(RegionLevel((x, y), float(level), z, nan, onset, nan, nan))
                continue
            forces = tissue.element_forces_N(x, y, z)
            touching = (forces > 0) & ~np.isnan(onset)
            dl = np.where(touching, onset - z, np.nan)
            stiffness = stiffness_pa(forces, onset, dl, sensor.element_area_m2, MIN_INDENTATION_M)
            rows.append(RegionLevel((x, y), float(level), z, forces, onset, dl, stiffness))
        out.append(rows)
    return out


def tumour_standout(study: list[list[RegionLevel]], level_index: int, tumours: list[dict], which: int, field: str,
                    sensor: Face | None = None) -> float:
    """How a tumour looks to an operator with no reference: the mean of the ``field`` map over the
    elements within a tumour radius of it, over the 95th percentile of the whole stitched map away
    from every tumour (elements more than 1.5 diameters from all of them). Above 1 the tumour is
    brighter than nearly everything tumour-free, bumps and the face's edge peaks included."""
    sensor = sensor or Face()
    off = sensor.element_offsets_m()
    patch, rest = [], []
    for region in study:
        level = region[level_index]
        values = getattr(level, field)
        ex, ey = level.region[0] + off[..., 0], level.region[1] + off[..., 1]
        dist = [np.hypot(ex - t["x_m"], ey - t["y_m"]) for t in tumours]
        patch.append(values[dist[which] <= tumours[which]["diameter_m"] / 2])
        far = np.all([d > 1.5 * t["diameter_m"] for d, t in zip(dist, tumours)], axis=0)
        rest.append(values[far])
    patch_values, rest_values = np.concatenate(patch), np.concatenate(rest)
    patch_values, rest_values = patch_values[~np.isnan(patch_values)], rest_values[~np.isnan(rest_values)]
    if len(patch_values) == 0 or len(rest_values) == 0:
        return float("nan")
    return float(patch_values.mean() / np.percentile(rest_values, 95))


def without_inclusions(phantom: Phantom) -> Phantom:
    """The same phantom with its inclusions taken out (the reference for contrasts)."""
    data = copy.deepcopy(phantom.source)
    data["phantom"].pop("inclusions", None)
    data["phantom"]["name"] = f"{phantom.name}-without-inclusions"
    return parse_phantom(data, f"{phantom.name} without inclusions")


def tumour_contrast(study: list[list[RegionLevel]], reference: list[list[RegionLevel]], level_index: int,
                    tumour: dict, field: str, sensor: Face | None = None) -> tuple[float, float]:
    """(relative contrast, absolute excess) of one tumour in the ``field`` map ("forces_N" or
    "stiffness_pa") at one level, against the tumour-free ``reference`` study."""
    sensor = sensor or Face()
    centres = [r[level_index].region for r in study]
    home = int(np.argmin([abs(cx - tumour["x_m"]) + abs(cy - tumour["y_m"]) for cx, cy in centres]))
    cx, cy = centres[home]
    off = sensor.element_offsets_m()
    near = np.hypot(cx + off[..., 0] - tumour["x_m"], cy + off[..., 1] - tumour["y_m"]) <= tumour["diameter_m"] / 2
    signal = getattr(study[home][level_index], field)[near]
    base = getattr(reference[home][level_index], field)[near]
    both = ~np.isnan(signal) & ~np.isnan(base)
    if not both.any() or base[both].mean() <= 0:  # the reference does not touch there
        return float("nan"), float("nan")
    return float(signal[both].mean() / base[both].mean() - 1.0), float(signal[both].mean() - base[both].mean())
