"""The console's panels on their own: history plots, contact figures, whole-tissue view, jog pad."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PySide6 import QtCore, QtWidgets

from control.messages import LevelRecord
from control.telemetry import TICK_DTYPE
from hardware.interfaces import TactileConstraints
from widgets.contact import ContactPanel, contact_metrics
from widgets.history_plots import KEEP_FRACTION, SAMPLE_HZ, HistoryPlots
from widgets.jog import JogPanel
from widgets.tissue_view import WholeTissueView

SENSOR = TactileConstraints()


def ticks(t0: float, seconds: float, force=1.0, depth_m=2e-3) -> np.ndarray:
    rows = np.zeros(int(round(seconds * 1000)), dtype=TICK_DTYPE)
    rows["t_s"] = t0 + np.arange(len(rows)) * 1e-3
    rows["tick"] = np.arange(len(rows))
    rows["force_desired_N"] = force
    rows["force_measured_N"] = force * 0.98
    rows["indentation_m"] = depth_m
    return rows


# ---- history plots ----------------------------------------------------------------------------------------


@pytest.fixture
def history(qtbot):
    plots = HistoryPlots(window_s=20.0, force_max_N=2.0, depth_limit_m=0.016)
    qtbot.addWidget(plots)
    plots.resize(600, 300)
    plots.show()
    qtbot.waitExposed(plots)
    return plots


def x_range(plots, name):
    return tuple(plots.findChild(QtWidgets.QWidget, name).getPlotItem().getViewBox().viewRange()[0])


def test_the_time_axis_stays_put_until_the_window_jumps(history):
    history.add_ticks(ticks(5000.0, 1.0))  # the loop clock is the host's: its zero means nothing
    assert history.time_origin_s() == 5000.0 and history.window_start_s() == 5000.0
    before = x_range(history, "forcePlot")
    for k in range(1, 19):
        history.add_ticks(ticks(5000.0 + k, 1.0))
        history.refresh()
        assert history.window_start_s() == 5000.0 and x_range(history, "forcePlot") == before
    assert x_range(history, "depthPlot") == before  # the two plots share the axis
    assert history.sample_count() == int(19 * SAMPLE_HZ)  # one sample per frame period, not per tick
    history.add_ticks(ticks(5019.0, 2.0))  # past the 20 s window: one jump, keeping its last quarter
    assert history.window_start_s() == 5000.0 + math.floor(20.999 - KEEP_FRACTION * 20.0)
    assert x_range(history, "forcePlot") == before
    labels = history.findChild(QtWidgets.QWidget, "depthPlot").getPlotItem().getAxis("bottom")._tickLevels[0]
    assert [text for _, text in labels][:2] == ["15", "20"]  # seconds since the first tick
    curve = [i for i in history.findChild(QtWidgets.QWidget, "forcePlot").scene().items()
             if isinstance(i, QtCore.QObject) and i.objectName() == "forceMeasuredCurve"][0]
    history.refresh()
    x, y = curve.getData()
    assert x.min() >= 0.0 and x.max() <= 20.0 and np.allclose(y, 0.98)


def test_a_new_controller_run_starts_the_plot_afresh(history):
    history.add_ticks(ticks(100.0, 2.0))
    history.mark_recorded(101.0, 1.0)
    history.add_ticks(ticks(3.0, 1.0))  # the clock went backwards: another run
    assert history.time_origin_s() == 3.0 and history.sample_count() == int(SAMPLE_HZ)


def test_the_axes_are_fixed_to_f_max_and_the_depth_ceiling(history):
    force = history.findChild(QtWidgets.QWidget, "forcePlot").getPlotItem().getViewBox().viewRange()[1]
    depth = history.findChild(QtWidgets.QWidget, "depthPlot").getPlotItem().getViewBox().viewRange()[1]
    assert force == pytest.approx([-0.072, 2.4]) and depth == pytest.approx([-0.528, 17.6])  # 3 % below 0: the label
    with pytest.raises(ValueError, match="F_max must be > 0"):
        history.set_force_max_N(0.0)
    with pytest.raises(ValueError, match="at least 2 s"):
        HistoryPlots(window_s=1.0)


# ---- contact figures --------------------------------------------------------------------------------------


def test_contact_figures_of_a_pressure_map():
    p = np.zeros((4, 15))
    p[1:3, 10:12] = 10e3  # four elements at rows 1-2, columns 10-11
    p[0, 0] = 200.0  # below the 300 Pa onset: not in contact
    m = contact_metrics(p, 300.0, SENSOR)
    assert m.elements == 4 and m.area_m2 == pytest.approx(16e-6)
    assert m.centre_m == pytest.approx((0.0, 7e-3))  # centres at y = +6 and +8 mm, x = +-1 mm
    assert m.peak_pa == 10e3 and m.peak_element == (1, 10)
    none = contact_metrics(np.zeros((4, 15)), 300.0, SENSOR)
    assert none.elements == 0 and none.centre_m is None
    assert math.isnan(contact_metrics(np.full((4, 15), np.nan), 300.0, SENSOR).peak_pa)
    with pytest.raises(ValueError, match=r"expected a \(4, 15\) pressure array"):
        contact_metrics(np.zeros((15, 4)), 300.0, SENSOR)


def test_contact_panel_shows_both_frames_of_the_centre(qtbot):
    panel = ContactPanel()
    qtbot.addWidget(panel)
    p = np.zeros((4, 15))
    p[1:3, 10:12] = 10e3
    panel.show_metrics(contact_metrics(p, 300.0, SENSOR), (0.020, 0.015, 0.024))
    centre = panel.findChild(QtWidgets.QLabel, "centreOfPressure").text()
    assert centre == "on the TSI   x +0.0   y +7.0 mm\non the tissue   x 20.0   y 22.0 mm"
    assert panel.findChild(QtWidgets.QLabel, "contactArea").text() == "16 mm²  (4 el.)"


# ---- whole-tissue view ------------------------------------------------------------------------------------


def record(x_m, level, force_N, stiffness_pa=40e3, region=0):
    p = np.full((4, 15), 5e3 * force_N)
    return LevelRecord(region=region, level=level, t_s=float(level), force_desired_N=force_N,
                       force_measured_N=force_N, rmse_N=0.01, settle_time_s=0.5,
                       tsi_position_m=(x_m, 0.015, 0.024), indentation_m=1e-3, pressure_pa=p,
                       pressure_std_pa=np.full((4, 15), 50.0), window_frames=30, element_force_N=p * 4e-6,
                       onset_height_m=np.full((4, 15), 0.025),
                       L0_m=np.full((4, 15), 0.025), dL_m=np.full((4, 15), 1e-3),
                       stiffness_pa=np.full((4, 15), stiffness_pa))


@pytest.fixture
def tissue(qtbot):
    view = WholeTissueView(SENSOR, min_indentation_m=0.2e-3, pressure_floor_pa=20e3, stiffness_floor_pa=100e3,
                           extent_m=(0.0, 0.072, 0.0, 0.030), areas=((0.004, 0.015), (0.012, 0.015)))
    qtbot.addWidget(view)
    view.resize(500, 300)
    view.show()
    qtbot.waitExposed(view)
    return view


def test_the_tissue_view_fills_in_area_by_area(tissue):
    summary = tissue.findChild(QtWidgets.QLabel, "tissueSummary")
    assert tissue.shown_values() is None and summary.text() == "no area palpated yet"
    tissue.add_record(record(0.004, 0, 1.0, region=0))
    tissue.add_record(record(0.004, 1, 2.0, region=0))
    tissue.refresh()
    assert tissue.level_force_N() == 2.0  # follows the highest level
    first = tissue.shown_values()
    assert summary.text().startswith("2 levels recorded in 1 area · 11 % of the phantom covered at 2 N")
    tissue.add_record(record(0.012, 0, 1.0, region=1))
    tissue.add_record(record(0.012, 1, 2.0, region=1))
    tissue.refresh()
    grown = tissue.shown_values()
    assert np.count_nonzero(np.isfinite(grown)) == 2 * np.count_nonzero(np.isfinite(first))
    assert "4 levels recorded in 2 areas · 22 % of the phantom" in summary.text()
    # Eq. 1 again from the recorded force, L0 and dL: F L0 / (A dL) = p L0 / dL
    tissue.set_quantity("stiffness_pa")
    expected = 10e3 * 0.025 / 1e-3
    assert np.nanmax(tissue.shown_values()) == pytest.approx(expected)
    assert tissue.levels_shown()[1] >= expected / 1e3
    tissue.set_level_force_N(1.0)
    assert tissue.level_force_N() == 1.0
    tissue.set_quantity("coverage")
    assert np.nanmax(tissue.shown_values()) == pytest.approx(1.0)
    assert tissue.levels_shown() == (0.0, 2.0)
    with pytest.raises(ValueError, match="unknown whole-tissue map"):
        tissue.set_quantity("temperature")


def test_the_tsi_footprint_follows_the_probe_and_a_double_click_asks_to_move(qtbot, tissue):
    assert tissue.footprint_rect_mm() is None
    tissue.set_tsi_position(0.020, 0.015)
    # drawn like the live maps: 30 mm along y across the screen, 8 mm along x up it
    assert tissue.footprint_rect_mm() == QtCore.QRectF(0.0, 16.0, 30.0, 8.0)
    plot = tissue.findChild(QtWidgets.QGraphicsView, "tissuePlot")
    view = plot.getPlotItem().getViewBox()
    point = plot.mapFromScene(view.mapViewToScene(QtCore.QPointF(12.0, 40.0)))  # y = 12 mm, x = 40 mm
    with qtbot.waitSignal(tissue.move_requested) as moved:
        # a real double click: press, release, press + double-click, release (pyqtgraph reports on release)
        qtbot.mouseClick(plot.viewport(), QtCore.Qt.MouseButton.LeftButton, pos=point)
        qtbot.mouseDClick(plot.viewport(), QtCore.Qt.MouseButton.LeftButton, pos=point)
        qtbot.mouseRelease(plot.viewport(), QtCore.Qt.MouseButton.LeftButton, pos=point)
    assert moved.args == [pytest.approx(0.040, abs=0.3e-3), pytest.approx(0.012, abs=0.3e-3)]


# ---- jog pad ----------------------------------------------------------------------------------------------


def test_the_jog_pad_steps_and_holding_a_button_does_not_queue_moves(qtbot):
    pad = JogPanel(jog_speed_m_s=0.01)
    qtbot.addWidget(pad)
    sent = []
    pad.jog_requested.connect(lambda *d: sent.append(d))
    pad.set_unavailable(None)
    pad.set_step_mm(2.0)
    assert pad.step("jogZMinus") and sent == [(0.0, 0.0, -2e-3)]
    assert not pad.step("jogZMinus")  # 2 mm take 0.2 s at 10 mm/s: a repeat before that is dropped
    button = pad.findChild(QtWidgets.QPushButton, "jogYPlus")
    assert button.autoRepeat() and button.autoRepeatInterval() == 200
    pad.set_unavailable("a fault holds the robot")
    assert not button.isEnabled() and not pad.step("jogYPlus")
    with pytest.raises(ValueError, match="not one of"):
        pad.set_step_mm(3.0)


# ---- colour image ------------------------------------------------------------------------------------------


def test_colour_values_follow_the_lookup_table_and_grey_out_no_data():
    from widgets.colormaps import CONTOUR_LUT, NO_DATA_RGB
    from widgets.colour_image import colour_values

    values = np.array([[0.0, 25.0, 50.0, np.nan, -5.0, 80.0]], dtype=np.float32)
    pixels = colour_values(values, (0.0, 50.0))

    def rgb(p):
        return (int(p) >> 16) & 0xFF, (int(p) >> 8) & 0xFF, int(p) & 0xFF

    assert [rgb(p) for p in pixels[0]] == [tuple(CONTOUR_LUT[0]), tuple(CONTOUR_LUT[128]), tuple(CONTOUR_LUT[255]),
                                           NO_DATA_RGB, tuple(CONTOUR_LUT[0]), tuple(CONTOUR_LUT[255])]
    assert all(int(p) >> 24 == 0xFF for p in pixels[0])  # opaque


def test_screen_and_exported_images_colour_a_value_alike():
    """One mapping from values to colours: the live maps' RGB32 pixels and an exported map's RGB agree."""
    from widgets.colormaps import map_rgb
    from widgets.colour_image import colour_values

    rng = np.random.default_rng(3)
    values = rng.uniform(-10.0, 110.0, size=(13, 7))
    values[2, 3] = np.nan
    pixels = colour_values(values, (0.0, 100.0))
    live = np.stack([(pixels >> 16) & 0xFF, (pixels >> 8) & 0xFF, pixels & 0xFF], axis=-1).astype(np.uint8)
    exported = map_rgb(values, 0.0, 100.0)  # (nx, ny) with x upwards
    np.testing.assert_array_equal(exported, live[::-1])
