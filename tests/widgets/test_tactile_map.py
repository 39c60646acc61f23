from __future__ import annotations

import numpy as np
import pytest
from PySide6 import QtCore, QtGui, QtWidgets

from widgets.colormaps import CONTOUR_COLORMAP, CONTOUR_LUT, NO_DATA_RGB
from widgets.tactile_map import (
    UPSAMPLE,
    TactileMapWidget,
    ViewMode,
    auto_levels,
    cubic_upsampling_matrix,
    iso_segments,
    nice_step,
)

ROWS, COLS = 4, 15


def hot_spot(peak_pa=30e3, base_pa=2e3, row=1.5, col=9.0):
    i, j = np.meshgrid(np.arange(ROWS), np.arange(COLS), indexing="ij")
    return base_pa + peak_pa * np.exp(-((i - row) ** 2 / 1.5 + (j - col) ** 2 / 4.0))


@pytest.fixture
def tmap(qtbot):
    widget = TactileMapWidget("Pressure")
    qtbot.addWidget(widget)
    widget.resize(900, 320)
    widget.show()
    qtbot.waitExposed(widget)
    return widget


def scene_item(widget, name):
    plot = widget.findChild(QtWidgets.QGraphicsView, "plot")
    found = [i for i in plot.scene().items() if isinstance(i, QtCore.QObject) and i.objectName() == name]
    assert len(found) == 1, f"expected one scene item named {name!r}, found {len(found)}"
    return found[0]


def pixel_at(widget, y_mm, x_mm) -> QtGui.QColor:
    """Colour of the rendered widget at sensor coordinates (y horizontal, x vertical), in mm."""
    plot = widget.findChild(QtWidgets.QGraphicsView, "plot")
    view = plot.getPlotItem().getViewBox()
    scene_pt = view.mapViewToScene(QtCore.QPointF(y_mm, x_mm))
    widget_pt = plot.mapTo(widget, plot.mapFromScene(scene_pt))
    image = widget.grab().toImage()
    ratio = image.devicePixelRatio()
    return image.pixelColor(int(widget_pt.x() * ratio), int(widget_pt.y() * ratio))


def element_centre_mm(i, j, pitch_mm=2.0):
    return (j - (COLS - 1) / 2) * pitch_mm, (i - (ROWS - 1) / 2) * pitch_mm


def close(colour: QtGui.QColor, rgb, tol=3):
    return all(abs(a - b) <= tol for a, b in zip((colour.red(), colour.green(), colour.blue()), rgb))


# ---- colour scale ----------------------------------------------------------------------------------------


def test_colour_scale_runs_from_blue_to_dark_red_and_avoids_the_no_data_grey():
    assert CONTOUR_LUT.shape == (256, 3) and CONTOUR_LUT.dtype == np.uint8
    low, high = CONTOUR_LUT[0], CONTOUR_LUT[-1]
    assert low[2] > 100 and low[0] == 0 and low[1] == 0  # blue
    assert 100 < high[0] < 160 and high[1] == 0 and high[2] == 0  # dark red
    brightest_red = CONTOUR_LUT[:, 0].argmax()
    assert CONTOUR_LUT[brightest_red, 0] == 255 and brightest_red < 255  # red comes before the dark end
    assert np.abs(CONTOUR_LUT.astype(int) - np.array(NO_DATA_RGB)).sum(axis=1).min() > 60
    assert np.array_equal(CONTOUR_COLORMAP.getLookupTable(nPts=256, alpha=False), CONTOUR_LUT)


# ---- pure helpers ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [4, 15])
def test_cubic_upsampling_keeps_constants_and_reproduces_ramps_between_the_edge_elements(n):
    w = cubic_upsampling_matrix(n, UPSAMPLE)
    assert w.shape == (n * UPSAMPLE, n)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)
    fine = (np.arange(n * UPSAMPLE) + 0.5) / UPSAMPLE - 0.5
    interior = (fine >= 1.0) & (fine <= n - 2.0)
    np.testing.assert_allclose((w @ np.arange(n, dtype=float))[interior], fine[interior], atol=1e-12)
    # Beyond the outer element centres the edge value is held, not extrapolated.
    assert np.all((w @ np.arange(n, dtype=float))[fine < 0] == 0.0)


def test_iso_segments_lie_on_their_level():
    ys = np.linspace(0.0, 30.0, 61)
    xs = np.linspace(0.0, 8.0, 17)
    field = ys[None, :] * 2.0 + xs[:, None]  # planar: bilinear crossings are exact
    pts = iso_segments(field, ys, xs, [10.0, 25.0])
    assert len(pts) > 0 and len(pts) % 2 == 0
    values = pts[:, 0] * 2.0 + pts[:, 1]
    assert np.all(np.isclose(values, 10.0) | np.isclose(values, 25.0))
    assert np.isclose(values, 10.0).any() and np.isclose(values, 25.0).any()


def test_iso_segments_close_around_a_peak_and_skip_nan_squares():
    ys = np.linspace(-15.0, 15.0, 121)
    xs = np.linspace(-4.0, 4.0, 33)
    field = np.exp(-(ys[None, :] ** 2 + xs[:, None] ** 2) / 8.0)
    pts = iso_segments(field, ys, xs, [0.5])
    radius = np.hypot(pts[:, 0], pts[:, 1])
    np.testing.assert_allclose(radius, np.sqrt(8.0 * np.log(2.0)), rtol=0.02)
    # A closed curve: every endpoint is shared by exactly two segments.
    _, counts = np.unique(np.round(pts, 9), axis=0, return_counts=True)
    assert np.all(counts == 2)
    field[:, ys > 0] = np.nan
    half = iso_segments(field, ys, xs, [0.5])
    assert len(half) > 0 and np.all(half[:, 0] <= ys[ys <= 0].max() + 1e-9)


def test_auto_levels_start_at_zero_round_out_hold_still_and_follow_big_changes():
    assert nice_step(40.0) == 10.0 and nice_step(7.0) == 2.0
    levels = auto_levels(36.6, None, floor=10.0)
    assert levels == (0.0, 40.0)
    assert auto_levels(31.0, levels, 10.0) == levels  # still reaches half the range: no flicker
    assert auto_levels(52.0, levels, 10.0) == (0.0, 60.0)  # outgrown: expand
    assert auto_levels(12.0, levels, 10.0) == (0.0, 15.0)  # much smaller: shrink
    assert auto_levels(0.3, None, 10.0) == (0.0, 10.0)  # noise alone is not stretched over the spectrum
    assert auto_levels(9.0, None, 45.0) == (0.0, 50.0)  # uniform light contact stays low on the scale
    assert auto_levels(np.float32(50e3 * 1e-3), None, 10.0) == (0.0, 50.0)  # float32 ulps


# ---- the widget ------------------------------------------------------------------------------------------


def test_bad_input_is_refused_with_a_clear_message(tmap):
    with pytest.raises(ValueError, match=r"Pressure map: expected a \(4, 15\) array .* got shape \(15, 4\)"):
        tmap.set_data(np.zeros((15, 4)))
    with pytest.raises(ValueError, match="expected numbers in Pa"):
        tmap.set_data(np.full((ROWS, COLS), "a"))
    with pytest.raises(ValueError, match="pitch_m must be > 0"):
        TactileMapWidget("Bad", pitch_m=0.0)
    with pytest.raises(ValueError, match="auto_floor_pa must be a finite value > 0"):
        tmap.set_auto_floor_pa(float("nan"))


def test_set_data_feeds_the_fast_path_in_kpa_without_new_items(tmap):
    image = scene_item(tmap, "mapImage")
    items_before = len(tmap.findChild(QtWidgets.QGraphicsView, "plot").scene().items())
    for k in range(5):
        data = hot_spot(peak_pa=20e3 + k * 1e3)
        tmap.set_data(data)
    assert scene_item(tmap, "mapImage") is image
    assert len(tmap.findChild(QtWidgets.QGraphicsView, "plot").scene().items()) == items_before
    assert image.image.dtype == np.float32 and image.image.flags.c_contiguous
    np.testing.assert_allclose(image.image, data / 1e3, rtol=1e-6)
    assert image.lut is CONTOUR_LUT or np.array_equal(image.lut, CONTOUR_LUT)
    # drawn as RGB32, the format the raster engine scales without converting it first
    assert image.qimage.format() == QtGui.QImage.Format.Format_RGB32
    lo, hi = tmap.levels_pa()
    assert tuple(image.levels) == pytest.approx((lo / 1e3, hi / 1e3))
    assert scene_item(tmap, "colorBar").levels() == pytest.approx((lo / 1e3, hi / 1e3))
    assert tmap.findChild(QtWidgets.QLabel, "maxLabel").text() == f"max {data.max() / 1e3:.1f} kPa"


def test_layout_puts_y_horizontal_and_x_vertical(tmap):
    data = np.zeros((ROWS, COLS))
    data[3, 14] = 50e3  # element at the largest x and the largest y
    tmap.set_data(data)
    hot_y, hot_x = element_centre_mm(3, 14)
    assert hot_y > 0 and hot_x > 0
    expected_hot = tuple(CONTOUR_LUT[-1])
    assert close(pixel_at(tmap, hot_y, hot_x), expected_hot)
    # y runs left to right and x bottom to top: the hot element is right of and above its mirror images.
    plot = tmap.findChild(QtWidgets.QGraphicsView, "plot")
    view = plot.getPlotItem().getViewBox()
    hot = view.mapViewToScene(QtCore.QPointF(hot_y, hot_x))
    cold = view.mapViewToScene(QtCore.QPointF(-hot_y, -hot_x))
    assert hot.x() > cold.x() and hot.y() < cold.y()
    width = view.mapViewToScene(QtCore.QPointF(15, 0)).x() - view.mapViewToScene(QtCore.QPointF(-15, 0)).x()
    height = view.mapViewToScene(QtCore.QPointF(0, -4)).y() - view.mapViewToScene(QtCore.QPointF(0, 4)).y()
    assert width / height == pytest.approx(30 / 8, rel=0.02)  # the real face's proportions


def test_nan_elements_are_drawn_as_no_data_not_as_zero(tmap):
    data = hot_spot()
    data[0, 0] = np.nan
    data[2, 3] = np.inf  # a broken reading is no data as well
    data[1, 1] = 0.0
    tmap.set_data(data)
    assert close(pixel_at(tmap, *element_centre_mm(0, 0)), NO_DATA_RGB)
    assert close(pixel_at(tmap, *element_centre_mm(2, 3)), NO_DATA_RGB)
    assert close(pixel_at(tmap, *element_centre_mm(1, 1)), tuple(CONTOUR_LUT[0]))
    assert np.isnan(tmap.data_pa()[2, 3])
    assert not scene_item(tmap, "noDataText").isVisible()


def test_an_empty_map_says_so_and_keeps_its_range(tmap):
    tmap.set_data(hot_spot())
    levels = tmap.levels_pa()
    tmap.set_data(np.full((ROWS, COLS), np.nan))
    assert scene_item(tmap, "noDataText").isVisible()
    assert tmap.findChild(QtWidgets.QLabel, "maxLabel").text() == "max —"
    assert tmap.levels_pa() == levels
    assert close(pixel_at(tmap, 0.0, -3.0), NO_DATA_RGB)


def test_contour_view_upsamples_keeps_no_data_and_draws_iso_lines(qtbot, tmap):
    data = hot_spot()
    data[:, :2] = np.nan
    tmap.set_data(data)
    iso_box = tmap.findChild(QtWidgets.QCheckBox, "isoLines")
    assert not iso_box.isEnabled()
    qtbot.mouseClick(tmap.findChild(QtWidgets.QRadioButton, "contourButton"), QtCore.Qt.MouseButton.LeftButton)
    assert tmap.view_mode() == ViewMode.CONTOUR
    assert not scene_item(tmap, "cellGrid").isVisible()
    image = scene_item(tmap, "mapImage")
    assert image.image.shape == (ROWS * UPSAMPLE, COLS * UPSAMPLE)
    assert image.image.dtype == np.float32 and image.image.flags.c_contiguous
    fine_nan = np.isnan(image.image)
    assert fine_nan[:, : 2 * UPSAMPLE].all() and not fine_nan[:, 2 * UPSAMPLE:].any()
    finite = image.image[~fine_nan]
    assert finite.min() * 1e3 >= np.nanmin(data) * (1 - 1e-6) and finite.max() * 1e3 <= np.nanmax(data) * (1 + 1e-6)
    assert close(pixel_at(tmap, *element_centre_mm(2, 0)), NO_DATA_RGB)
    # The image still covers exactly the sensing face after the change of resolution.
    assert image.mapRectToView(image.boundingRect()) == QtCore.QRectF(-15.0, -4.0, 30.0, 8.0)

    qtbot.mouseClick(iso_box, QtCore.Qt.MouseButton.LeftButton)
    curves = scene_item(tmap, "isoCurves")
    assert tmap.iso_lines() and curves.isVisible()
    x, y = curves.getData()
    assert len(x) > 0 and np.all(x >= -11.0)  # none inside the no-data columns (y < -11 mm)

    qtbot.mouseClick(tmap.findChild(QtWidgets.QRadioButton, "cellsButton"), QtCore.Qt.MouseButton.LeftButton)
    assert tmap.view_mode() == ViewMode.CELLS and not curves.isVisible() and not iso_box.isEnabled()
    assert scene_item(tmap, "mapImage").image.shape == (ROWS, COLS)
    assert image.mapRectToView(image.boundingRect()) == QtCore.QRectF(-15.0, -4.0, 30.0, 8.0)


def test_a_single_hot_element_is_not_exaggerated_by_the_contour(tmap):
    data = np.zeros((ROWS, COLS))
    data[1, 7] = 40e3
    tmap.set_data(data)
    tmap.set_view_mode(ViewMode.CONTOUR)
    fine = scene_item(tmap, "mapImage").image
    assert fine.min() >= 0.0 and fine.max() <= 40.0 + 1e-4


def type_value(qtbot, spin, text):
    spin.selectAll()
    qtbot.keyClicks(spin, text)
    qtbot.keyClick(spin, QtCore.Qt.Key.Key_Return)


def test_colour_range_follows_the_data_until_locked_and_typed_in(qtbot, tmap):
    lock = tmap.findChild(QtWidgets.QCheckBox, "lockRange")
    lo_spin = tmap.findChild(QtWidgets.QDoubleSpinBox, "levelMin")
    hi_spin = tmap.findChild(QtWidgets.QDoubleSpinBox, "levelMax")
    error = tmap.findChild(QtWidgets.QLabel, "levelError")
    tmap.set_data(hot_spot(peak_pa=22e3))
    assert tmap.levels_pa() == pytest.approx((0.0, 25e3))
    assert not lo_spin.isEnabled() and hi_spin.value() == pytest.approx(25.0)  # shows the automatic range
    tmap.set_data(hot_spot(peak_pa=70e3))
    assert tmap.levels_pa() == pytest.approx((0.0, 80e3))

    qtbot.mouseClick(lock, QtCore.Qt.MouseButton.LeftButton)
    assert tmap.is_locked() and lo_spin.isEnabled() and hi_spin.isEnabled()
    assert tmap.levels_pa() == pytest.approx((0.0, 80e3))  # locking keeps what is shown
    type_value(qtbot, hi_spin, "50")
    type_value(qtbot, lo_spin, "5")
    assert tmap.levels_pa() == pytest.approx((5e3, 50e3))
    tmap.set_data(hot_spot(peak_pa=120e3))
    assert tmap.levels_pa() == pytest.approx((5e3, 50e3))
    assert scene_item(tmap, "colorBar").levels() == pytest.approx((5.0, 50.0))

    type_value(qtbot, lo_spin, "60")
    assert error.isVisible() and "must be below max 50" in error.text()
    assert tmap.levels_pa() == pytest.approx((5e3, 50e3))
    type_value(qtbot, lo_spin, "10")
    assert not error.isVisible() and tmap.levels_pa() == pytest.approx((10e3, 50e3))

    qtbot.mouseClick(lock, QtCore.Qt.MouseButton.LeftButton)
    assert not tmap.is_locked()
    assert tmap.levels_pa() == pytest.approx((0.0, 150e3))  # 122 kPa rounded out to 50 kPa steps


def test_raising_the_floor_keeps_uniform_contact_low_on_the_scale(tmap):
    tmap.set_data(np.full((ROWS, COLS), 9e3))
    assert tmap.levels_pa() == pytest.approx((0.0, 10e3))
    tmap.set_auto_floor_pa(45e3)
    assert tmap.auto_floor_pa() == pytest.approx(45e3)
    assert tmap.levels_pa() == pytest.approx((0.0, 50e3))


def test_lock_levels_api_validates(tmap):
    with pytest.raises(ValueError, match="finite min < max"):
        tmap.lock_levels(20e3, 10e3)
    tmap.lock_levels(1e3, 9e3)
    assert tmap.is_locked() and tmap.levels_pa() == pytest.approx((1e3, 9e3))
    tmap.unlock_levels()
    assert not tmap.is_locked()


def test_the_contrast_view_blanks_the_elements_whose_expected_reading_is_too_uncertain(tmap):
    contrast = np.full((ROWS, COLS), 0.02)
    contrast[1, 7] = 0.12  # a tumour
    contrast[0, 2] = 0.84  # a face hanging off the tissue's end: known only to +-50 %
    sigma = np.full((ROWS, COLS), 0.03)
    sigma[0] = 0.5
    tmap.set_data(hot_spot())
    tmap.set_contrast_view(True)
    tmap.set_contrast(contrast, ((1, 7),), sigma)
    assert close(pixel_at(tmap, *element_centre_mm(0, 2)), NO_DATA_RGB)
    assert tmap.findChild(QtWidgets.QLabel, "maxLabel").text() == "max +12 %"  # the tumour, not the overhang
    assert not close(pixel_at(tmap, *element_centre_mm(1, 7)), NO_DATA_RGB)
    sigma[0, 2] = np.nan  # an uncertainty nobody knows is not a small one
    tmap.set_contrast(contrast, (), sigma)
    assert close(pixel_at(tmap, *element_centre_mm(0, 2)), NO_DATA_RGB)
    tmap.set_contrast(contrast)  # without an uncertainty every element is shown
    assert tmap.findChild(QtWidgets.QLabel, "maxLabel").text() == "max +84 %"
