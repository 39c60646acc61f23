"""Tumours in a session's contrast, their position, the force level where they first show, and their depth.

The rule (written down once, here), applied to the stiffness map and, separately, to the force map (their
contrasts are made by :mod:`session.flatfield`):

* **Evidence.** In each level record (an area at a force), each element's contrast is weighed against its
  uncertainty with a matched filter: for a blob of Gaussian profile of width ``w`` centred on element e,
  ``z(e) = sum_j K_ej c_j / s_j^2 / sqrt(sum_j K_ej^2 / s_j^2)``, the likelihood-ratio statistic of a blob
  of unknown height against none, over the elements in contact. Blobs of every width in
  ``kernel_widths_m`` are tried and the largest statistic kept. Where the expected pattern's uncertainty
  is partly shared between elements (``Contrast.modes``: the tissue going on beyond the palpated end, a
  surface rebuilt a little too low under one element of a bump's flank), the blob's spread counts their
  covariance where that makes it larger (:func:`evidence`).
* **Threshold.** Healthy tissue gives independent standard normal ``c_j / s_j``; the threshold is the
  value the largest statistic over one area's face exceeds with probability ``false_alarm_per_area``
  (found once by simulating healthy faces), so each palpated area raises a false alarm that often.
* **Spots.** Every local maximum of a blob width's statistic (over its 8 neighbours) that passes the
  threshold is a spot, so two tumours under one face stay two (the widest blob may sum both into one
  maximum; a narrower one does not); its score is the largest statistic there, its first position the
  precision-weighted centroid of the positive contrast around it, in the tissue frame (TSI position +
  element offset).
* **Across areas and levels.** Spots at the same force level within ``merge_radius_m`` of each other are one
  (areas may overlap), and so is a spot at the edge of its face within that radius plus half the face's
  width of a stronger one (it sees only the near side of what raised it); spots at successive levels within
  that radius are the same tumour. A tumour's
  **first level** is the lowest force from which it shows at every higher level palpated at its position (a
  spot that comes and goes is noise, not a tumour becoming palpable); one that does not last up to the
  highest force palpated there is dropped. Its score is that of its strongest spot; its position is where a
  Gaussian blob fitted (weighted by precision) to the contrast of every element of every area within
  ``fit_radius_m`` of its strongest spot inside its face (of its strongest if every spot reaches an edge),
  at that spot's level, peaks: the areas on both sides of a seam each see part of a tumour under it, and
  only together do they show where it is.
* **Explained away** (:func:`explained_away`, when a forward model is given): a weaker tumour within a
  stronger one's reach is kept only if it still passes the threshold over what the stronger one's own
  mechanics makes of its face (its far field reaches the tissue's far side, and the faces beside it), or, on
  the stiffness map, if that makes less than half of its contrast (a tumour of its own the far field tipped
  under it). Those
  kept are placed by what stands out over the others' spheres (a far field's slope pulls a blob's peak
  towards the tumour that made it, the stronger one's as well as the weaker one's).
* **Depth**, by the paper's rule (Section IV-B): the TSI indentation depth of the record, at the first
  level, whose footprint holds the tumour (the nearest TSI centre if several do). The model-based estimate
  with its interval is added by :mod:`session.depth`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy import ndimage

from session.flatfield import ACCURACY, MAPS, Contrast
from session.stitch import level_groups
from tissue.face import element_offsets_m
from tissue.mechanics.progress import Progress

SOURCES = MAPS
_NULL_DRAWS = 20000  # healthy faces simulated to set the threshold: its quantile is good to ~0.1 in z


class DetectError(ValueError):
    """Invalid detection parameters; the message names the parameter."""


@dataclass(frozen=True)
class DetectParams:
    # Chance that a palpated area of healthy tissue raises a spot. A phantom is palpated in about ten areas,
    # and the study's goal is at most 0.1 false positives per phantom: at 1 % per area noise alone would
    # spend nearly all of that, and the rebuilt surface's own errors (a bump's foot or end) spend more. At
    # 0.1 % (z 4.15 over one face, 3.5 at 1 %), the spots detected in 80 study phantoms of two seeds fell
    # from 13 false ones to 8 and 40 phantoms of a third, not looked at before, from 11 to 5, with the
    # same tumours found within 2 mm (103 of 118, 44 of 55); a 10 mm-deep one seen at z 3.8 is lost.
    false_alarm_per_area: float = 0.001
    accuracy: float = ACCURACY  # the least relative scatter healthy tissue is allowed (repeatability of a reading)
    merge_radius_m: float = 4e-3  # half the TSI's width: one tumour seen twice is closer than this
    fit_radius_m: float = 6e-3  # contrast this close to a spot places the tumour
    kernel_widths_m: tuple[float, ...] = (2e-3, 4e-3)  # blob widths (Gaussian sigma) the matched filter tries

    def __post_init__(self):
        a = self.false_alarm_per_area
        if not (isinstance(a, (int, float)) and math.isfinite(a) and 1e-6 <= a <= 0.5):
            raise DetectError(f"false-alarm rate per area must be within [1e-6, 0.5], got {a!r}")
        if not (isinstance(self.accuracy, (int, float)) and math.isfinite(self.accuracy)
                and 0.001 <= self.accuracy <= 0.5):
            raise DetectError(f"accuracy must be a relative scatter within [0.001, 0.5], got {self.accuracy!r}")
        if not (math.isfinite(self.merge_radius_m) and 0.0 < self.merge_radius_m <= 0.05):
            raise DetectError(f"merge radius must be within (0, 50] mm, got {self.merge_radius_m * 1e3:g} mm")
        if not (math.isfinite(self.fit_radius_m) and 2e-3 <= self.fit_radius_m <= 0.05):
            raise DetectError(f"fit radius must be within [2, 50] mm, got {self.fit_radius_m * 1e3:g} mm")
        widths = tuple(float(w) for w in self.kernel_widths_m)
        if not widths or not all(math.isfinite(w) and 0.5e-3 <= w <= 20e-3 for w in widths):
            given = widths_text_mm(widths) or "none"
            raise DetectError(f"blob widths must be one or more within [0.5, 20] mm, got {given}")
        object.__setattr__(self, "kernel_widths_m", widths)


def widths_text_mm(widths_m: tuple[float, ...]) -> str:
    """Blob widths as the command line and the reviewer write them: mm, comma-separated."""
    return ", ".join(f"{w * 1e3:g}" for w in widths_m)


def widths_from_mm(text: str) -> tuple[float, ...]:
    """Blob widths in m from their text in mm, comma-separated (their range is DetectParams' to check);
    raises DetectError."""
    try:
        return tuple(float(w) * 1e-3 for w in text.split(","))
    except ValueError:
        raise DetectError(f"{text!r} is not a comma-separated list of widths in mm") from None


@dataclass(frozen=True)
class DepthParams:
    """The model-based depth's own parameters (``session.depth``). Together they set how wide the
    depth's interval is."""

    # The forward model's error in a tumour's predicted contrast, relative, each element's its own: the
    # mesh, a tumour off the array's middle, the gain spread the flat field left. Fitted again once the error
    # an element's levels share was counted (session.depth), on the validation study's seed alone, in both
    # worlds (14 + 11 tumours found), by how far the truths fell from the estimate in interval widths: 0.10,
    # 0.15, 0.20 and 0.25 put the median truth at 0.50, 0.40, 0.42 and 0.30 half-widths in the ideal world
    # and 0.62, 0.59, 0.59 and 0.63 in the realistic one, against 0.67 for calibrated intervals. Checked on
    # three held-out seeds, realistic (28 tumours): median error 1.22 -> 0.62 mm, intervals covering 92.9 ->
    # 89.3 %; ideal: docs/validation.md, "The model's own error, fitted again".
    model_error: float = 0.10
    # The part of that error all the tumour's elements share, relative: one scale on everything predicted
    # (the flat field's own scale, the sensor's cover, how much the press stiffened the tissue). 0.2 with
    # a model error of 0.25: the 90 % intervals covered 89 % of the truths found in two studies (s777, s4711,
    # 82 tumours), median 3.1 mm wide, before the levels' shared error was counted. Tried again with it, on the
    # validation seed with model errors of 0.15 and 0.20: 0.1 read the ideal world's depths closer (median
    # error 0.41 -> 0.33, 0.43 -> 0.32 mm) and the realistic one's further (0.70 -> 0.86, 0.69 -> 0.81 mm).
    scale_error: float = 0.2
    # How unsure the model is of the tissue's law, relative: how fast a tumour's contrast grows as the press
    # thins the tissue over it is taken anywhere from 1 - law_spread to 1 + law_spread times what the reduced
    # finite-strain model gives, and marginalised (session.depth; 1 reaches small strain, where it does not
    # grow). Real silicone follows neither that model's law nor small strain; 0 trusts the model's law.
    law_spread: float = 0.5

    def __post_init__(self):
        for name, e, least, most in (("model error", self.model_error, 0.01, 2.0),
                                     ("scale error", self.scale_error, 0.0, 2.0),
                                     ("law spread", self.law_spread, 0.0, 1.0)):
            if not (isinstance(e, (int, float)) and math.isfinite(e) and least <= e <= most):
                raise DetectError(f"depth {name} must be a relative error within [{least:g}, {most:g}], got {e!r}")


@dataclass(frozen=True)
class Spot:
    record: int  # its /levels row
    level_index: int  # 0 = lowest force in the session
    force_N: float
    x_m: float
    y_m: float
    score: float  # largest matched-filter statistic
    contrast: float  # largest contrast among its elements
    elements: int
    # the edges of its face it reaches, as outward directions (x, y): what raised it may lie beyond them,
    # under a neighbouring area
    outward: tuple[tuple[int, int], ...]
    # where, of the contrast its statistic summed, the largest is (the widest blob may peak rows away from it)
    strongest_xy_m: tuple[float, float] = (math.nan, math.nan)

    @property
    def at_edge(self) -> bool:
        return bool(self.outward)


@dataclass(frozen=True)
class Tumour:
    x_m: float
    y_m: float
    depth_m: float  # the paper's rule: TSI indentation at the first level (NaN if no record there holds it)
    first_level_N: float
    source: str  # "stiffness" | "force"
    score: float  # the strongest spot's statistic (a z score: how many standard deviations of healthy tissue)
    contrast: float  # its largest contrast (0.3 = 30 % harder than homogeneous tissue)
    levels_N: tuple[float, ...]  # every force level it shows at, from the first
    depth_model_m: float = math.nan  # model-based estimate (session.depth), with its 90 % interval
    depth_low_m: float = math.nan
    depth_high_m: float = math.nan
    spots: tuple[Spot, ...] = field(default=(), repr=False, compare=False)

    def to_json(self) -> dict:
        d = {k: v for k, v in asdict(self).items() if k != "spots"}
        d["levels_N"] = list(self.levels_N)
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}

    def with_depth_model(self, depth_m: float, low_m: float, high_m: float) -> Tumour:
        return replace(self, depth_model_m=depth_m, depth_low_m=low_m, depth_high_m=high_m)


def _kernels(shape: tuple[int, int], pitch_m: float, widths_m: tuple[float, ...]) -> np.ndarray:
    """(widths, n, n) Gaussian weights between the n elements of a face."""
    offsets = element_offsets_m(shape[0], shape[1], pitch_m).reshape(-1, 2)
    d2 = ((offsets[:, None, :] - offsets[None, :, :]) ** 2).sum(axis=-1)
    return np.stack([np.exp(-0.5 * d2 / (w * w)) for w in widths_m])


def evidence(contrast: np.ndarray, sigma: np.ndarray, pitch_m: float, widths_m: tuple[float, ...],
             modes: np.ndarray | None = None) -> np.ndarray:
    """The matched-filter statistic centred on each element, the largest over the blob widths (see the
    module docstring); NaN off contact. :func:`evidence_by_width` gives each width's."""
    return np.max(evidence_by_width(contrast, sigma, pitch_m, widths_m, modes), axis=0)


def evidence_by_width(contrast: np.ndarray, sigma: np.ndarray, pitch_m: float, widths_m: tuple[float, ...],
                      modes: np.ndarray | None = None) -> np.ndarray:
    """(widths, rows, cols): the matched-filter statistic of a blob of each width centred on each element;
    NaN off contact.

    ``modes`` (m, rows, cols): uncertainties of the expected pattern shared between elements, one standard
    deviation each and included in ``sigma``. Where their parts under a blob add up (the face's end half
    reading high together if the tissue goes on beyond the palpated end), the blob's sum varies by more
    than independent errors would make it, and its statistic is divided by that larger spread. Where they
    cancel (a surface a little higher under one element loads it more and its neighbours less) it is not
    made surer: that would trust the model's shape of its own error more than its size."""
    shape = contrast.shape
    kernels = _kernels(shape, pitch_m, widths_m)
    used = np.isfinite(contrast.ravel()) & np.isfinite(sigma.ravel()) & (sigma.ravel() > 0)
    out = np.full((len(kernels), contrast.size), -np.inf)
    if not used.any():
        return np.full((len(kernels), *shape), np.nan)
    precision = np.where(used, 1.0 / np.where(used, sigma.ravel(), 1.0) ** 2, 0.0)
    weighted = np.where(used, contrast.ravel(), 0.0) * precision
    shared = None
    if modes is not None and len(modes):
        shared = np.where(used, modes.reshape(len(modes), -1), 0.0) * precision  # (m, n): each mode, weighted
        own = (shared ** 2 / np.where(used, precision, 1.0)).sum(axis=0)  # their diagonal, in those weights
    for n, k in enumerate(kernels):
        num = k @ weighted
        variance = (k * k) @ precision
        if shared is not None:
            # the weighted sum's variance with the modes' whole covariance instead of their diagonal alone
            variance = np.maximum(variance, variance + ((shared @ k.T) ** 2).sum(axis=0) - (k * k) @ own)
        den = np.sqrt(variance)
        out[n] = np.divide(num, den, out=np.full(num.shape, -np.inf), where=den > 0)
    return np.where(used, out, np.nan).reshape(len(kernels), *shape)


@functools.lru_cache(maxsize=32)
def threshold(false_alarm: float, shape: tuple[int, int], pitch_m: float, widths_m: tuple[float, ...]) -> float:
    """The statistic healthy tissue's largest value over one face exceeds with probability ``false_alarm``."""
    kernels = _kernels(shape, pitch_m, widths_m)
    rng = np.random.default_rng(20240501)
    null = rng.standard_normal((_NULL_DRAWS, shape[0] * shape[1]))
    largest = np.full(_NULL_DRAWS, -np.inf)
    for k in kernels:
        largest = np.maximum(largest, (null @ k.T / np.sqrt((k * k).sum(axis=1))).max(axis=1))
    return float(np.quantile(largest, 1.0 - false_alarm))


def significant_peaks(z: np.ndarray, limit: float, contrast: np.ndarray) -> np.ndarray:
    """Where the statistic of some blob width (``z``: (widths, rows, cols), or one width's (rows, cols))
    passes ``limit`` at a local maximum over its 8 neighbours, among the elements that read harder than
    expected: a boolean mask of the face.

    Each width's maxima count, so two tumours under one face stay two: the widest blob centred between a
    strong tumour and a weaker one 8 mm beside it sums both and has one maximum, on the strong one, while
    the narrower blob still has one on each (s7043-0002: a 1.9 mm-deep tumour at the phantom's end first
    showed at 4 N, and was given a depth of 10 mm, for its 1-3 N maxima were hidden under its neighbour's).

    A tumour only ever stiffens the tissue, so no blob is centred where the contrast is not positive. The
    widest blob centred on an element the flat field knows little of (the side of a face partly off a
    ridge) sums its neighbours' contrast, and a far field rising across the face towards a strong tumour
    peaked there, on the far edge, at contrast -0.21 and z 9, and was reported as a tumour of its own."""
    finite = np.nan_to_num(z.reshape(-1, *z.shape[-2:]), nan=-np.inf)
    peaks = (finite > limit) & (finite >= ndimage.maximum_filter(finite, size=(1, 3, 3), mode="constant",
                                                                 cval=-np.inf))
    candidates = peaks.any(axis=0) & (np.nan_to_num(contrast, nan=0.0) > 0)
    # One blob seen at two widths may peak on neighbouring elements: the stronger one stands for both (two
    # spots a row apart reach 0.7 mm further, enough to join the next tumour's edge spot to this one).
    score = finite.max(axis=0)
    out = np.zeros_like(candidates)
    for flat in sorted(np.flatnonzero(candidates), key=lambda k: -score.flat[k]):
        i, j = np.unravel_index(flat, candidates.shape)
        if not out[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2].any():
            out[i, j] = True
    return out


def spots(levels: np.ndarray, contrast: Contrast, pitch_m: float, params: DetectParams) -> list[Spot]:
    """The significant spots of every level record."""
    shape = levels.dtype["pressure_pa"].shape
    limit = threshold(params.false_alarm_per_area, tuple(shape), pitch_m, params.kernel_widths_m)
    offsets = element_offsets_m(shape[0], shape[1], pitch_m)
    level_of = np.empty(len(levels), dtype=int)
    force_of = np.empty(len(levels))
    for index, (force, records) in enumerate(level_groups(levels)):
        level_of[records] = index
        force_of[records] = force
    out = []
    for r in range(len(levels)):
        c, s = contrast.contrast[r], contrast.sigma[r]
        by_width = evidence_by_width(c, s, pitch_m, params.kernel_widths_m,
                                     None if contrast.modes is None else contrast.modes[r])
        z = np.max(by_width, axis=0)
        peaks = significant_peaks(by_width, limit, c)
        tsi = levels["tsi_position_m"][r]
        near = np.hypot(offsets[..., 0][None, None] - offsets[..., 0][..., None, None],
                        offsets[..., 1][None, None] - offsets[..., 1][..., None, None])
        for i, j in zip(*np.nonzero(peaks)):
            around = near[i, j] <= 1.5 * pitch_m
            weight = np.where(around, np.clip(np.nan_to_num(c), 0.0, None) / np.nan_to_num(s, nan=np.inf) ** 2, 0.0)
            if not weight.sum() > 0:
                weight = (near[i, j] == 0).astype(float)
            x = float(tsi[0] + (weight * offsets[..., 0]).sum() / weight.sum())
            y = float(tsi[1] + (weight * offsets[..., 1]).sum() / weight.sum())
            # What raised it may lie beyond the face if the statistic peaks on the face's edge or the contrast
            # it summed is largest there (a tumour under the next area shows here as a rise towards the edge;
            # the widest blob tried may peak a row or two inside it).
            summed = near[i, j] <= max(1.5 * pitch_m, max(params.kernel_widths_m))
            si, sj = np.unravel_index(np.nanargmax(np.where(summed, c, -np.inf)), shape)
            outward = _edges_reached((i, si), (j, sj), shape)
            strongest = (float(tsi[0] + offsets[si, sj, 0]), float(tsi[1] + offsets[si, sj, 1]))
            out.append(Spot(r, int(level_of[r]), float(force_of[r]), x, y, float(z[i, j]), float(np.nanmax(c[around])),
                            int(around.sum()), outward, strongest))
    return out


def _edges_reached(rows: tuple[int, ...], cols: tuple[int, ...], shape: tuple[int, int]) -> tuple[tuple[int, int], ...]:
    """The edges of the face (outward directions along x and y) that the elements at ``rows`` and ``cols``
    (indices along each axis) lie on."""
    edges = set()
    for axis, (indices, last) in enumerate(((rows, shape[0] - 1), (cols, shape[1] - 1))):
        for index, outward in ((0, -1), (last, 1)):
            if index in indices:
                edges.add((outward, 0) if axis == 0 else (0, outward))
    return tuple(sorted(edges))


# What a tumour's own mechanics does to the rest of its faces: (records) -> (contrast, its uncertainty), each
# (len(records), rows, cols), or None when it cannot be said
Signature = Callable[[Tumour, np.ndarray], "tuple[np.ndarray, np.ndarray] | None"]


# What of a weaker spot's contrast the stronger tumours' spheres must make for it to be theirs (explained_away)
EXPLAINED_SHARE = 0.5


def explained_away(tumours: list[Tumour], levels: np.ndarray, contrast: Contrast, pitch_m: float,
                   params: DetectParams, signature: Signature, progress: Progress | None = None) -> list[Tumour]:
    """The tumours of one map less those a stronger one explains: a stiff sphere under a rigid face moves
    load across the whole face (a shallow one 11 mm from one side of the tissue lowers the near side's
    elements by 0.1 and raises the far side's by 0.07, where the flat field expects homogeneous tissue), and
    that far field passes the threshold as a spot of its own, in the tumour's own faces and in the faces
    beside them (where the stronger one raised no spot of its own). Strongest first, each tumour is tested
    again at its highest level: its contrast there over what the stronger ones' best-fitting spheres make
    of those faces (``signature``: zero where a face lies beyond a sphere's reach), the model's error added
    to its uncertainty. It stays if a spot of it still passes the threshold there, if (stiffness map only:
    the spheres are fitted to its contrast) the spheres make less than :data:`EXPLAINED_SHARE` of the spot's
    contrast at its peak, or if a stronger one that reaches it has no signature to explain it with. Those
    that stay are then placed over one another (:func:`_placed_over_each_other`). ``progress(fraction,
    message)`` before each tumour is tested and placed."""
    limit = threshold(params.false_alarm_per_area, tuple(levels.dtype["pressure_pa"].shape), pitch_m,
                      params.kernel_widths_m)
    offsets = element_offsets_m(*levels.dtype["pressure_pa"].shape, pitch_m)
    said = _Said(signature)
    kept: list[Tumour] = []
    steps = _Steps(progress, len(tumours) * (1 + _placement_sweeps(tumours)))
    for n, t in enumerate(sorted(tumours, key=lambda t: -t.score)):
        steps(f"tumour {n + 1} of {len(tumours)}")
        top = [spot for spot in t.spots if spot.force_N == t.levels_N[-1]]
        if not kept:
            kept.append(t)
            continue
        survives = False
        for spot, by_kept in zip(top, said(kept, [spot.record for spot in top])):
            if any(s is None for s in by_kept):
                survives = True
                break
            r = spot.record
            residual, sigma = _over(contrast, r, by_kept)
            z = evidence(residual, sigma, pitch_m, params.kernel_widths_m,
                         None if contrast.modes is None else contrast.modes[r])
            tsi = levels["tsi_position_m"][r]
            around = np.hypot(tsi[0] + offsets[..., 0] - spot.x_m, tsi[1] + offsets[..., 1] - spot.y_m) <= 1.5 * pitch_m
            if np.nanmax(np.where(around & (np.nan_to_num(residual) > 0), z, -np.inf)) > limit:
                survives = True
                break
            # A spot the stronger spheres make only a small part of is a tumour of its own that their far
            # field tipped under the threshold: a 4.9 mm-deep tumour 7 mm from a 9.9 mm-deep one read +0.26
            # where that one's sphere made +0.076, and fell from 4.42 to 3.88 (threshold 4.06; s48003-0007).
            # The spheres are fitted to the stiffness contrast; the force map's holds the surface's relief
            # too, and there the share kept three more false tumours in one ideal-world phantom.
            if contrast.map == "stiffness":
                peak = np.nanargmax(np.where(around, contrast.contrast[r], -np.inf))
                made = float(np.prod([1.0 + c.flat[peak] for c, _ in by_kept])) - 1.0
                if made < EXPLAINED_SHARE * contrast.contrast[r].flat[peak]:
                    survives = True
                    break
        if survives:
            kept.append(t)
    placed = _placed_over_each_other(kept, levels, contrast, pitch_m, params, said, steps)
    return sorted(placed, key=lambda t: (t.x_m, t.y_m))


class _Steps:
    """A loop's ``progress``: step k of ``total`` told as the fraction k / total, with what it is at; steps
    a loop leaves out (an early end) are skipped over, never told back."""

    def __init__(self, progress: Progress | None, total: int):
        self._progress = progress
        self._total = max(total, 1)
        self._done = 0

    def __call__(self, message: str) -> None:
        if self._progress is not None:
            self._progress(min(self._done / self._total, 1.0), message)
        self._done += 1


class _Said:
    """What tumours' best-fitting spheres make of level records' faces, each solved once per tumour (where
    it lies, with what it was fitted to) and record: ``said(tumours, records)`` is, per record, one
    (contrast, uncertainty) per tumour, None where a tumour has no fit."""

    def __init__(self, signature: Signature):
        self._signature = signature
        self._made: dict[tuple[Tumour, int], tuple[np.ndarray, np.ndarray] | None] = {}

    def __call__(self, tumours: list[Tumour], records) -> list[list[tuple[np.ndarray, np.ndarray] | None]]:
        for t in tumours:
            wanted = sorted({int(r) for r in records if (t, int(r)) not in self._made})
            if wanted:
                made = self._signature(t, np.array(wanted))
                for n, r in enumerate(wanted):
                    self._made[(t, r)] = None if made is None else (made[0][n], made[1][n])
        return [[self._made[(t, int(r))] for t in tumours] for r in records]


# Each sweep cuts what one's misplacement does to the other's about tenfold: two tumours 11 mm apart, the
# stronger detected 0.84 mm off, stand within 0.12 mm after one sweep and 0.013 mm after two.
PLACEMENT_SWEEPS = 2


def _placement_sweeps(tumours: list[Tumour]) -> int:
    return PLACEMENT_SWEEPS if len(tumours) > 1 else 0


def _placed_over_each_other(kept: list[Tumour], levels: np.ndarray, contrast: Contrast, pitch_m: float,
                            params: DetectParams, said: _Said, steps: _Steps) -> list[Tumour]:
    """Each tumour placed by its own contrast over what the others' best-fitting spheres make of the faces at
    the level that placed it: a large tumour's far field slopes across a weaker one's blob and pulls its peak
    towards it (an 8.5 mm-deep tumour 9 mm from a 12 mm-wide shallow one was placed 3.4 mm off, on the side
    towards it), and a weaker one's pulls the stronger one's too (a 4 mm-deep tumour 8 mm from a 9 mm-deep,
    11 mm-wide one was placed 1.6 mm towards it, and the weaker one, placed over that misplaced sphere,
    2.2 mm away from it). Strongest first, over the others where they now lie, in sweeps; its paper's depth
    is taken again where it now lies. One that no other reaches stays where detection placed it."""
    kept = list(kept)
    groups = level_groups(levels)
    sweeps = _placement_sweeps(kept)
    for sweep in range(sweeps):
        for n, t in enumerate(kept):
            steps(f"placing tumour {n + 1} of {len(kept)} (sweep {sweep + 1} of {sweeps})")
            others = kept[:n] + kept[n + 1:]
            records = groups[_placing_spot(t.spots).level_index][1]
            by_others = said(others, list(records))
            if not any(s is not None and s[0].any() for by in by_others for s in by):
                continue
            over, sigma = _over_faces(contrast, records, by_others)
            x, y = _blob_centre(levels, over, sigma, records, [(t.x_m, t.y_m)], pitch_m, params.fit_radius_m)
            first = next(records for force, records in groups if force == t.first_level_N)
            kept[n] = replace(t, x_m=x, y_m=y, depth_m=_depth_at(levels, first, x, y, pitch_m))
    return kept


def over_the_others(tumour: Tumour, others: list[Tumour], levels: np.ndarray, contrast: Contrast,
                    signature: Signature, reach_m: float) -> Contrast:
    """``contrast`` over what the best-fitting spheres of ``others`` make of the faces of the records whose
    centre lies within ``reach_m`` of ``tumour`` along x, their model error added: what ``tumour`` itself
    did to the tissue, for a model of one sphere to explain. Faces no other reaches are left as they are.

    A contrast is over its face's median (the record's scale, :mod:`session.flatfield`), and two tumours
    under one face raise that median where one does not: the small tumour of a face that also held a
    large one read 7 % low everywhere, its healthy elements -0.07 where they stood at 0, a skirt that made
    it a shallow sphere (4.6 mm deep read as 1.1 mm, s5519-0006). So each face is scaled back by the
    median of what the spheres, ``tumour``'s own among them, make of it together."""
    return _over_the_others(tumour, others, levels, contrast, _Said(signature), reach_m)


def _over_the_others(tumour: Tumour, others: list[Tumour], levels: np.ndarray, contrast: Contrast, said: _Said,
                     reach_m: float) -> Contrast:
    records = np.flatnonzero(np.abs(levels["tsi_position_m"][:, 0] - tumour.x_m) <= reach_m)
    made = said([tumour, *others], list(records))
    over, sigma = _over_faces(contrast, records, [by[1:] for by in made], [by[0] for by in made])
    return replace(contrast, contrast=over, sigma=sigma)


# What the sphere that best explains a tumour in a given contrast makes of level records' faces: (tumour,
# contrast, records) -> as Signature
FittedSignature = Callable[[Tumour, Contrast, np.ndarray], "tuple[np.ndarray, np.ndarray] | None"]

# A sphere fitted where a neighbour's skirt is still in the contrast takes part of it as its own, and the
# neighbour read over it then loses that part twice. Each sphere is fitted again over the others' fits of
# the sweep before, until the fits settle (the model's fit is the mode of a grid, so they do) or for at
# most this many sweeps: what is double counted shrinks each sweep by about the square of the share of one
# tumour's footprint that reaches the other's centre (by half, for two broad ones 4.5 mm apart).
DEPTH_SWEEPS = 4


def over_each_other(tumours: list[Tumour], levels: np.ndarray, contrast: Contrast, fitted: FittedSignature,
                    reach_m: float, progress: Progress | None = None) -> list[Contrast]:
    """Each tumour's ``contrast`` over the spheres of the other tumours of its map (:func:`over_the_others`),
    each of those fitted, in sweeps, to its own contrast over the others of the sweep before (the first
    sweep fits them to ``contrast`` itself); ``progress(fraction, message)`` before each tumour of a sweep."""
    over = [contrast] * len(tumours)
    sweeps = DEPTH_SWEEPS if len(tumours) > 1 else 1
    steps = _Steps(progress, sweeps * len(tumours))
    for sweep in range(sweeps):
        given = dict(zip(tumours, over))
        # a sphere's fit in this sweep is the same whichever tumour is read over it: solved once
        said = _Said(lambda o, records, given=given: fitted(o, given[o], records))
        over = []
        for n, t in enumerate(tumours):
            steps(f"tumour {n + 1} of {len(tumours)} over the others (sweep {sweep + 1} of at most {sweeps})")
            over.append(_over_the_others(t, [o for o in tumours if o.source == t.source and o is not t], levels,
                                         contrast, said, reach_m))
        if all(np.array_equal(new.contrast, given[t].contrast) for t, new in zip(tumours, over)):
            break
    return over


def _over_faces(contrast: Contrast, records, said: list[list[tuple[np.ndarray, np.ndarray] | None]],
                own: list[tuple[np.ndarray, np.ndarray] | None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Every record's (contrast, uncertainty), those of ``records`` over what the spheres ``said`` (per
    record) make of their faces (:func:`_over`), with the face's scale put back as the spheres and the
    tumour's ``own`` (per record) make it; a face no sphere reaches is left as it is."""
    over, sigma = np.array(contrast.contrast, copy=True), np.array(contrast.sigma, copy=True)
    for n, (r, by) in enumerate(zip(records, said)):
        if any(s is not None and s[0].any() for s in by):
            over[r], sigma[r] = _over(contrast, r, by, None if own is None else own[n])
    return over, sigma


def _over(contrast: Contrast, record: int, said: list[tuple[np.ndarray, np.ndarray] | None],
          own: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(contrast, its uncertainty) of ``record`` over what the spheres ``said`` make of its face (those
    with no fit left out), their model error added; with the tumour's ``own`` sphere, times the median of
    what all of them make of the face together (each sphere's contrast is over its own face's median)."""
    said = [s for s in said if s is not None]
    made = np.prod([1.0 + c for c, _ in said], axis=0)
    scale = 1.0 if own is None else float(np.median((1.0 + own[0]) * made))
    return ((1.0 + contrast.contrast[record]) * scale / made - 1.0,
            np.sqrt(contrast.sigma[record] ** 2 + sum(e ** 2 for _, e in said)))


def _footprint_holds(levels: np.ndarray, records: np.ndarray, x_m: float, y_m: float, pitch_m: float,
                     margin_m: float = 0.0) -> np.ndarray:
    """Which of ``records`` had the point (x, y) under the TSI's face (grown by ``margin_m``)."""
    rows, cols = levels.dtype["pressure_pa"].shape
    pos = levels["tsi_position_m"][records]
    return ((np.abs(x_m - pos[:, 0]) <= rows * pitch_m / 2 + margin_m)
            & (np.abs(y_m - pos[:, 1]) <= cols * pitch_m / 2 + margin_m))


def _depth_at(levels: np.ndarray, records: np.ndarray, x_m: float, y_m: float, pitch_m: float) -> float:
    """Indentation of the record (among ``records``) whose TSI footprint holds (x, y), nearest centre first;
    else of the nearest whose footprint reaches within half a pitch of it (areas laid to cover a tissue
    leave gaps of a few tenths of a millimetre between them, and a tumour under one is fitted there)."""
    inside = _footprint_holds(levels, records, x_m, y_m, pitch_m)
    if not inside.any():
        inside = _footprint_holds(levels, records, x_m, y_m, pitch_m, margin_m=pitch_m / 2)
    if not inside.any():
        return math.nan
    candidates = np.flatnonzero(inside)
    pos = levels["tsi_position_m"][records[candidates]]
    best = candidates[np.argmin(np.hypot(x_m - pos[:, 0], y_m - pos[:, 1]))]
    return float(levels["indentation_m"][records[best]])


def detect(levels: np.ndarray, contrast: Contrast, pitch_m: float, params: DetectParams | None = None
           ) -> list[Tumour]:
    """Tumours in one map's contrast (``contrast.map``) of a session's level records, ordered along x."""
    params = params or DetectParams()
    groups = level_groups(levels)
    found = spots(levels, contrast, pitch_m, params)
    rows = levels.dtype["pressure_pa"].shape[0]
    # One cluster per tumour and level. A spot that reaches its face's edge sees only the near side of what
    # raised it, and its centroid falls short of it by up to the face's width: it joins a stronger spot of
    # a neighbouring area that far beyond that edge, whichever spot of its cluster that is (a strong tumour
    # at a seam raised the edge of the area beyond the next one, 8 mm from the next one's spot, 12 mm from
    # the cluster's strongest), measured from its centroid or from where its contrast is largest (a strong
    # tumour 6 mm beyond the face's end raised its near edge, and the widest blob peaked at the far one).
    # Not one on its face's other side: a tumour at one edge of an area stays a tumour when a stronger spot
    # rises 8 mm away beyond the other (on a bumpy phantom, a tumour beside a bump's flank, whose
    # uncertainty drowned its score, was joined to a weak rise at the next area's edge and lost).
    per_level: list[list[list[Spot]]] = [[] for _ in groups]
    beyond_edge = rows * pitch_m / 2
    for spot in sorted(found, key=lambda s: -s.score):
        clusters = per_level[spot.level_index]
        near = [c for c in clusters if any(_joins(spot, px, py, o, params.merge_radius_m, beyond_edge)
                                           for o in c for px, py in _places(spot))]
        if near:
            near[0].append(spot)
        else:
            clusters.append([spot])
    # A cluster carries on the nearest track from a lower level within the merge radius, or one its edge
    # spots join as above: where the stronger spot's own area stopped below this level (a stiff tumour near
    # the surface reaches the force limit first), the edge of the area beside it still shows its far field
    # at the levels above, and that is the same tumour, not a new one first seen there.
    tracks: list[dict[int, list[Spot]]] = []
    for index, clusters in enumerate(per_level):
        claimed: set[int] = set()
        for cluster in clusters:
            lead = cluster[0]
            best, best_d = None, math.inf
            for t, track in enumerate(tracks):
                last = track[max(track)][0]
                d = math.hypot(lead.x_m - last.x_m, lead.y_m - last.y_m)
                if t in claimed or max(track) >= index or d >= best_d:
                    continue
                if d <= params.merge_radius_m or any(_joins(spot, px, py, last, params.merge_radius_m, beyond_edge)
                                                     for spot in cluster if spot.at_edge for px, py in _places(spot)):
                    best, best_d = t, d
            if best is None:
                tracks.append({index: cluster})
                claimed.add(len(tracks) - 1)
            else:
                tracks[best][index] = cluster
                claimed.add(best)
    tumours = []
    for track in tracks:
        last = track[max(track)][0]
        top = _highest_level_at(levels, groups, last.x_m, last.y_m, pitch_m)
        if top is None or top not in track:
            continue
        first = top
        while first - 1 in track:
            first -= 1
        run = [track[k] for k in range(first, top + 1)]
        strongest = max(run, key=lambda cluster: cluster[0].score)
        lead = strongest[0]
        placer = _placing_spot([spot for cluster in run for spot in cluster])
        x, y = _blob_centre(levels, contrast.contrast, contrast.sigma, groups[placer.level_index][1],
                            [(placer.x_m, placer.y_m)], pitch_m, params.fit_radius_m)
        depth = _depth_at(levels, groups[first][1], x, y, pitch_m)
        tumours.append(Tumour(x_m=x, y_m=y, depth_m=depth, first_level_N=groups[first][0], source=contrast.map,
                              score=lead.score, contrast=max(s.contrast for s in strongest),
                              levels_N=tuple(groups[k][0] for k in range(first, top + 1)),
                              spots=tuple(s for cluster in run for s in cluster)))
    return sorted(_merged(tumours, params, levels, contrast, groups, pitch_m), key=lambda t: (t.x_m, t.y_m))


def _placing_spot(spots) -> Spot:
    """The spot whose level places a tumour: its strongest inside its face, the strongest if all reach an
    edge. A spot at its face's edge sees one side of what raised it, and where a stiff tumour's own area
    stopped below the top level (the pressure ceiling), the levels above see it from the edge of the next
    area only, often most strongly: placed at such a level, a 1.5 mm-deep tumour was put at that edge,
    1.7 mm off, and 0.1 mm off from the strongest level its own area saw all of it."""
    inside = [spot for spot in spots if not spot.at_edge]
    return max(inside or spots, key=lambda spot: spot.score)


def _places(spot: Spot) -> list[tuple[float, float]]:
    """Where ``spot`` is seen from when joining it to another: its centroid, and where its contrast is
    largest if it reaches its face's edge (see :func:`detect`)."""
    return [(spot.x_m, spot.y_m)] + ([spot.strongest_xy_m] if spot.at_edge else [])


def _joins(spot: Spot, x_m: float, y_m: float, other: Spot, radius_m: float, beyond_edge_m: float) -> bool:
    """Whether ``spot``, seen from (x, y), is one with ``other``: within ``radius_m``, or within
    ``radius_m + beyond_edge_m`` where ``other`` lies beyond an edge of the face ``spot`` reaches."""
    dx, dy = other.x_m - x_m, other.y_m - y_m
    distance = math.hypot(dx, dy)
    return distance <= radius_m or (distance <= radius_m + beyond_edge_m
                                    and any(dx * ox + dy * oy > 0 for ox, oy in spot.outward))


def _merged(tumours: list[Tumour], params: DetectParams, levels: np.ndarray, contrast: Contrast, groups,
            pitch_m: float) -> list[Tumour]:
    """One tumour for tracks whose fitted centres lie within the merge radius: spots of two areas on either
    side of a tumour can start two tracks (each centroid pulled towards its own face), which the blob fit
    then places near the same tumour, each from the elements around its own place. The merged tumour is
    fitted again, at the level that placed the stronger one, from both places over the elements around
    either, and put where the better fit puts it; it keeps the stronger one's score, and the levels are the
    union, so the first level (and the paper's depth with it) is the earlier one's."""
    out: list[Tumour] = []
    radius = params.merge_radius_m
    for t in sorted(tumours, key=lambda t: -t.score):
        near = next((k for k, kept in enumerate(out) if math.hypot(t.x_m - kept.x_m, t.y_m - kept.y_m) <= radius), None)
        if near is None:
            out.append(t)
            continue
        kept = out[near]
        placer = _placing_spot(kept.spots)
        x, y = _blob_centre(levels, contrast.contrast, contrast.sigma, groups[placer.level_index][1],
                            [(kept.x_m, kept.y_m), (t.x_m, t.y_m)], pitch_m, params.fit_radius_m)
        first_N = min(kept.first_level_N, t.first_level_N)
        first = next(records for force, records in groups if force == first_N)
        out[near] = replace(kept, x_m=x, y_m=y, first_level_N=first_N, depth_m=_depth_at(levels, first, x, y, pitch_m),
                            levels_N=tuple(sorted(set(kept.levels_N) | set(t.levels_N))),
                            contrast=max(kept.contrast, t.contrast), spots=kept.spots + t.spots)
    return out


def _blob_centre(levels: np.ndarray, values: np.ndarray, sigma: np.ndarray, records: np.ndarray,
                 starts: list[tuple[float, float]], pitch_m: float, radius_m: float) -> tuple[float, float]:
    """Where a Gaussian blob fitted to the contrast ``values`` (uncertainty ``sigma``) within ``radius_m`` of
    the starting points, over every element of every record at that level, peaks (weighted least squares).
    From several starts (two tracks of one tumour), every fit sees the same elements and the one that
    explains them best is kept; the first start again if every fit fails or leaves its fitted region."""
    from scipy.optimize import least_squares

    rows, cols = levels.dtype["pressure_pa"].shape
    offsets = element_offsets_m(rows, cols, pitch_m)
    xs, ys, cs, ws = [], [], [], []
    for r in records:
        ex = levels["tsi_position_m"][r, 0] + offsets[..., 0]
        ey = levels["tsi_position_m"][r, 1] + offsets[..., 1]
        c, s = values[r], sigma[r]
        near = np.zeros(ex.shape, bool)
        for x_m, y_m in starts:
            near |= np.hypot(ex - x_m, ey - y_m) <= radius_m
        use = near & np.isfinite(c) & np.isfinite(s) & (s > 0)
        xs.append(ex[use]), ys.append(ey[use]), cs.append(c[use]), ws.append(1.0 / s[use])
    x, y, c, w = (np.concatenate(v) for v in (xs, ys, cs, ws))
    if len(c) < 5 or not (c > 0).any():
        return starts[0]

    def residual(p):
        height, cx, cy, log_width = p
        width = math.exp(log_width)
        return w * (height * np.exp(-0.5 * ((x - cx) ** 2 + (y - cy) ** 2) / width ** 2) - c)

    # The centre stays over the elements fitted: data that still rise at the face's edge put a blob's peak
    # beyond it, where nothing was palpated (a spot at the tissue's side was placed 5 mm off the tissue).
    x_lo, x_hi = float(x.min()) - pitch_m / 2, float(x.max()) + pitch_m / 2
    y_lo, y_hi = float(y.min()) - pitch_m / 2, float(y.max()) + pitch_m / 2
    best, best_cost = starts[0], math.inf
    for x_m, y_m in starts:
        x_m, y_m = min(max(x_m, x_lo), x_hi), min(max(y_m, y_lo), y_hi)
        start = (float(c.max()), x_m, y_m, math.log(pitch_m))
        lower = (0.0, max(x_m - radius_m, x_lo), max(y_m - radius_m, y_lo), math.log(0.5 * pitch_m))
        upper = (np.inf, min(x_m + radius_m, x_hi), min(y_m + radius_m, y_hi), math.log(4 * radius_m))
        try:
            fit = least_squares(residual, start, bounds=(lower, upper), max_nfev=200)
        except (ValueError, np.linalg.LinAlgError):
            continue
        cx, cy = float(fit.x[1]), float(fit.x[2])
        if fit.success and math.hypot(cx - x_m, cy - y_m) < radius_m * 0.999 and fit.cost < best_cost:
            best, best_cost = (cx, cy), float(fit.cost)
    return best


def _highest_level_at(levels: np.ndarray, groups, x_m: float, y_m: float, pitch_m: float,
                      margin_m: float = 0.0) -> int | None:
    """Index of the highest force level palpated with (x, y) under the face (grown by ``margin_m``), if any."""
    for index in range(len(groups) - 1, -1, -1):
        if _footprint_holds(levels, groups[index][1], x_m, y_m, pitch_m, margin_m).any():
            return index
    return None


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
    depth_estimate_m: float  # the paper's rule
    first_level_N: float
    detection: int  # index of the matched detection in the list given, -1 when not found
    palpated: bool  # whether the session palpated the place at all (True when not known)
    depth_model_m: float = math.nan
    depth_low_m: float = math.nan
    depth_high_m: float = math.nan
    score: float = math.nan
    # the detector's statistic where the tumour truly is (:func:`evidence_at`): its signal over the error of
    # healthy tissue there, found or not; NaN when not asked for or never under the face
    evidence_z: float = math.nan


MATCH_RADIUS_M = 2e-3


def evidence_at(levels: np.ndarray, contrast: Contrast, pitch_m: float, params: DetectParams, x_m: float,
                y_m: float) -> float:
    """The detector's statistic (:func:`evidence`, the largest over its blob widths) at the element over
    (``x_m``, ``y_m``), the largest over every record that had the point under an element; NaN if none did.
    What a tumour there showed above healthy tissue's error, whether or not it was reported: compared with
    :func:`threshold` it says whether the physics let it be seen at the study's false-alarm rate (a healthy
    point's largest over a session's ten or so records is about 1.5)."""
    rows, cols = levels.dtype["pressure_pa"].shape
    offsets = element_offsets_m(rows, cols, pitch_m)
    best = -math.inf
    for r in np.flatnonzero(_footprint_holds(levels, np.arange(len(levels)), x_m, y_m, pitch_m)):
        tsi = levels["tsi_position_m"][r]
        i, j = np.unravel_index(np.argmin(np.hypot(tsi[0] + offsets[..., 0] - x_m, tsi[1] + offsets[..., 1] - y_m)),
                                (rows, cols))
        z = evidence(contrast.contrast[r], contrast.sigma[r], pitch_m, params.kernel_widths_m,
                     None if contrast.modes is None else contrast.modes[r])[i, j]
        if np.isfinite(z):
            best = max(best, float(z))
    return best if np.isfinite(best) else math.nan


def match_ground_truth(tumours: list[Tumour], ground_truth: list[dict], levels: np.ndarray | None = None,
                       pitch_m: float | None = None, match_radius_m: float = MATCH_RADIUS_M,
                       contrasts: dict[str, Contrast] | None = None, params: DetectParams | None = None
                       ) -> tuple[list[TruthMatch], dict[str, int]]:
    """Pair each true tumour with the nearest detection (per map) within ``match_radius_m``.

    Returns the matches and, per map, the number of detections that matched no true tumour (false
    positives). With ``levels`` and ``pitch_m``, a true tumour no area was palpated over is marked
    ``palpated=False``; with the maps' ``contrasts`` and the detector's ``params`` too, each match carries
    the detector's statistic where the tumour is (:func:`evidence_at`).
    """
    matches: list[TruthMatch] = []
    false_positives: dict[str, int] = {}
    groups = level_groups(levels) if levels is not None else None
    for source in SOURCES:
        found = [(k, t) for k, t in enumerate(tumours) if t.source == source]
        used: set[int] = set()
        # closest pairs first, so a detection goes to the true tumour it is nearest to
        pairs = sorted((math.hypot(t.x_m - float(truth["x_m"]), t.y_m - float(truth["y_m"])), i, k)
                       for i, truth in enumerate(ground_truth) for k, t in found)
        assigned: dict[int, tuple[int, float]] = {}
        for d, i, k in pairs:
            if d <= match_radius_m and i not in assigned and k not in used:
                assigned[i] = (k, d)
                used.add(k)
        for i, truth in enumerate(ground_truth):
            tx, ty = float(truth["x_m"]), float(truth["y_m"])
            depth = float(truth.get("depth_m", math.nan))
            # a tumour centred in the gap between two areas lies under both
            palpated = groups is None or _highest_level_at(levels, groups, tx, ty, pitch_m, pitch_m / 2) is not None
            seen = (evidence_at(levels, contrasts[source], pitch_m, params, tx, ty)
                    if contrasts is not None and source in contrasts and params is not None else math.nan)
            if i not in assigned:
                matches.append(TruthMatch(i, tx, ty, depth, source, False, math.nan, math.nan, math.nan, -1, palpated,
                                          evidence_z=seen))
                continue
            k, d = assigned[i]
            t = tumours[k]
            matches.append(TruthMatch(i, tx, ty, depth, source, True, d, t.depth_m, t.first_level_N, k, palpated,
                                      t.depth_model_m, t.depth_low_m, t.depth_high_m, t.score, seen))
        false_positives[source] = len(found) - len(used)
    return matches, false_positives
