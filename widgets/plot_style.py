"""How the console's pyqtgraph plots are set up and coloured, written once for every map and plot."""

from __future__ import annotations

from collections.abc import Iterable

import pyqtgraph as pg
from PySide6 import QtGui, QtWidgets

from widgets.colormaps import CONTOUR_LUT, NO_DATA_RGB

# One colour per quantity wherever it is drawn (the console's history, the reviewer's timeline), so a
# reviewer reads a trace as the operator saw it; chosen for the dark plot backgrounds both use.
F_DESIRED_COLOUR = (255, 163, 72)
F_MEASURED_COLOUR = (120, 220, 255)
DEPTH_COLOUR = (230, 140, 255)
RECORDED_COLOUR = (95, 211, 95)
LIMIT_COLOUR = (255, 107, 107)


def dark_palette() -> QtGui.QPalette:
    """The console's and the reviewer's one scheme: dark, as a console beside a robot in a dimmed lab is,
    and the background the trace colours above were chosen for."""
    palette = QtGui.QPalette()
    role, group = QtGui.QPalette.ColorRole, QtGui.QPalette.ColorGroup
    for r, colour in ((role.Window, "#1e1e1e"), (role.WindowText, "#ececec"), (role.Base, "#2a2a2a"),
                      (role.AlternateBase, "#323232"), (role.Text, "#ececec"), (role.Button, "#3a3a3a"),
                      (role.ButtonText, "#ececec"), (role.ToolTipBase, "#ffffe0"), (role.ToolTipText, "#000000"),
                      (role.Highlight, "#1f6fd1"), (role.HighlightedText, "#ffffff")):
        palette.setColor(r, QtGui.QColor(colour))
    for r in (role.WindowText, role.Text, role.ButtonText):
        palette.setColor(group.Disabled, r, QtGui.QColor("#7a7a7a"))
    return palette


def map_view(plot: pg.PlotWidget, bottom: str, left: str) -> pg.ViewBox:
    """A map's axes: labelled, square pixels, no context menu or auto-range button (a map has one scale)."""
    item = plot.getPlotItem()
    item.setMenuEnabled(False)
    item.hideButtons()
    item.setLabel("bottom", bottom)
    item.setLabel("left", left)
    view = item.getViewBox()
    view.setAspectLocked(True)
    return view


def add_map_layers(view: pg.ViewBox, image_name: str) -> tuple[QtWidgets.QGraphicsRectItem, pg.ImageItem]:
    """A grey no-data backdrop (place it with ``setRect``) under an image drawn in the contour scale."""
    no_data = QtWidgets.QGraphicsRectItem(0, 0, 1, 1)
    no_data.setBrush(pg.mkBrush(NO_DATA_RGB))
    no_data.setPen(pg.mkPen(None))
    no_data.setZValue(-10)
    view.addItem(no_data)
    image = pg.ImageItem(axisOrder="row-major")
    image.setObjectName(image_name)
    image.setLookupTable(CONTOUR_LUT)
    view.addItem(image)
    return no_data, image


def follow_palette(widget: QtWidgets.QWidget, plots: Iterable[pg.PlotWidget], axes: Iterable[pg.AxisItem],
                   background: QtGui.QPalette.ColorRole = QtGui.QPalette.ColorRole.Window) -> None:
    """Paint plots and axes in ``widget``'s Qt palette, so they sit in a dark or light window alike."""
    palette = widget.palette()
    text = palette.color(QtGui.QPalette.ColorRole.WindowText)
    for plot in plots:
        plot.setBackground(palette.color(background))
    for axis in axes:
        axis.setPen(pg.mkPen(text))
        axis.setTextPen(pg.mkPen(text))
