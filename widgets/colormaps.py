"""The paper's colour contour scale, built once for every tactile map.

The paper's display "utilizes the visual color spectrum ... with dark red indicating the highest pressure
intensity and blue indicating the lowest": a jet-like spectrum, blue -> cyan -> yellow -> red, ending in
dark red so the tumour reads as the darkest red on screen. Keeping that scale (rather than a perceptually
uniform one) lets an operator compare our maps with the paper's figures at a glance.

No data (an element without contact has no stiffness) must never look like a low value, so it is drawn in a
neutral grey, a colour the spectrum does not contain.

Values become colours in one place, :func:`lut_index`, the way pyqtgraph's ImageItem indexes its lookup
table, so a value has the same colour in the live maps (pyqtgraph and :mod:`widgets.colour_image`), in the
reviewer and in exported images and reports (:mod:`widgets.map_painting`).
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg

# Stops of the spectrum as (position, RGB). The dark ends make the extremes distinguishable from the
# saturated blue and red next to them.
_STOPS: tuple[tuple[float, tuple[int, int, int]], ...] = (
    (0.000, (0, 0, 144)),  # dark blue: lowest
    (0.125, (0, 0, 255)),  # blue
    (0.375, (0, 255, 255)),  # cyan
    (0.625, (255, 255, 0)),  # yellow
    (0.875, (255, 0, 0)),  # red
    (1.000, (128, 0, 0)),  # dark red: highest
)

CONTOUR_COLORMAP: pg.ColorMap = pg.ColorMap(
    pos=np.array([p for p, _ in _STOPS]),
    color=np.array([c for _, c in _STOPS], dtype=np.ubyte),
    mapping=pg.ColorMap.CLIP,
    name="palpation-contour",
)

# 256 uint8 RGB entries: the size ImageItem's fast path indexes directly.
CONTOUR_LUT: np.ndarray = CONTOUR_COLORMAP.getLookupTable(nPts=256, alpha=False)
CONTOUR_LUT.setflags(write=False)

NO_DATA_RGB: tuple[int, int, int] = (128, 128, 128)


def lut_index(values: np.ndarray, levels: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(index into CONTOUR_LUT, finite mask) for ``values`` coloured over ``levels`` = (lo, hi):
    ``floor((v - lo) * N / (hi - lo))`` clipped to the table, as pyqtgraph indexes a lookup table of N
    entries. Non-finite values get index 0 and are False in the mask (draw them in NO_DATA_RGB)."""
    lo, hi = float(levels[0]), float(levels[1])
    n = len(CONTOUR_LUT)
    finite = np.isfinite(values)
    index = np.where(finite, values, lo).astype(np.float64)
    index -= lo
    index *= n / (hi - lo)
    np.clip(index, 0, n - 1, out=index)
    return index.astype(np.intp), finite


def colour_range(values: np.ndarray) -> tuple[float, float]:
    """[2nd percentile, max] of the finite values: a map's own contrast, robust to a stray low cell (the
    reviewer's maps and exported images)."""
    finite = values[np.isfinite(values)]
    if not finite.size:
        return (0.0, 1.0)
    lo, hi = float(np.percentile(finite, 2.0)), float(finite.max())
    if hi <= lo:
        hi = lo + max(abs(lo) * 0.01, 1e-12)
    return lo, hi


CONTRAST_SPAN = (0.2, 1.0)  # a contrast map's colour range: at least ±20 %, at most ±100 % (measured / expected - 1)


def contrast_range(values: np.ndarray) -> tuple[float, float]:
    """A symmetric range for a contrast map, so healthy tissue (0) is always the middle colour: ±20 % at
    least (a few % of noise stays one colour), and at most ±100 %, beyond which a tumour saturates in dark
    red rather than turning every weaker one into the background."""
    finite = np.abs(values[np.isfinite(values)])
    span = float(np.clip(finite.max() if finite.size else 0.0, *CONTRAST_SPAN))
    return -span, span


def map_rgb(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(nx, ny, 3) uint8 image of an (nx, ny) map, x upwards (row 0 is the highest x) and y to the right, the
    orientation of every whole-tissue map (:mod:`widgets.tissue_view` says why)."""
    image = values[::-1]
    index, finite = lut_index(image, (lo, hi))
    rgb = CONTOUR_LUT[index].copy()
    rgb[~finite] = NO_DATA_RGB
    return np.ascontiguousarray(rgb, dtype=np.uint8)
