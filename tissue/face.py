"""The probe's face as the tissue meets it: the element grid, the cover's spread and Eq. 1.

The TSI is a rigid, level face of ``rows x cols`` square elements at ``pitch_m`` (the paper's 4 x 15 of
2 mm). Arrays over the face are shaped ``(rows, cols)``: row ``i`` runs along the tissue's x, column ``j``
along y, and element ``(i, j)`` is centred at ``((i - (rows-1)/2) pitch, (j - (cols-1)/2) pitch)`` from the
face's centre (:func:`element_offsets_m`). The simulated rig, the recorded session and the analysis all
place elements by this one rule.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ROWS, COLS, PITCH_M = 4, 15, 2e-3  # the paper's TSI: 15 x 4 capacitive elements of 2 x 2 mm (Section II)

# The elastomer cover over the elements spreads load sideways by about its thickness; 0.5 mm is that of thin
# capacitive skins (docs/phantoms.md, section 2). A session records the value its array had.
COVER_SPREAD_M = 0.5e-3
MAX_COVER_SPREAD_M = 2e-3  # a cover that spreads load further blurs an element beyond its neighbours


def element_offsets_m(rows: int, cols: int, pitch_m: float) -> np.ndarray:
    """(rows, cols, 2) element-centre (x, y) offsets from the face's centre."""
    ix = (np.arange(rows) - (rows - 1) / 2.0) * pitch_m
    jy = (np.arange(cols) - (cols - 1) / 2.0) * pitch_m
    gx, gy = np.meshgrid(ix, jy, indexing="ij")
    return np.stack([gx, gy], axis=-1)


@dataclass(frozen=True, slots=True)
class Face:
    """The geometry of a face of ``rows x cols`` elements at ``pitch_m``."""

    rows: int = ROWS
    cols: int = COLS
    pitch_m: float = PITCH_M

    @property
    def element_area_m2(self) -> float:
        return self.pitch_m * self.pitch_m

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    @property
    def size_m(self) -> tuple[float, float]:
        """Extent of the face along (x, y)."""
        return (self.rows * self.pitch_m, self.cols * self.pitch_m)

    def element_offsets_m(self) -> np.ndarray:
        return element_offsets_m(self.rows, self.cols, self.pitch_m)


def stiffness_pa(force_N, L0_m, dL_m, element_area_m2: float, min_indentation_m: float) -> np.ndarray:
    """Eq. 1, E = F L0 / (A dL), for each element; NaN where it is not usable: an input not finite, an
    indentation below ``min_indentation_m`` (below it the ratio is the noise's), or no tissue (L0 <= 0).
    Arrays of any matching shapes; an unusable element is divided by one, never by zero."""
    force_N, L0_m, dL_m = np.asarray(force_N, float), np.asarray(L0_m, float), np.asarray(dL_m, float)
    with np.errstate(invalid="ignore"):
        usable = np.isfinite(force_N) & np.isfinite(L0_m) & np.isfinite(dL_m) & (dL_m >= min_indentation_m) & (L0_m > 0)
    out = force_N * L0_m / (element_area_m2 * np.where(usable, dL_m, 1.0))
    return np.where(usable, out, np.nan)


def cover_weight(spread_m: float, pitch_m: float) -> float:
    """Fraction of a uniformly loaded element's force a Gaussian spread of ``spread_m`` moves into one
    neighbour (exact integral of the Gaussian's tail over the element)."""
    if spread_m <= 0.0:
        return 0.0
    a = pitch_m / spread_m
    # (1/a) * integral_0^a Q(t) dt = Q(a) + (phi(0) - phi(a)) / a, Q the Gaussian tail, phi its density
    q = 0.5 * math.erfc(a / math.sqrt(2.0))
    return q + (1.0 - math.exp(-0.5 * a * a)) / (math.sqrt(2.0 * math.pi) * a)


def cover_operators(weight: float, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) matrices with ``left @ p @ right`` = the cover's spread of ``p``: each element passes
    ``weight`` of its load to each neighbour along both axes, and an edge element keeps the share that
    would leave the array (so every column of either matrix sums to one and the total force is kept)."""
    mats = []
    for n in shape:
        m = np.eye(n) * (1.0 - 2.0 * weight)
        idx = np.arange(n - 1)
        m[idx, idx + 1] = weight
        m[idx + 1, idx] = weight
        m[0, 0] += weight
        m[n - 1, n - 1] += weight
        mats.append(m)
    return mats[0], mats[1].T
