"""A colour map of any rectangular grid in the tissue frame: stitched whole-tissue maps and per-element maps
whose unit is not a pressure (the indentation, in mm).

x runs upwards and y to the right, in mm, with the real aspect ratio: the one orientation of every
whole-tissue map, the console's, the exported images' and the report's (:mod:`widgets.tissue_view` says
why), so a tumour the surgeon saw up and to the left on the console is up and to the left here. The colour
range is the map's own [2nd percentile, maximum] (see :func:`widgets.colormaps.colour_range`), or for a
contrast map a range symmetric about healthy tissue (:func:`widgets.colormaps.contrast_range`), the same as
in the exported images, so a spot looks alike on screen and on paper. Cells without a value are drawn in
the no-data grey.
Markers: white rings (found tumours), dashed dark circles of the true size (a simulated phantom's tumours).
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from widgets.colormaps import CONTOUR_COLORMAP, colour_range, contrast_range
from widgets.plot_style import add_map_layers, follow_palette, map_view

FOUND_RING_MM = 6.0


class GridMapView(QtWidgets.QWidget):
    """``set_map(values, extent_m)`` with values shaped (nx, ny), first index along x, drawn x upwards and y
    to the right, as every map of the console is.

    Child objectNames: ``title``, ``plot``; graphics items: ``mapImage``, ``foundMarkers``, ``truthMarkers``,
    ``colorBar``.
    """

    def __init__(self, title: str, unit: str = "kPa", scale: float = 1e-3,
                 contrast: bool = False, on_tsi: bool = False, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self._unit, self._scale = unit, scale
        self._range = contrast_range if contrast else colour_range
        self._values = np.full((1, 1), np.nan)
        self._title = QtWidgets.QLabel(title, objectName="title")
        font = self._title.font()
        font.setBold(True)
        self._title.setFont(font)
        # a long title wraps rather than widening the window past a laptop's screen
        self._title.setWordWrap(True)
        self._title.setMinimumWidth(200)

        self._plot = pg.PlotWidget()
        self._plot.setObjectName("plot")
        item = self._plot.getPlotItem()
        # ``on_tsi``: coordinates from the TSI's centre, named as the live tactile maps name them
        y_name = "y on the TSI (mm)" if on_tsi else "y (mm)"
        self._view = map_view(self._plot, y_name, "x (mm)")
        self._no_data, self._image = add_map_layers(self._view, "mapImage")
        self._truth = pg.ScatterPlotItem(pxMode=False, brush=None,
                                         pen=pg.mkPen((20, 20, 20), width=2, style=QtCore.Qt.PenStyle.DashLine))
        self._truth.setObjectName("truthMarkers")
        self._truth.setZValue(5)
        self._view.addItem(self._truth)
        self._found = pg.ScatterPlotItem(pxMode=False, brush=None, pen=pg.mkPen("w", width=3))
        self._found.setObjectName("foundMarkers")
        self._found.setZValue(6)
        self._view.addItem(self._found)
        self._bar = pg.ColorBarItem(values=(0.0, 1.0), colorMap=CONTOUR_COLORMAP, label=unit, interactive=False,
                                    colorMapMenu=False, width=16)
        self._bar.setObjectName("colorBar")
        item.layout.addItem(self._bar, 2, 5)

        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(2, 2, 2, 2)
        layout.addWidget(self._title)
        layout.addWidget(self._plot, 1)
        self._apply_palette()

    def _apply_palette(self) -> None:
        follow_palette(self, [self._plot], [])

    def set_title(self, text: str) -> None:
        self._title.setText(text)

    def set_unit(self, unit: str, scale: float) -> None:
        """Values arrive in SI units and are shown multiplied by ``scale`` in ``unit`` (e.g. "mm", 1e3)."""
        self._unit, self._scale = unit, scale
        self._bar.getAxis("left").setLabel(unit)  # where ColorBarItem puts its label

    def levels(self) -> tuple[float, float]:
        """The colour range, in SI units."""
        lo, hi = self._bar.levels()
        return lo / self._scale, hi / self._scale

    def values(self) -> np.ndarray:
        """The map last shown, in SI units, shaped (nx, ny)."""
        return self._values

    def set_map(self, values: np.ndarray, extent_m: tuple[float, float, float, float]) -> None:
        values = np.asarray(values, dtype=float)
        if values.ndim != 2:
            raise ValueError(f"{self._title.text()}: expected a 2-D map, got shape {values.shape}")
        x0, x1, y0, y1 = (v * 1e3 for v in extent_m)
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"{self._title.text()}: empty extent {extent_m}")
        self._values = values
        lo, hi = self._range(values)
        # row-major images put their first index upwards: (nx, ny) draws x upwards
        image = np.ascontiguousarray(values * self._scale, dtype=np.float32)
        rect = QtCore.QRectF(y0, x0, y1 - y0, x1 - x0)
        self._image.setImage(image, autoLevels=False, levels=(lo * self._scale, hi * self._scale), rect=rect)
        self._no_data.setRect(rect)
        self._bar.setLevels((lo * self._scale, hi * self._scale), update_items=False)
        self._view.setRange(rect, padding=0.02)

    def set_markers(self, found_xy_m: list[tuple[float, float]], truth: list[tuple[float, float, float]]) -> None:
        """Found tumours at (x, y); true tumours at (x, y, diameter), all in m."""
        def screen(points):
            return [(y * 1e3, x * 1e3) for x, y, *_ in points]

        found = screen(found_xy_m)
        self._found.setData([p[0] for p in found], [p[1] for p in found], size=FOUND_RING_MM, symbol="o")
        if truth:
            shown = screen(truth)
            self._truth.setData([p[0] for p in shown], [p[1] for p in shown], size=[d * 1e3 for _, _, d in truth],
                                symbol="o")
        else:
            self._truth.setData([], [])

    def marker_counts(self) -> tuple[int, int]:
        """(found, truth) markers shown."""
        return len(self._found.data), len(self._truth.data)

    def clear(self) -> None:
        self._values = np.full((1, 1), np.nan)
        self._image.clear()
        self.set_markers([], [])

    def changeEvent(self, event: QtCore.QEvent) -> None:
        if event.type() == QtCore.QEvent.Type.PaletteChange:
            self._apply_palette()
        super().changeEvent(event)
