"""One orientation for every whole-tissue map (issue 50): x upwards and y to the right, as the live tactile maps
and the jog keys have it, in the console, the reviewer, ``stitch -o`` and the report.

Each view and picture is given one hot spot at a known (x, y) and the spot is looked for in the picture
itself: a surgeon who saw a tumour up and to the left on the console must find it up and to the left in the
reviewer and on paper.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PySide6 import QtGui, QtWidgets
from scipy import ndimage

from session.analysis import AnalysisParams
from session.stitch import Grid, LevelMap, StitchParams, StitchResult
from tests.widgets.test_console_fits import _pixels
from tests.widgets.test_panels import SENSOR, record
from widgets.colormaps import CONTOUR_LUT, lut_index
from widgets.map_painting import render_maps_png, write_report
from widgets.review.map_view import GridMapView
from widgets.tissue_view import WholeTissueView

EXTENT_M = (0.0, 0.072, 0.0, 0.030)
# high x, low y: near the top left corner when x is drawn upwards and y to the right
HOT_XY_M = (0.060, 0.006)
TOP_LEFT = (6 / 30, 1 - 60 / 72)  # where the spot is, as a share of the map's width and height from the top left
TALL = 30 / 72  # the map's width over its height


def _one_hot_spot() -> np.ndarray:
    """A 72 x 30 mm map of 1 mm cells, shaped (nx, ny): 1 everywhere, 10 on 3 x 3 cells around HOT_XY_M."""
    values = np.ones((72, 30))
    i, j = (round(v * 1e3) for v in HOT_XY_M)
    values[i - 1:i + 2, j - 1:j + 2] = 10.0
    return values


def _spot_in_map(image: QtGui.QImage, background, spot) -> tuple[float, float, float]:
    """Where the ``spot``-coloured pixels lie in the largest patch of ``background`` and ``spot`` colours (the
    map; a colour bar holds both colours too, but in a thin strip): (share of the patch's width from its left,
    share of its height from its top, its width over its height)."""
    pixels = _pixels(image).astype(int)

    def near(rgb) -> np.ndarray:
        return np.all(np.abs(pixels - np.asarray(rgb, dtype=int)) <= 24, axis=2)

    hot = near(spot)
    labels, count = ndimage.label(near(background) | hot)
    assert count, "no map in the picture"
    largest = 1 + int(np.argmax(np.bincount(labels.ravel())[1:]))
    rows, cols = np.nonzero(labels == largest)
    hot_rows, hot_cols = np.nonzero(hot & (labels == largest))
    assert hot_rows.size, "no hot spot in the map"
    width, height = cols.max() - cols.min() + 1, rows.max() - rows.min() + 1
    return ((hot_cols.mean() - cols.min()) / width, (hot_rows.mean() - rows.min()) / height, width / height)


def _assert_top_left(found, where=TOP_LEFT, aspect=TALL) -> None:
    across, down, shape = found
    assert shape == pytest.approx(aspect, rel=0.15), f"the map is {shape:.2f} as wide as tall, not {aspect:.2f}"
    assert (across, down) == (pytest.approx(where[0], abs=0.08), pytest.approx(where[1], abs=0.08)), (
        f"the hot spot is {across:.2f} across and {down:.2f} down the map, not {where[0]:.2f} and {where[1]:.2f}")


def test_the_console_draws_a_hot_spot_where_the_live_map_does(qtbot):
    """The reference the others follow: one area at x 36, y 15 mm with its hottest element at the top row
    (x + 3 mm) and the first column (y - 14 mm), as a live map draws it at its top left."""
    view = WholeTissueView(SENSOR, min_indentation_m=0.2e-3, pressure_floor_pa=20e3, stiffness_floor_pa=100e3,
                           extent_m=EXTENT_M)
    qtbot.addWidget(view)
    view.resize(500, 600)
    view.show()
    qtbot.waitExposed(view)
    palpated = record(0.036, 0, 1.0)
    pressure = palpated.pressure_pa.copy()
    pressure[3, 0] = 50e3
    view.add_record(dataclasses.replace(palpated, pressure_pa=pressure))
    view.refresh()
    levels = view.levels_shown()
    (background, hot), _ = lut_index(np.array([5.0, 50.0]), levels)
    plot = view.findChild(QtWidgets.QWidget, "tissuePlot")
    axes = plot.getPlotItem()
    assert (axes.getAxis("left").labelText, axes.getAxis("bottom").labelText) == ("x (mm)", "y (mm)")
    # the area is 8 mm along x by 30 along y; the element 1 mm from its left and 1 mm from its top
    _assert_top_left(_spot_in_map(plot.grab().toImage(), CONTOUR_LUT[background], CONTOUR_LUT[hot]),
                     where=(1 / 30, 1 / 8), aspect=30 / 8)


def test_the_reviewer_draws_x_upwards_and_y_to_the_right(qtbot):
    view = GridMapView("Whole tissue")  # as the reviewer makes its stitched and contrast maps
    qtbot.addWidget(view)
    view.resize(500, 600)
    view.show()
    qtbot.waitExposed(view)
    view.set_map(_one_hot_spot() * 1e3, EXTENT_M)
    plot = view.findChild(QtWidgets.QWidget, "plot")
    axes = plot.getPlotItem()
    assert (axes.getAxis("left").labelText, axes.getAxis("bottom").labelText) == ("x (mm)", "y (mm)")
    _assert_top_left(_spot_in_map(plot.grab().toImage(), CONTOUR_LUT[0], CONTOUR_LUT[-1]))


def _analysis() -> SimpleNamespace:
    """What the painters read of an analysis: one level whose force and stiffness maps have the hot spot."""
    values = _one_hot_spot()
    level = LevelMap(3.0, 0, np.arange(1), values * 1e3, values * 10e3, np.full(values.shape, 1e-3),
                     np.ones(values.shape), 4e-3)
    stitched = StitchResult(Grid(0.0, 0.0, 1e-3, 72, 30), StitchParams(), [level])
    session = SimpleNamespace(path=Path("flat.h5"), created_utc="2026-12-06T12:00:00+00:00", uuid="0", simulated=True,
                              phantom_name="flat", regions=lambda: [0], tissue_extent_m=EXTENT_M, warnings=[],
                              ground_truth=[], software_version="test")
    return SimpleNamespace(session=session, stitched=stitched, tumours=[], params=AnalysisParams(),
                           flat_field="none", has_ground_truth=False)


@pytest.mark.parametrize("write", [render_maps_png, write_report], ids=["stitch -o", "report"])
def test_the_exported_maps_draw_x_upwards_and_y_to_the_right(qapp, tmp_path, write):
    path = tmp_path / "maps.png"
    write(path, _analysis())
    _assert_top_left(_spot_in_map(QtGui.QImage(str(path)), CONTOUR_LUT[0], CONTOUR_LUT[-1]))


def test_the_reports_tables_give_every_cell_the_width_its_text_needs(qapp):
    # equal columns clipped the headers ("depth, model (m") and the model depths ("2.3 [1.1, 3.")
    from widgets.map_painting import TABLE_GAP_PX, table_columns

    normal = QtGui.QFont("DejaVu Sans")
    normal.setPixelSize(14)
    bold = QtGui.QFont(normal)
    bold.setBold(True)
    rows = [["true tumour", "x, y (mm)", "depth (mm)", "map", "found", "error (mm)", "depth, rule (mm)",
             "depth, model (mm)", "first level (N)"],
            ["1", "12.0, 15.0", "2.0", "stiffness", "not palpated", "0.1", "1.69", "10.5 [8.2, 12.0]", "1"]]
    width = 1116.0  # the report's table on an A4 page at 150 dpi
    widths, header_lines = table_columns(rows, normal, bold, width)
    assert sum(widths) == pytest.approx(width)
    body, head = QtGui.QFontMetricsF(normal), QtGui.QFontMetricsF(bold)
    for c, w in enumerate(widths):
        assert body.horizontalAdvance(rows[1][c]) <= w - TABLE_GAP_PX + 1e-6, rows[1][c]
        assert all(head.horizontalAdvance(word) <= w - TABLE_GAP_PX + 1e-6 for word in rows[0][c].split())
    assert header_lines in (1, 2)
