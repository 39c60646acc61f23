"""The paper's colour contour scale, built once for every tactile map.

The paper's display "utilizes the visual color spectrum ... with dark red indicating the highest pressure
intensity and blue indicating the lowest": a jet-like spectrum, blue -> cyan -> yellow -> red, ending in
dark red so the tumour reads as the darkest red on screen. Keeping that scale (rather than a perceptually
uniform one) lets an operator compare our maps with the paper's figures at a glance.

No data (an element without contact has no stiffness) must never look like a low value, so it is drawn in a
neutral grey, a colour the spectrum does not contain.
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
