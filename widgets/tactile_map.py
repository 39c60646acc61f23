"""A live map of one (4, 15) tactile array: pressure or stiffness, in the paper's colour contour scale.

The sensor's long axis (y, 15 elements, 30 mm) is drawn horizontally and its short axis (x, 4 elements,
8 mm) vertically, with the aspect ratio of the real sensing face, so a hot spot appears where it is under
the instrument. Coordinates are element offsets from the TSI centre in mm (the convention of
``hardware.interfaces``); values arrive in Pa and are shown in kPa.

Two views: *cells* draws one square per element, which is exactly what was measured; *contour* upsamples
with a bicubic (Keys, a = -0.5) kernel, clips to the measured range so the kernel's overshoot cannot invent
a peak, and can overlay iso-lines at round values (about five across the colour range).

A *contrast* view shows, instead of the reading, how far each element lies from what homogeneous tissue
would read there (measured / expected - 1, in %; the probe's own edge pattern divided out) on a range
symmetric about healthy tissue, with the spots that pass the detection threshold circled. The contrast is
computed elsewhere (:meth:`session.live.LiveMaps.frame_contrast`) and handed to :meth:`set_contrast`.
Elements whose expected reading is too uncertain to read a contrast from (see :data:`UNREADABLE_SIGMA`)
are left blank in that view.
"""

from __future__ import annotations

import enum
import math

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets
from scipy import ndimage

from control.telemetry import COLS, ROWS
from widgets.colormaps import CONTOUR_COLORMAP, contrast_range
from widgets.colour_image import ColourImageItem
from widgets.plot_style import follow_palette

UPSAMPLE = 8  # contour pixels per element along each axis
MARKER_ARM_MM = 1.6
_KPA_PER_PA = 1e-3
_SPIN_LIMIT_KPA = 1e4  # ten times the stiffness of a hard tumour; the spin boxes stay narrow
_PCT = 100.0
# An element whose expected reading is uncertain by more than this (one standard deviation, relative) is
# left blank in the contrast view. The row of a face that overhangs the tissue's end is uncertain by about
# 50 % (the share of the element still on the tissue), and read +84 % there in a study session: the
# brightest element of the map, on no tumour, and it stretched the symmetric colour range until the
# tumour's +10 % beside it was pale. Detection weighs such elements down by their uncertainty anyway.
UNREADABLE_SIGMA = 0.25
NO_CONTRAST_TEXT = "contrast from the 4th area on\n(or with a reference palpation)"


class ViewMode(enum.Enum):
    CELLS = "cells"
    CONTOUR = "contour"


def cubic_upsampling_matrix(n: int, factor: int) -> np.ndarray:
    """(n*factor, n) matrix W so that ``W @ samples`` is the Keys-cubic interpolant at the fine pixel centres.

    Fine pixel k covers [k/factor, (k+1)/factor) of an element pitch; positions beyond the first and last
    element centres repeat the edge value (the sensor has no data outside its face).
    """
    a = -0.5
    fine = (np.arange(n * factor) + 0.5) / factor - 0.5
    s = np.clip(fine, 0.0, n - 1.0)
    base = np.floor(s).astype(int)
    w = np.zeros((n * factor, n))
    for offset in (-1, 0, 1, 2):
        j = base + offset
        d = np.abs(s - j)
        near = (a + 2) * d**3 - (a + 3) * d**2 + 1
        far = a * d**3 - 5 * a * d**2 + 8 * a * d - 4 * a
        weight = np.where(d <= 1, near, np.where(d < 2, far, 0.0))
        np.add.at(w, (np.arange(n * factor), np.clip(j, 0, n - 1)), weight)
    return w


# Marching squares: corners 0..3 = (r, c), (r, c+1), (r+1, c+1), (r+1, c); bit i set when corner i is above
# the level. Edges 0..3 join corners (0,1), (1,2), (2,3), (3,0). Each case lists up to two segments as edge
# pairs; the saddles (5, 10) are resolved by joining the below-level corners, which is consistent and
# cannot cross another level's line.
_SEGMENTS = np.full((16, 2, 2), -1, dtype=np.int8)
for _case, _segs in {
    1: [(3, 0)], 2: [(0, 1)], 3: [(3, 1)], 4: [(1, 2)], 5: [(3, 0), (1, 2)], 6: [(0, 2)], 7: [(3, 2)],
    8: [(2, 3)], 9: [(0, 2)], 10: [(0, 1), (2, 3)], 11: [(1, 2)], 12: [(1, 3)], 13: [(0, 1)], 14: [(3, 0)],
}.items():
    for _i, _seg in enumerate(_segs):
        _SEGMENTS[_case, _i] = _seg


def iso_segments(field: np.ndarray, xs: np.ndarray, ys: np.ndarray, levels) -> np.ndarray:
    """Iso-line segments of ``field`` (rows along ``ys``, columns along ``xs``) at each of ``levels``.

    Returns a (2 * n_segments, 2) array of (x, y) points, consecutive rows forming one segment (pyqtgraph's
    ``connect="pairs"``). Squares touching a NaN sample produce no segment.
    """
    f00, f01, f11, f10 = field[:-1, :-1], field[:-1, 1:], field[1:, 1:], field[1:, :-1]
    finite = np.isfinite(f00) & np.isfinite(f01) & np.isfinite(f11) & np.isfinite(f10)
    pieces = []
    for level in levels:
        with np.errstate(invalid="ignore"):
            case = (f00 > level) * 1 + (f01 > level) * 2 + (f11 > level) * 4 + (f10 > level) * 8
        case[~finite] = 0
        r, c = np.nonzero((case != 0) & (case != 15))
        if r.size == 0:
            continue
        a, b, cc, d = f00[r, c], f01[r, c], f11[r, c], f10[r, c]
        xa, xb, ya, yb = xs[c], xs[c + 1], ys[r], ys[r + 1]
        # The crossing on every edge of the square; a segment only ever uses edges whose corners straddle
        # the level, where the denominator is non-zero, so the other edges' inf/NaN are never read.
        ex, ey = np.empty((r.size, 4)), np.empty((r.size, 4))
        with np.errstate(divide="ignore", invalid="ignore"):
            ex[:, 0], ey[:, 0] = xa + (level - a) / (b - a) * (xb - xa), ya
            ex[:, 1], ey[:, 1] = xb, ya + (level - b) / (cc - b) * (yb - ya)
            ex[:, 2], ey[:, 2] = xb - (level - cc) / (d - cc) * (xb - xa), yb
            ex[:, 3], ey[:, 3] = xa, yb - (level - d) / (a - d) * (yb - ya)
        cases = case[r, c]
        for s in (0, 1):
            edges = _SEGMENTS[cases, s]
            rows = np.nonzero(edges[:, 0] >= 0)[0]
            if rows.size == 0:
                continue
            e0, e1 = edges[rows, 0], edges[rows, 1]
            seg = np.empty((rows.size, 2, 2))
            seg[:, 0, 0], seg[:, 0, 1] = ex[rows, e0], ey[rows, e0]
            seg[:, 1, 0], seg[:, 1, 1] = ex[rows, e1], ey[rows, e1]
            pieces.append(seg.reshape(-1, 2))
    if not pieces:
        return np.empty((0, 2))
    return np.concatenate(pieces)


def nice_step(span: float, target_ticks: int = 5) -> float:
    """A 1-2-5 x 10^k step giving about ``target_ticks`` intervals over ``span`` (> 0)."""
    raw = span / target_ticks
    power = 10.0 ** math.floor(math.log10(raw))
    for mult in (1.0, 2.0, 5.0, 10.0):
        if raw <= mult * power * (1 + 1e-6):
            return mult * power
    return 10.0 * power


def auto_levels(data_max: float, current: tuple[float, float] | None, floor: float) -> tuple[float, float]:
    """Colour range [0, top] that follows the data's maximum without flickering at display rate.

    The bottom stays at 0: pressure and stiffness are never negative, so "nothing" is always the lowest
    colour, whatever the noise. The top is at least ``floor``, so a uniform or noise-only map is not
    stretched over the whole spectrum (which would paint healthy tissue tumour-red); above it the top
    follows the maximum, rounded up to a round number, and is kept while the data still reaches half of it.
    """
    top = max(data_max, floor)
    if current is not None and top <= current[1] and top >= 0.5 * current[1]:
        return current
    step = nice_step(top)
    slack = 1e-6  # float32 data sits a few ulps off a round value; it must not push the range a step out
    return (0.0, math.ceil(top / step - slack) * step)


class TactileMapWidget(QtWidgets.QWidget):
    """One tactile array as a colour map with a kPa colour bar; ``set_data`` is cheap enough for 60 Hz.

    Child objectNames: ``title``, ``maxLabel``, ``cellsButton``, ``contourButton``, ``isoLines``,
    ``contrastView``, ``lockRange``, ``levelMin``, ``levelMax``, ``levelError``, ``plot``; graphics items in
    the plot's scene: ``mapImage`` (a :class:`~widgets.colour_image.ColourImageItem`), ``cellGrid``,
    ``isoCurves``, ``noDataText``, ``contrastSpots``, ``colorBar``; the marker is :meth:`marker_m`.
    """

    def __init__(self, title: str, *, pitch_m: float = 2e-3, auto_floor_pa: float = 10e3,
                 no_data_text: str = "no data",
                 parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        if not pitch_m > 0:
            raise ValueError(f"{title} map: pitch_m must be > 0, got {pitch_m!r}")
        self._name = title
        self._floor_kpa = self._checked_floor_kpa(auto_floor_pa)
        self._mode = ViewMode.CELLS
        self._levels_kpa: tuple[float, float] | None = None
        self._locked = False
        self._data_kpa = np.full((ROWS, COLS), np.nan, dtype=np.float32)
        self._max_text = ""
        self._marker_at: tuple[int, int] | None = None
        self._no_data_text = no_data_text
        self._contrast_on = False
        self._contrast_pct: np.ndarray | None = None  # None: no flat field yet
        self._contrast_spots: tuple[tuple[int, int], ...] = ()
        self._spots_drawn: tuple[tuple[int, int], ...] = ()

        pitch_mm = pitch_m * 1e3
        width_mm, height_mm = COLS * pitch_mm, ROWS * pitch_mm
        self._rect = QtCore.QRectF(-width_mm / 2, -height_mm / 2, width_mm, height_mm)
        self._wy = cubic_upsampling_matrix(COLS, UPSAMPLE).astype(np.float32)
        self._wx = cubic_upsampling_matrix(ROWS, UPSAMPLE).astype(np.float32)
        self._fine_to_cell_row = np.arange(ROWS * UPSAMPLE) // UPSAMPLE
        self._fine_to_cell_col = np.arange(COLS * UPSAMPLE) // UPSAMPLE
        self._fine_y_mm = self._rect.left() + (np.arange(COLS * UPSAMPLE) + 0.5) * pitch_mm / UPSAMPLE
        self._fine_x_mm = self._rect.top() + (np.arange(ROWS * UPSAMPLE) + 0.5) * pitch_mm / UPSAMPLE

        self._build_controls(title)
        self._build_plot()
        self._apply_levels(auto_levels(0.0, None, self._floor_kpa))
        self._render()

    # ---- construction --------------------------------------------------------------------------------

    def _build_controls(self, title: str) -> None:
        self._title = QtWidgets.QLabel(title, objectName="title")
        font = self._title.font()
        font.setPointSizeF(font.pointSizeF() * 1.3)
        font.setBold(True)
        self._title.setFont(font)
        self._max_label = QtWidgets.QLabel("", objectName="maxLabel")
        self._max_label.setFont(font)
        # room for the widest reading, so a changing maximum never re-lays out the bar
        self._max_label.setMinimumWidth(QtGui.QFontMetrics(font).horizontalAdvance("max 000.0 kPa"))

        # Radio buttons: their checked state reads at a glance in any palette, unlike flat tool buttons.
        self._cells = QtWidgets.QRadioButton("Cells", objectName="cellsButton", checked=True)
        self._contour = QtWidgets.QRadioButton("Contour", objectName="contourButton")
        self._cells.setToolTip("One square per element: exactly what was measured")
        self._contour.setToolTip("Bicubic interpolation between elements")
        group = QtWidgets.QButtonGroup(self)
        group.setExclusive(True)
        group.addButton(self._cells)
        group.addButton(self._contour)
        self._cells.toggled.connect(lambda on: on and self.set_view_mode(ViewMode.CELLS))
        self._contour.toggled.connect(lambda on: on and self.set_view_mode(ViewMode.CONTOUR))

        self._iso = QtWidgets.QCheckBox("Iso", objectName="isoLines", enabled=False)
        self._iso.setToolTip("Lines of equal value at round steps of the colour range (contour view)")
        self._iso.toggled.connect(self._render)

        self._contrast_box = QtWidgets.QCheckBox("Contrast", objectName="contrastView")
        self._contrast_box.setToolTip("Each element over what homogeneous tissue would read there, in % (the "
                                      "probe's own pattern divided out); significant spots are circled. An "
                                      "element whose expected reading is uncertain by over "
                                      f"{UNREADABLE_SIGMA * _PCT:.0f} % is left blank")
        self._contrast_box.toggled.connect(self.set_contrast_view)

        self._lock = QtWidgets.QCheckBox("Lock", objectName="lockRange")
        self._lock.setToolTip("Keep the colour range fixed instead of following the data")
        self._lock.toggled.connect(self._lock_toggled)
        self._min_spin = self._make_spin("levelMin", "Lowest value of the colour range")
        self._max_spin = self._make_spin("levelMax", "Highest value of the colour range")
        self._level_error = QtWidgets.QLabel("", objectName="levelError")
        self._level_error.setStyleSheet("color: #ff6b6b; font-weight: bold;")
        self._level_error.hide()

        # Two rows, the reading above the controls: in one the map could not be narrower than ~830 px, and
        # the console did not fit a 1600 px screen.
        heading = QtWidgets.QHBoxLayout()
        heading.setContentsMargins(0, 0, 0, 0)
        heading.addWidget(self._title)
        heading.addSpacing(8)
        heading.addWidget(self._max_label)
        heading.addStretch(1)
        bar = QtWidgets.QHBoxLayout()
        bar.setContentsMargins(0, 0, 0, 0)
        bar.addWidget(self._cells)
        bar.addWidget(self._contour)
        bar.addWidget(self._iso)
        bar.addWidget(self._contrast_box)
        bar.addStretch(1)
        bar.addWidget(self._lock)
        bar.addWidget(self._min_spin)
        self._to_label = QtWidgets.QLabel("to")
        bar.addWidget(self._to_label)
        bar.addWidget(self._max_spin)
        bar.addWidget(self._level_error)
        self._bar_layout = QtWidgets.QVBoxLayout()
        self._bar_layout.setContentsMargins(0, 0, 0, 0)
        self._bar_layout.setSpacing(2)
        self._bar_layout.addLayout(heading)
        self._bar_layout.addLayout(bar)

    def _make_spin(self, name: str, tip: str) -> QtWidgets.QDoubleSpinBox:
        spin = QtWidgets.QDoubleSpinBox(objectName=name, enabled=False)
        spin.setRange(-_SPIN_LIMIT_KPA, _SPIN_LIMIT_KPA)
        spin.setMaximumWidth(QtGui.QFontMetrics(spin.font()).horizontalAdvance("-0000.0 kPa") + 30)
        spin.setDecimals(1)
        spin.setSuffix(" kPa")
        spin.setKeyboardTracking(False)  # apply on Enter / focus-out, not on every keystroke
        spin.setToolTip(tip)
        spin.valueChanged.connect(self._spin_changed)
        return spin

    def _build_plot(self) -> None:
        self._plot = pg.PlotWidget()
        self._plot.setObjectName("plot")  # PlotWidget hands constructor keywords to its PlotItem
        item = self._plot.getPlotItem()
        item.setMenuEnabled(False)
        item.hideButtons()
        view = item.getViewBox()
        view.setMouseEnabled(x=False, y=False)
        view.setAspectLocked(True)
        view.setRange(self._rect, padding=0.0)
        view.setDefaultPadding(0.0)
        # Ticks only across the sensing face, so the margins the locked aspect adds carry no coordinates.
        half_w, half_h = self._rect.width() / 2, self._rect.height() / 2
        y_ticks = np.arange(-math.floor(half_w / 5) * 5, half_w + 1e-9, 5.0)
        x_ticks = np.arange(-math.floor(half_h / 2) * 2, half_h + 1e-9, 2.0)
        tick_font = QtGui.QFont()
        tick_font.setPointSize(10)
        for side, label, ticks in (("bottom", "y on the TSI (mm)", y_ticks), ("left", "x (mm)", x_ticks)):
            axis = item.getAxis(side)
            axis.setTicks([[(float(v), f"{v:g}") for v in ticks], []])
            axis.setTickFont(tick_font)
            item.setLabel(side, label)

        self._image = ColourImageItem()  # NaN is coloured no-data grey in the image itself
        self._image.setObjectName("mapImage")
        view.addItem(self._image)

        self._grid = pg.PlotCurveItem(pen=pg.mkPen((0, 0, 0, 90), width=1), connect="pairs")
        self._grid.setData(*self._grid_lines())
        self._grid.setZValue(5)
        self._grid.setObjectName("cellGrid")
        view.addItem(self._grid, ignoreBounds=True)

        self._iso_item = pg.PlotCurveItem(pen=pg.mkPen((0, 0, 0, 210), width=1.5), connect="pairs")
        self._iso_item.setZValue(6)
        self._iso_item.hide()
        self._iso_item.setObjectName("isoCurves")
        view.addItem(self._iso_item, ignoreBounds=True)

        self._no_data_label = pg.TextItem(self._no_data_text, color=(235, 235, 235), anchor=(0.5, 0.5))
        font = QtGui.QFont()
        font.setPointSize(14)
        font.setBold(True)
        self._no_data_label.setFont(font)
        self._no_data_label.setPos(0.0, 0.0)
        self._no_data_label.setZValue(10)
        self._no_data_label.setObjectName("noDataText")
        view.addItem(self._no_data_label, ignoreBounds=True)

        self._spot_item = pg.ScatterPlotItem(symbol="o", size=22, pen=pg.mkPen((255, 255, 255), width=2.5),
                                             brush=None, pxMode=True)
        self._spot_item.setZValue(13)
        self._spot_item.setObjectName("contrastSpots")
        view.addItem(self._spot_item, ignoreBounds=True)

        # A cross with a dark outline under a light core reads on every colour of the scale. Plain path
        # items: moving one costs a fraction of what a ScatterPlotItem costs to paint.
        arm = MARKER_ARM_MM
        cross = QtGui.QPainterPath()
        cross.moveTo(-arm, 0.0)
        cross.lineTo(arm, 0.0)
        cross.moveTo(0.0, -arm)
        cross.lineTo(0.0, arm)
        self._markers = []
        for z, colour, width in ((11, (20, 20, 20), 5.0), (12, (255, 255, 255), 2.0)):
            marker = QtWidgets.QGraphicsPathItem(cross)
            pen = pg.mkPen(colour, width=width)
            pen.setCosmetic(True)
            marker.setPen(pen)
            marker.setZValue(z)
            marker.hide()
            view.addItem(marker, ignoreBounds=True)
            self._markers.append(marker)

        self._bar = pg.ColorBarItem(values=(0.0, 1.0), colorMap=CONTOUR_COLORMAP, label="kPa", interactive=False,
                                    colorMapMenu=False, width=18)
        self._bar.axis.setTickFont(tick_font)
        self._bar.setObjectName("colorBar")
        item.layout.addItem(self._bar, 2, 5)
        item.layout.setColumnFixedWidth(4, 6)
        self._apply_palette()

        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        layout.setSpacing(2)
        layout.addLayout(self._bar_layout)
        layout.addWidget(self._plot, 1)

    def _apply_palette(self) -> None:
        axes = [self._plot.getPlotItem().getAxis(side) for side in ("bottom", "left")]
        axes += [self._bar.getAxis(side) for side in ("left", "right", "top", "bottom")]
        follow_palette(self, [self._plot], axes)

    def changeEvent(self, event: QtCore.QEvent) -> None:
        if event.type() == QtCore.QEvent.Type.PaletteChange:
            self._apply_palette()
        super().changeEvent(event)

    def _grid_lines(self) -> tuple[np.ndarray, np.ndarray]:
        r = self._rect
        ys = np.linspace(r.left(), r.right(), COLS + 1)[1:-1]
        xs = np.linspace(r.top(), r.bottom(), ROWS + 1)[1:-1]
        px = np.concatenate([np.repeat(ys, 2), np.tile([r.left(), r.right()], xs.size)])
        py = np.concatenate([np.tile([r.top(), r.bottom()], ys.size), np.repeat(xs, 2)])
        return px, py

    # ---- public API ----------------------------------------------------------------------------------

    def set_no_data_text(self, text: str) -> None:
        """What the map says when it has nothing to show (no frame yet, no contact, ...)."""
        if text != self._no_data_text:
            self._no_data_text = text
            self._render()

    def set_data(self, array_pa: np.ndarray) -> None:
        """Show a (4, 15) array in Pa (rows = x, cols = y). NaN or infinite elements are drawn as no data."""
        array = np.asarray(array_pa)
        if array.shape != (ROWS, COLS):
            raise ValueError(f"{self._name} map: expected a ({ROWS}, {COLS}) array (rows = x, cols = y), "
                             f"got shape {array.shape}")
        if array.dtype.kind not in "fiu":
            raise ValueError(f"{self._name} map: expected numbers in Pa, got dtype {array.dtype}")
        data = np.multiply(array, _KPA_PER_PA, dtype=np.float32)
        data[~np.isfinite(data)] = np.nan
        self._data_kpa = data
        self._render()

    def set_marker_m(self, point_m: tuple[float, float] | None) -> None:
        """Mark a point of the face, (x, y) in m from the TSI centre (e.g. the centre of pressure); None hides it."""
        if point_m is None:
            if self._marker_at is not None:
                self._marker_at = None
                for marker in self._markers:
                    marker.hide()
            return
        x_mm, y_mm = point_m[0] * 1e3, point_m[1] * 1e3
        at = (round(x_mm * 20), round(y_mm * 20))  # move it only after 0.05 mm
        if at == self._marker_at:
            return
        self._marker_at = at
        for marker in self._markers:
            marker.setPos(y_mm, x_mm)  # y runs across the screen, x up it
            marker.show()

    def set_contrast(self, contrast: np.ndarray | None, spots: tuple[tuple[int, int], ...] = (),
                     sigma: np.ndarray | None = None) -> None:
        """The frame's contrast (measured / expected - 1, (4, 15)) and the elements (row, col) where a
        significant spot peaks, shown in the contrast view; None while there is no flat field. ``sigma``
        (4, 15): the contrast's relative uncertainty, to blank the elements it cannot be read from."""
        if contrast is None:
            self._contrast_pct, self._contrast_spots = None, ()
        else:
            contrast = np.asarray(contrast, dtype=np.float64)
            if contrast.shape != (ROWS, COLS):
                raise ValueError(f"{self._name} map: expected a ({ROWS}, {COLS}) contrast, got shape {contrast.shape}")
            pct = (contrast * _PCT).astype(np.float32)
            pct[~np.isfinite(pct)] = np.nan
            if sigma is not None:
                pct[~(np.asarray(sigma, dtype=np.float64) <= UNREADABLE_SIGMA)] = np.nan
            self._contrast_pct, self._contrast_spots = pct, tuple(spots)
        if self._contrast_on:
            self._render()

    def contrast_view(self) -> bool:
        return self._contrast_on

    def set_contrast_view(self, on: bool) -> None:
        """Show the contrast (True) or the reading itself."""
        on = bool(on)
        if on == self._contrast_on:
            return
        self._contrast_on = on
        self._contrast_box.setChecked(on)
        # a contrast's range is always symmetric about healthy tissue: nothing to lock or type in
        self._lock.setEnabled(not on)
        for widget in (self._min_spin, self._to_label, self._max_spin):
            widget.setVisible(not on)
        self._bar.getAxis("left").setLabel("% over healthy" if on else "kPa")
        if not on:
            self._bar.setLevels(self._levels_kpa, update_items=False)
        self._render()

    def contrast_spots(self) -> tuple[tuple[int, int], ...]:
        """The elements circled in the contrast view (none outside it)."""
        return self._contrast_spots if self._contrast_on and self._contrast_pct is not None else ()

    def marker_m(self) -> tuple[float, float] | None:
        """The marked point (x, y) in m, or None."""
        if self._marker_at is None:
            return None
        pos = self._markers[0].pos()
        return pos.y() * 1e-3, pos.x() * 1e-3

    def data_pa(self) -> np.ndarray:
        """The array last shown, in Pa (NaN where there is no data)."""
        return self._data_kpa.astype(np.float64) / _KPA_PER_PA

    def view_mode(self) -> ViewMode:
        return self._mode

    def set_view_mode(self, mode: ViewMode) -> None:
        mode = ViewMode(mode)
        if mode == self._mode:
            return
        self._mode = mode
        button = self._cells if mode == ViewMode.CELLS else self._contour
        button.setChecked(True)
        self._iso.setEnabled(mode == ViewMode.CONTOUR)
        self._grid.setVisible(mode == ViewMode.CELLS)
        self._render()

    def iso_lines(self) -> bool:
        return self._iso.isChecked()

    def set_iso_lines(self, on: bool) -> None:
        """Overlay iso-lines in the contour view (remembered, but not drawn, in the cells view)."""
        self._iso.setChecked(on)

    def levels_pa(self) -> tuple[float, float]:
        """The colour range in Pa, whether following the data or locked."""
        lo, hi = self._levels_kpa
        return lo / _KPA_PER_PA, hi / _KPA_PER_PA

    def is_locked(self) -> bool:
        return self._locked

    def lock_levels(self, low_pa: float, high_pa: float) -> None:
        """Fix the colour range; raises ValueError unless low < high (both finite)."""
        if not (math.isfinite(low_pa) and math.isfinite(high_pa) and low_pa < high_pa):
            raise ValueError(f"{self._name} map: colour range needs finite min < max, got {low_pa!r} .. {high_pa!r}")
        self._set_spins(low_pa * _KPA_PER_PA, high_pa * _KPA_PER_PA)
        self._lock.setChecked(True)
        self._apply_levels((low_pa * _KPA_PER_PA, high_pa * _KPA_PER_PA))
        self._render()

    def unlock_levels(self) -> None:
        """Let the colour range follow the data again."""
        self._lock.setChecked(False)

    def auto_floor_pa(self) -> float:
        return self._floor_kpa / _KPA_PER_PA

    def set_auto_floor_pa(self, floor_pa: float) -> None:
        """The lowest top of the following colour range (the range is [0, max(data max, floor)])."""
        self._floor_kpa = self._checked_floor_kpa(floor_pa)
        if not self._locked:
            self._render()

    def _checked_floor_kpa(self, floor_pa: float) -> float:
        if not (math.isfinite(floor_pa) and floor_pa > 0):
            raise ValueError(f"{self._name} map: auto_floor_pa must be a finite value > 0, got {floor_pa!r}")
        return floor_pa * _KPA_PER_PA

    # ---- internals -----------------------------------------------------------------------------------

    def _lock_toggled(self, on: bool) -> None:
        self._locked = on
        self._min_spin.setEnabled(on)
        self._max_spin.setEnabled(on)
        self._level_error.hide()
        if not on:
            if np.isfinite(self._data_kpa).any():
                self._levels_kpa_follow()
            else:  # nothing to follow (no contact): the range starts again from the automatic floor
                self._apply_levels((0.0, self._floor_kpa))
            self._render()

    def _spin_changed(self) -> None:
        if not self._locked:
            return
        lo, hi = self._min_spin.value(), self._max_spin.value()
        if lo >= hi:
            self._level_error.setText(f"min {lo:g} kPa must be below max {hi:g} kPa")
            self._level_error.show()
            return
        self._level_error.hide()
        self._apply_levels((lo, hi))
        self._render()

    def _set_spins(self, lo_kpa: float, hi_kpa: float) -> None:
        for spin, value in ((self._min_spin, lo_kpa), (self._max_spin, hi_kpa)):
            was_blocked = spin.blockSignals(True)  # showing a range is not the operator typing one
            spin.setValue(value)
            spin.blockSignals(was_blocked)

    def _levels_kpa_follow(self) -> None:
        finite = self._data_kpa[np.isfinite(self._data_kpa)]
        if finite.size == 0:
            return  # nothing to follow: keep the last range
        self._apply_levels(auto_levels(float(finite.max()), self._levels_kpa, self._floor_kpa))

    def _apply_levels(self, levels_kpa: tuple[float, float]) -> None:
        if levels_kpa == self._levels_kpa:
            return
        self._levels_kpa = levels_kpa
        self._bar.setLevels(levels_kpa, update_items=False)
        if not self._locked:
            self._set_spins(*levels_kpa)

    def _render(self) -> None:
        contrast = self._contrast_on
        if contrast:
            data = self._contrast_pct if self._contrast_pct is not None else np.full((ROWS, COLS), np.nan, np.float32)
        else:
            data = self._data_kpa
        valid = np.isfinite(data)
        any_valid = bool(valid.any())
        if contrast:
            levels = tuple(v * _PCT for v in contrast_range(data / _PCT))
            self._bar.setLevels(levels, update_items=False)
        else:
            if not self._locked:
                self._levels_kpa_follow()
            levels = self._levels_kpa
        image = data if self._mode == ViewMode.CELLS else self._upsample(data, valid, any_valid)
        self._image.set_data(image, levels, self._rect)

        if not any_valid:
            text = "max —"
        elif contrast:
            text = f"max {float(data[valid].max()):+.0f} %"
        else:
            text = f"max {float(data[valid].max()):.1f} kPa"
        if text != self._max_text:
            self._max_text = text
            self._max_label.setText(text)
        why = NO_CONTRAST_TEXT if contrast and self._contrast_pct is None else self._no_data_text
        if why != self._no_data_label.textItem.toPlainText():
            self._no_data_label.setText(why)
        self._no_data_label.setVisible(not any_valid)
        spots = self.contrast_spots()
        if spots != self._spots_drawn:  # at display rate: redraw only what changed
            self._spots_drawn = spots
            pitch_mm = self._rect.height() / ROWS
            self._spot_item.setData([self._rect.left() + (j + 0.5) * pitch_mm for _, j in spots],
                                    [self._rect.top() + (i + 0.5) * pitch_mm for i, _ in spots])
            self._spot_item.setVisible(bool(spots))

        show_iso = self._mode == ViewMode.CONTOUR and self._iso.isChecked() and any_valid
        if show_iso:
            lo, hi = levels
            step = nice_step(hi - lo)
            levels = np.arange(math.floor(lo / step) + 1, math.ceil(hi / step)) * step
            pts = iso_segments(image, self._fine_y_mm, self._fine_x_mm, levels[(levels > lo) & (levels < hi)])
            self._iso_item.setData(pts[:, 0], pts[:, 1])
        self._iso_item.setVisible(show_iso)

    def _upsample(self, data: np.ndarray, valid: np.ndarray, any_valid: bool) -> np.ndarray:
        if not any_valid:
            return np.full((ROWS * UPSAMPLE, COLS * UPSAMPLE), np.nan, dtype=np.float32)
        filled = data
        if not valid.all():
            # Borrow each missing element's value from its nearest measured one, so the kernel sees no NaN;
            # those pixels are masked again below.
            nearest = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
            filled = data[tuple(nearest)]
        fine = self._wx @ filled @ self._wy.T
        np.clip(fine, filled.min(), filled.max(), out=fine)
        if not valid.all():
            fine[~valid[np.ix_(self._fine_to_cell_row, self._fine_to_cell_col)]] = np.nan
        return np.ascontiguousarray(fine, dtype=np.float32)
