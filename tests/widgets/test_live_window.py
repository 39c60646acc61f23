"""The console window against a scripted controller: exact snapshots in, exact readouts and commands out.

The fast-forward tests (test_console.py) show the same window working against the real loop; these pin
down what each figure shows for a given tick, event or frame.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from PySide6 import QtCore, QtGui, QtWidgets

from control.autopilot import Area, AutopilotPlan
from control.config import ControlConfig, RampSettings, SafetyLimits
from control.messages import (
    ClearFault,
    CommandApplied,
    CommandRefused,
    EStop,
    FaultCleared,
    FaultKind,
    FaultRaised,
    Jog,
    LevelRecord,
    LevelRecorded,
    Notice,
    SetRamp,
    SetSz,
)
from control.telemetry import LiveSnapshot, LoopHealth, empty_frame, empty_tick
from hardware.interfaces import Phase, TactileConstraints
from widgets.findings_table import FindingsPanel, FindingsTable
from widgets.flowchart import LevelLadder
from widgets.health import HealthPanel
from widgets.history_plots import HistoryPlots
from widgets.live_window import LiveWindow
from widgets.messages import MessagesPane
from widgets.sz_switch import SzSwitch
from widgets.tactile_map import TactileMapWidget, ViewMode
from widgets.tissue_view import WholeTissueView


class FakeController(QtCore.QObject):
    """The members LiveWindow uses of app.bridge.ControllerBridge."""

    snapshot = QtCore.Signal(object)
    started = QtCore.Signal()
    stopped = QtCore.Signal()
    crashed = QtCore.Signal(str)
    silent = QtCore.Signal(float)
    answering = QtCore.Signal(float)

    def __init__(self):
        super().__init__()
        self.sent = []

    def send(self, command):
        self.sent.append(command)


def make_tick(**fields):
    tick = empty_tick()
    tick["sz"] = 1
    tick["x_des_m"] = tick["x_slave_m"] = (0.036, 0.015, 0.06)
    tick["master_age_s"] = np.nan  # no master device: the console jogs
    tick["sensor_age_s"] = 0.004
    tick["slave_age_s"] = 0.001
    tick["force_measured_N"] = 0.0
    for name, value in fields.items():
        tick[name] = value
    return tick


def make_frame(seq=1, peak_pa=30e3):
    frame = empty_frame()
    frame["sensor_seq"] = seq
    frame["tsi_position_m"] = (0.036, 0.015, 0.027)
    i, j = np.meshgrid(np.arange(4), np.arange(15), indexing="ij")
    frame["pressure_pa"] = 1e3 + peak_pa * np.exp(-((i - 1.5) ** 2 + (j - 9.0) ** 2 / 3.0))
    stiffness = np.full((4, 15), 25e3, dtype=np.float32)
    stiffness[:, :3] = np.nan  # not in contact
    frame["stiffness_pa"] = stiffness
    return frame


def make_record(region=0, level=0, force=1.0, x=0.012):
    p = np.full((4, 15), 5e3)
    return LevelRecord(region=region, level=level, t_s=2.0 + level, force_desired_N=force, force_measured_N=force,
                       rmse_N=0.02, settle_time_s=0.6, tsi_position_m=(x, 0.015, 0.024),
                       indentation_m=1e-3 * (1 + level),
                       pressure_pa=p, pressure_std_pa=np.full((4, 15), 50.0), window_frames=30,
                       element_force_N=p * 4e-6, onset_height_m=np.full((4, 15), 0.025),
                       L0_m=np.full((4, 15), 0.025), dL_m=np.full((4, 15), 1e-3 * (1 + level)),
                       stiffness_pa=np.full((4, 15), 40e3))


HEALTH = LoopHealth(rate_hz=999.6, late_over_0_5ms_pct=0.42, p99_abs_jitter_us=41.0, missed_ticks=3,
                    longest_stall_ms=4.5, rt_priority=False, cpu=1)
PLAN = AutopilotPlan((Area(0, 0.004, 0.015, 0.028), Area(1, 0.012, 0.015, 0.028)), travel_z_m=0.045,
                     jog_speed_m_s=0.01, phantom_extent_m=(0.0, 0.072, 0.0, 0.030))
CONFIG = ControlConfig(ramp=RampSettings(rmse_threshold_N=0.1))


@pytest.fixture
def settings(tmp_path):
    return QtCore.QSettings(str(tmp_path / "console.ini"), QtCore.QSettings.Format.IniFormat)


@pytest.fixture
def controller():
    return FakeController()


def open_window(qtbot, controller, settings, **kwargs) -> LiveWindow:
    kwargs.setdefault("config", CONFIG)
    win = LiveWindow(controller, settings=settings, **kwargs)
    qtbot.addWidget(win)
    win.show()
    qtbot.waitExposed(win)
    win.activateWindow()
    qtbot.waitUntil(win.isActiveWindow)
    return win


@pytest.fixture
def window(qtbot, controller, settings):
    return open_window(qtbot, controller, settings, plan=PLAN)


def push(controller, tick, frame=None, events=(), health=None):
    controller.snapshot.emit(LiveSnapshot(tick=tick, frame=frame, ticks=tick[None], events=list(events),
                                          health=health))


def label(win, name) -> QtWidgets.QLabel:
    found = win.findChild(QtWidgets.QLabel, name)
    assert found is not None, f"no QLabel named {name!r}"
    return found


def button(win, name) -> QtWidgets.QPushButton:
    found = win.findChild(QtWidgets.QPushButton, name)
    assert found is not None, f"no QPushButton named {name!r}"
    return found


def test_readouts_follow_the_snapshot(window, controller):
    assert label(window, "forceDesired").text() == "—"
    push(controller, make_tick(phase=Phase.SETTLING, sz=0, level=2, n_levels=7, force_desired_N=3.0,
                               force_measured_N=2.968, rmse_N=0.042, indentation_m=2.4e-3))
    assert label(window, "phaseLabel").text() == "SETTLING"
    assert label(window, "levelLabel").text() == "level 3 of 7: F_d 3.00 N"
    assert label(window, "rmseLabel").text() == "RMSE 0.042 N < ε 0.100 N"
    assert label(window, "forceDesired").text() == "3.00 N"
    assert label(window, "forceMeasured").text() == "2.97 N"
    assert label(window, "indentation").text() == "2.4 mm"
    push(controller, make_tick(force_measured_N=-0.003))  # sensor noise in air
    assert label(window, "forceMeasured").text() == "0.00 N"
    push(controller, make_tick(force_measured_N=-0.02))
    assert label(window, "forceMeasured").text() == "-0.02 N"
    push(controller, make_tick(phase=Phase.SETTLING, sz=0, level=2, n_levels=7, force_desired_N=3.0,
                               force_measured_N=2.968, rmse_N=0.042, indentation_m=2.4e-3))
    ladder = window.findChild(LevelLadder, "levelLadder")
    assert ladder.recorded() == 2 and ladder.current() == 2  # levels 1 and 2 recorded, 3 settling

    push(controller, make_tick(phase=Phase.SETTLING, sz=0, level=2, n_levels=7, rmse_N=0.25))
    assert label(window, "rmseLabel").text() == "RMSE 0.250 N ≥ ε 0.100 N"
    window.set_ramp(RampSettings(rmse_threshold_N=0.3))
    push(controller, make_tick(phase=Phase.SETTLING, sz=0, level=2, n_levels=7, rmse_N=0.25))
    assert label(window, "rmseLabel").text() == "RMSE 0.250 N < ε 0.300 N"

    push(controller, make_tick(phase=Phase.RETRACT, level=-1, n_levels=7))  # ended early: an abort
    assert label(window, "levelLabel").text() == "2 of 7 recorded, not finished"
    assert ladder.recorded() == 2 and ladder.current() is None
    push(controller, make_tick(phase=Phase.APPROACH))
    assert label(window, "phaseLabel").text() == "APPROACH"
    assert label(window, "rmseLabel").text() == "ε 0.300 N"
    assert label(window, "indentation").text() == "no contact"


def test_region_done_is_unmistakable(window, controller):
    done = label(window, "regionDone")
    push(controller, make_tick(phase=Phase.SETTLING, sz=0, level=6, n_levels=7))
    assert done.property("done") is False and "REGION DONE" not in done.text()
    push(controller, make_tick(phase=Phase.DONE, sz=1, region_done=1, level=-1, n_levels=7))
    assert done.property("done") is True and "REGION DONE" in done.text()
    assert label(window, "phaseLabel").text() == "DONE"
    assert label(window, "levelLabel").text() == "all 7 levels recorded"
    assert window.findChild(LevelLadder, "levelLadder").recorded() == 7
    push(controller, make_tick(phase=Phase.SEEK_CONTACT, sz=0, region_done=0, level=0, n_levels=7))
    assert done.property("done") is False
    assert window.findChild(LevelLadder, "levelLadder").recorded() == 0


def test_sz_switch_sends_a_request_and_shows_only_the_reported_state(qtbot, window, controller):
    switch = window.findChild(SzSwitch, "szSwitch")
    position, force = button(window, "szPosition"), button(window, "szForce")
    assert switch.state() is None and not force.isEnabled()  # nothing reported yet: nothing to toggle
    qtbot.keyClick(window, QtCore.Qt.Key.Key_S)
    assert controller.sent == []

    push(controller, make_tick(sz=1))
    assert switch.state() is True and position.property("active") is True and force.property("active") is False
    qtbot.mouseClick(force, QtCore.Qt.MouseButton.LeftButton)
    assert controller.sent == [SetSz(position_control=False)]
    assert switch.state() is True and force.property("pending") is True
    push(controller, make_tick(sz=0, phase=Phase.SEEK_CONTACT))
    assert switch.state() is False and switch.pending() is None and force.property("active") is True

    qtbot.keyClick(window, QtCore.Qt.Key.Key_S)
    assert controller.sent[-1] == SetSz(position_control=True)
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Space)  # Space must not toggle S_z next to a robot
    assert len(controller.sent) == 2


def test_emergency_stop_from_button_and_escape(qtbot, window, controller):
    qtbot.mouseClick(button(window, "estopButton"), QtCore.Qt.MouseButton.LeftButton)
    assert controller.sent == [EStop()]
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Escape)
    assert controller.sent == [EStop(), EStop()]


def test_fault_banner_shows_the_explanation_and_clears(qtbot, window, controller):
    banner = window.findChild(QtWidgets.QFrame, "faultBanner")
    assert not banner.isVisible()
    message = "F_ts 12.4 N exceeded the 12.0 N ceiling; robot held"
    push(controller, make_tick(phase=Phase.HOLD, fault=FaultKind.FORCE_CEILING),
         events=[FaultRaised(1.0, FaultKind.FORCE_CEILING, message)])
    assert banner.isVisible()
    assert label(window, "faultText").text() == f"FAULT: force ceiling — {message}"
    assert label(window, "phaseLabel").text() == "HOLD"
    assert window.messages().severities()[-1] == "error" and message in window.messages().lines()[-1]
    qtbot.mouseClick(button(window, "clearFault"), QtCore.Qt.MouseButton.LeftButton)
    assert controller.sent == [ClearFault()]
    push(controller, make_tick(phase=Phase.HOLD, fault=FaultKind.FORCE_CEILING))  # still held
    assert banner.isVisible()
    push(controller, make_tick(phase=Phase.APPROACH, fault=0), events=[FaultCleared(2.0, FaultKind.FORCE_CEILING)])
    assert not banner.isVisible()
    # A fault whose event was not seen still names its kind.
    push(controller, make_tick(phase=Phase.HOLD, fault=FaultKind.SENSOR_STALE))
    assert banner.isVisible() and label(window, "faultText").text() == "FAULT: sensor stale"


def test_a_stopped_controller_is_shown_as_a_fault_that_cannot_be_cleared(window, controller):
    push(controller, make_tick())
    controller.crashed.emit("The controller process stopped unexpectedly (killed by SIGKILL)")
    banner = window.findChild(QtWidgets.QFrame, "faultBanner")
    assert banner.isVisible() and "CONTROLLER STOPPED" in label(window, "faultText").text()
    assert "SIGKILL" in label(window, "faultText").text()
    assert not button(window, "clearFault").isVisible()
    assert not button(window, "tareButton").isEnabled() and not button(window, "jogXPlus").isEnabled()


def test_a_controller_that_stops_answering_is_shown_as_such_and_the_health_line_follows(window, controller):
    """Issue 49: a controller stopped with SIGSTOP during force control was shown for 12.5 s as FORCE,
    SETTLING and a green "Loop OK · 1000 Hz"; after SIGKILL the banner was right but the health line still
    said OK."""
    calm = LoopHealth(rate_hz=1000.0, late_over_0_5ms_pct=0.05, p99_abs_jitter_us=30.0, missed_ticks=0,
                      longest_stall_ms=0.0, rt_priority=True, cpu=1)
    push(controller, make_tick(), health=calm)
    assert window.findChild(QtWidgets.QLabel, "healthChip").property("level") == "good"
    controller.silent.emit(0.08)
    banner = window.findChild(QtWidgets.QFrame, "faultBanner")
    assert banner.isVisible() and label(window, "faultText").text().startswith("CONTROLLER NOT ANSWERING — no "
                                                                              "report for 80 ms")
    chip, line = label(window, "healthChip"), label(window, "loopHealth")
    assert chip.property("level") == "bad" and "controller not answering for 80 ms" in chip.text()
    assert "controller not answering" in line.text() and "Loop OK" not in line.text()
    assert not button(window, "jogXPlus").isEnabled() and not button(window, "tareButton").isEnabled()
    controller.answering.emit(0.3)
    assert not banner.isVisible() and chip.property("level") == "good"
    assert "answers again, after 300 ms" in window.messages().lines()[-1]
    controller.crashed.emit("The controller process stopped unexpectedly (killed by SIGKILL)")
    assert chip.property("level") == "bad" and "controller stopped" in line.text()


def test_maps_show_new_frames_only_with_the_contact_figures(window, controller):
    pressure = window.findChild(TactileMapWidget, "pressureMap")
    stiffness = window.findChild(TactileMapWidget, "stiffnessMap")
    assert np.isnan(pressure.data_pa()).all()  # before the first frame: no data, not zeros
    frame = make_frame(seq=5)
    push(controller, make_tick(), frame=frame)
    np.testing.assert_allclose(pressure.data_pa(), frame["pressure_pa"], rtol=1e-6)
    shown_stiffness = stiffness.data_pa()
    assert np.isnan(shown_stiffness[:, :3]).all()
    np.testing.assert_allclose(shown_stiffness[:, 3:], 25e3, rtol=1e-6)
    # every element is above the 900 Pa confirm threshold: the whole face is in contact
    assert label(window, "contactArea").text() == "240 mm²  (60 el.)"
    assert label(window, "peakPressure").text() == f"{frame['pressure_pa'].max() / 1e3:.1f} kPa"
    p = frame["pressure_pa"].astype(float)
    offsets = TactileConstraints().element_offsets_m()
    expected = (p[..., None] * offsets).sum(axis=(0, 1)) / p.sum()
    assert pressure.marker_m() == pytest.approx(tuple(expected), abs=0.05e-3)  # the cross sits at the centre
    assert expected[1] > 2e-3  # pulled towards the hot spot at column 9 of 15
    assert "on the tissue" in label(window, "centreOfPressure").text()

    same_seq = make_frame(seq=5, peak_pa=90e3)  # a snapshot repeating the frame it already showed
    push(controller, make_tick(), frame=same_seq)
    np.testing.assert_allclose(pressure.data_pa(), frame["pressure_pa"], rtol=1e-6)
    newer = make_frame(seq=6, peak_pa=90e3)
    push(controller, make_tick(), frame=newer)
    np.testing.assert_allclose(pressure.data_pa(), newer["pressure_pa"], rtol=1e-6)


def test_in_the_air_the_pressure_map_is_the_grey_no_contact_state_not_a_dark_blue_one(window, controller):
    # issue 13: no contact showed a dark-blue map reading "max 0.1 kPa", the array's own noise
    pressure = window.findChild(TactileMapWidget, "pressureMap")
    air = make_frame(seq=7, peak_pa=0.0)
    air["pressure_pa"] = np.random.default_rng(3).normal(60.0, 40.0, (4, 15))  # far below the 900 Pa threshold
    push(controller, make_tick(), frame=air)
    assert np.isnan(pressure.data_pa()).all()
    assert pressure.findChild(QtWidgets.QLabel, "maxLabel").text() == "max —"
    assert pressure._no_data_label.textItem.toPlainText() == "no contact" and pressure._no_data_label.isVisible()
    touch = make_frame(seq=8)
    push(controller, make_tick(), frame=touch)
    np.testing.assert_allclose(pressure.data_pa(), touch["pressure_pa"], rtol=1e-6)
    assert not pressure._no_data_label.isVisible()


def test_loop_health_reaches_the_status_bar_and_the_panel(window, controller):
    health = label(window, "loopHealth")
    push(controller, make_tick(), health=HEALTH)
    assert "1000 Hz" in health.text() and "0.42 %" in health.text() and "missed 3" in health.text()
    assert health.property("degraded") is False
    panel = window.findChild(HealthPanel)
    assert label(window, "rtPriority").text() == "no, CPU 1" and panel.level("rtPriority") == "watch"
    assert panel.level("loopRate") == "good" and panel.level("lateTicks") == "good"
    assert label(window, "masterAge").text() == "none attached"
    assert label(window, "sensorAge").text() == "4 ms  (limit 60 ms)" and panel.level("sensorAge") == "good"
    warned = LoopHealth(**{**{f: getattr(HEALTH, f) for f in HEALTH.__slots__},
                           "warning": "SCHED_FIFO not permitted"})
    push(controller, make_tick(), health=warned)
    assert "SCHED_FIFO not permitted" in health.text() and health.property("degraded") is True

    push(controller, make_tick(), events=[CommandRefused(3.0, SetSz(False), "a fault holds the robot")])
    assert window.statusBar().currentMessage() == "SetSz refused: a fault holds the robot"
    assert window.messages().lines()[-1].endswith("Refused SetSz: a fault holds the robot")


def test_device_ages_turn_red_past_the_safety_timeouts(controller, settings):
    panel = HealthPanel(SafetyLimits())
    tick = make_tick(sensor_age_s=0.08, slave_age_s=0.007, master_age_s=0.01)
    panel.show_ages(tick)
    assert panel.level("sensorAge") == "bad" and panel.level("slaveAge") == "watch"
    assert panel.level("masterAge") == "good"


def test_messages_carry_the_time_since_the_session_started(window, controller):
    controller.started.emit()
    push(controller, make_tick(t_s=100.0))
    push(controller, make_tick(t_s=102.5), events=[Notice(102.5, "Tactile sensor tared: the current reading "
                                                                 "is the new zero.")])
    line = window.messages().lines()[-1]
    assert "t    2.50 s" in line and "Tactile sensor tared" in line
    assert line[:8].count(":") == 2  # the wall-clock time it arrived, HH:MM:SS
    # issue 13: a second run records a session of its own, and its times start again from its first tick
    controller.stopped.emit()
    controller.started.emit()
    push(controller, make_tick(t_s=340.0))
    push(controller, make_tick(t_s=341.25), events=[Notice(341.25, "Second run.")])
    line = window.messages().lines()[-1]
    assert "t    1.25 s" in line and "Second run." in line


def test_level_records_fill_the_history_and_the_whole_tissue_view(window, controller):
    push(controller, make_tick(t_s=1.0))
    push(controller, make_tick(t_s=3.0), events=[LevelRecorded(3.0, make_record(level=0, force=1.0)),
                                                 LevelRecorded(4.0, make_record(level=1, force=2.0))])
    tissue = window.findChild(WholeTissueView)
    assert tissue.record_count() == 2 and tissue.level_force_N() == 2.0
    assert np.isfinite(tissue.shown_values()).any()
    markers = window.findChild(HistoryPlots)._recorded.getData()
    assert list(markers[1]) == [1.0, 2.0]


def test_keyboard_jog_moves_along_the_map_axes_only_when_allowed(qtbot, window, controller):
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Up)
    assert controller.sent == []  # no tick yet: unknown whether a master is attached
    push(controller, make_tick(phase=Phase.APPROACH))
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Up)
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Right)
    qtbot.keyClick(window, QtCore.Qt.Key.Key_PageDown)
    assert controller.sent == [Jog((1e-3, 0.0, 0.0)), Jog((0.0, 1e-3, 0.0)), Jog((0.0, 0.0, -1e-3))]
    reason = label(window, "jogReason")
    push(controller, make_tick(phase=Phase.SETTLING, sz=0, level=0, n_levels=7))
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Left)
    assert len(controller.sent) == 3 and "between areas" in reason.text()
    push(controller, make_tick(phase=Phase.APPROACH, master_age_s=0.002))
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Left)
    assert len(controller.sent) == 3 and "master device" in reason.text()


def test_invalid_ramp_is_refused_with_the_reason_and_never_sent(qtbot, window, controller):
    f_min = window.findChild(QtWidgets.QDoubleSpinBox, "force_min_N")
    apply = button(window, "rampApply")
    summary = label(window, "rampSummary")
    assert summary.text().startswith("7 levels: 1, 2, 3")
    f_min.setValue(8.0)
    assert not apply.isEnabled()
    assert summary.text() == "Refused — F_max: must be >= F_min (8 N), got 7"
    qtbot.mouseClick(apply, QtCore.Qt.MouseButton.LeftButton)
    assert controller.sent == []
    f_min.setValue(0.0)
    assert summary.text() == "Refused — F_min: must be > 0, got 0"
    f_min.setValue(2.0)
    assert apply.isEnabled() and summary.text() == "6 levels: 2, 3, 4, 5, 6, 7 N"
    qtbot.mouseClick(apply, QtCore.Qt.MouseButton.LeftButton)
    assert controller.sent == [SetRamp(RampSettings(force_min_N=2.0, rmse_threshold_N=0.1))]
    status = label(window, "rampStatus")
    push(controller, make_tick(),
         events=[CommandRefused(1.0, controller.sent[-1], "settings can change only between regions")])
    assert status.text() == "Not applied — the controller refused: settings can change only between regions"
    assert window.findChild(LevelLadder, "levelLadder").forces() == [1, 2, 3, 4, 5, 6, 7]


def test_gains_are_shown_locked_and_sent_only_once_unlocked(qtbot, window, controller):
    k_z = window.findChild(QtWidgets.QDoubleSpinBox, "stiffness_N_m_z")
    apply = button(window, "gainsApply")
    assert k_z.value() == 20000.0 and not k_z.isEnabled() and not apply.isEnabled()
    qtbot.mouseClick(window.findChild(QtWidgets.QCheckBox, "gainsUnlock"), QtCore.Qt.MouseButton.LeftButton)
    assert k_z.isEnabled()
    k_z.setValue(0.0)
    assert label(window, "gainsSummary").text() == "Refused — K_d z: must be > 0, got 0"
    assert not apply.isEnabled()
    # the controller's own stability rule, before anything is sent (issue 49: the panel checked positivity only)
    b_z = window.findChild(QtWidgets.QDoubleSpinBox, "damping_N_s_m_z")
    k_z.setValue(25000.0)
    b_z.setValue(80.0)
    assert "force control on z would be stable only on tissue up to 1897 N/m" in label(window, "gainsSummary").text()
    assert not apply.isEnabled()
    b_z.setValue(200.0)
    qtbot.mouseClick(apply, QtCore.Qt.MouseButton.LeftButton)
    sent = controller.sent[-1]
    assert sent.gains.stiffness_N_m == (1600.0, 1600.0, 25000.0)
    assert not k_z.isEnabled()  # locked again at once
    push(controller, make_tick(), events=[CommandApplied(1.0, sent, "Impedance gains changed.")])
    assert label(window, "gainsStatus").text() == "Applied."


def test_layout_and_settings_are_restored_on_the_next_run(qtbot, controller, settings):
    first = open_window(qtbot, controller, settings, plan=PLAN)
    first.findChild(TactileMapWidget, "pressureMap").set_view_mode(ViewMode.CONTOUR)
    first.findChild(TactileMapWidget, "stiffnessMap").lock_levels(0.0, 150e3)
    first.findChild(QtWidgets.QDockWidget, "messagesDock").close()
    first.findChild(QtWidgets.QComboBox, "jogStep").setCurrentIndex(4)  # 5 mm
    first.findChild(WholeTissueView).set_quantity("stiffness_pa")
    # a ramp the controller accepted
    first.findChild(QtWidgets.QDoubleSpinBox, "force_max_N").setValue(3.0)
    qtbot.mouseClick(button(first, "rampApply"), QtCore.Qt.MouseButton.LeftButton)
    push(controller, make_tick(), events=[CommandApplied(1.0, controller.sent[-1], "Ramp set: 1 to 3 N ...")])
    assert first.findChild(LevelLadder, "levelLadder").forces() == [1, 2, 3]
    first.close()

    second_controller = FakeController()
    second = open_window(qtbot, second_controller, settings, plan=PLAN)
    assert second.findChild(TactileMapWidget, "pressureMap").view_mode() == ViewMode.CONTOUR
    stiffness = second.findChild(TactileMapWidget, "stiffnessMap")
    assert stiffness.is_locked() and stiffness.levels_pa() == pytest.approx((0.0, 150e3))
    assert not second.findChild(QtWidgets.QDockWidget, "messagesDock").isVisible()
    assert second.findChild(QtWidgets.QComboBox, "jogStep").currentText() == "5 mm"
    assert second.findChild(WholeTissueView).quantity() == "stiffness_pa"
    # the accepted ramp is asked for again once the controller runs, and shown once it is confirmed
    assert second_controller.sent == []
    second_controller.started.emit()
    push(second_controller, make_tick())
    assert second_controller.sent == [SetRamp(RampSettings(force_max_N=3.0, rmse_threshold_N=0.1))]


def test_a_changed_configuration_wins_over_the_restored_ramp(qtbot, controller, settings):
    first = open_window(qtbot, controller, settings)
    first.findChild(QtWidgets.QDoubleSpinBox, "force_max_N").setValue(3.0)
    qtbot.mouseClick(button(first, "rampApply"), QtCore.Qt.MouseButton.LeftButton)
    push(controller, make_tick(), events=[CommandApplied(1.0, controller.sent[-1], "Ramp set: 1 to 3 N ...")])
    first.close()
    second_controller = FakeController()
    edited = ControlConfig(ramp=RampSettings(force_max_N=5.0))  # the configuration file changed meanwhile
    second = open_window(qtbot, second_controller, settings, config=edited)
    second_controller.started.emit()
    push(second_controller, make_tick())
    assert second_controller.sent == []
    assert any("configuration's ramp changed" in line for line in second.messages().lines())


def test_autopilot_panel_starts_and_stops_and_says_why_it_cannot(qtbot, window, controller):
    start, stop = button(window, "autopilotStart"), button(window, "autopilotStop")
    status = label(window, "autopilotStatus")
    assert not start.isEnabled() and "waiting for the controller" in status.text()
    push(controller, make_tick(phase=Phase.APPROACH))
    assert start.isEnabled() and not stop.isEnabled()
    window.findChild(QtWidgets.QSpinBox, "autopilotFirst").setValue(2)
    qtbot.mouseClick(start, QtCore.Qt.MouseButton.LeftButton)
    push(controller, make_tick(phase=Phase.APPROACH))
    # area 2 of the plan at the travel height: one jog from X_d
    assert controller.sent == [Jog(pytest.approx((0.012 - 0.036, 0.0, 0.045 - 0.06)))]
    assert stop.isEnabled() and "moving above area 2 of 2" in status.text()
    assert not button(window, "jogXPlus").isEnabled()  # the autopilot owns the TSI
    qtbot.mouseClick(stop, QtCore.Qt.MouseButton.LeftButton)
    assert "stopped by the operator" in status.text() and button(window, "jogXPlus").isEnabled()


def test_without_a_plan_the_autopilot_is_unavailable(qtbot, controller, settings):
    win = open_window(qtbot, controller, settings)
    push(controller, make_tick())
    assert not button(win, "autopilotStart").isEnabled()
    assert "no phantom file" in label(win, "autopilotStatus").text()


def test_colour_ranges_start_from_the_ramp_and_tissue_scale(window):
    pressure = window.findChild(TactileMapWidget, "pressureMap")
    stiffness = window.findChild(TactileMapWidget, "stiffnessMap")
    face_m2 = 60 * 4e-6
    assert pressure.auto_floor_pa() == pytest.approx(1.5 * 7.0 / face_m2)  # default F_max = 7 N
    window.set_ramp(RampSettings(force_min_N=2.0, force_max_N=12.0, force_step_N=2.0))
    assert pressure.auto_floor_pa() == pytest.approx(1.5 * 12.0 / face_m2)
    assert stiffness.auto_floor_pa() == pytest.approx(100e3)


def test_every_message_pane_line_is_bounded(qtbot):
    pane = MessagesPane(max_lines=5)
    qtbot.addWidget(pane)
    for k in range(8):
        pane.add(f"line {k}")
    assert [line.split()[-1] for line in pane.lines()] == ["3", "4", "5", "6", "7"]


def test_the_message_pane_follows_the_newest_line_until_the_operator_scrolls_up(qtbot):
    # The console's pane was left showing its first lines, and the region-done findings arrived out of
    # sight: the lines of start-up were added before the pane was laid out, so the scroll bar grew only
    # when it was shown, with the view at the top, and every later line found it "scrolled up".
    pane = MessagesPane()
    qtbot.addWidget(pane)
    for k in range(20):
        pane.add(f"start-up line {k}: recording the session to a long path that wraps over two lines")
    pane.resize(300, 150)
    pane.show()
    qtbot.waitExposed(pane)
    bar = pane.findChild(QtWidgets.QListWidget, "messageList").verticalScrollBar()
    pane.add("Area 1: stiffness map: tumour at (12.1, 15.0) mm, first at 2 N, depth 2.0 mm")
    qtbot.waitUntil(lambda: bar.maximum() > 0 and bar.value() == bar.maximum())
    bar.setValue(0)  # the operator scrolls up to read an old line: it stays in view
    before = bar.maximum()
    pane.add("one more")
    qtbot.waitUntil(lambda: bar.maximum() > before)
    assert bar.value() == 0
    bar.setValue(bar.maximum())  # and back at the bottom, the pane follows again
    pane.add("and another")
    qtbot.waitUntil(lambda: bar.value() == bar.maximum())


def words(label: QtWidgets.QLabel) -> str:
    """A label's text as read: the spaces that keep a figure on one line read as spaces."""
    return label.text().replace("\u00a0", " ")


def test_the_health_chip_sums_up_the_loop_and_the_devices(window, controller):
    chip = label(window, "healthChip")
    assert chip.text() == "loop: no report yet" and chip.property("level") == "watch"
    push(controller, make_tick(), health=LoopHealth(rate_hz=1000.0, late_over_0_5ms_pct=0.05, p99_abs_jitter_us=30.0,
                                                    missed_ticks=0, longest_stall_ms=0.4, rt_priority=True, cpu=1))
    assert chip.property("level") == "good"
    assert words(chip) == "Loop OK · 1000 Hz · late 0.05 %\nsensor 4 ms · robot 1 ms"
    for _ in range(6):  # device ages are refreshed at a tenth of the display rate
        push(controller, make_tick(sensor_age_s=0.2))
    assert chip.property("level") == "bad" and words(chip).startswith("LOOP / DEVICE PROBLEM")
    assert "sensor 200 ms" in words(chip)


def test_the_chip_and_the_status_bar_give_one_verdict_on_the_loop(window, controller):
    # issue 13: the health box said "Loop OK" while the status bar said "longest stall 108 ms · missed 480"
    chip, bar = label(window, "healthChip"), label(window, "loopHealth")
    calm = LoopHealth(rate_hz=1000.0, late_over_0_5ms_pct=0.05, p99_abs_jitter_us=30.0, missed_ticks=2,
                      longest_stall_ms=3.0, rt_priority=True, cpu=1)
    push(controller, make_tick(), health=calm)  # a blip of two periods is no reason to look
    assert words(chip).startswith("Loop OK") and bar.text().startswith("Loop OK · ")
    assert bar.property("degraded") is False
    stalled = LoopHealth(**{**{f: getattr(calm, f) for f in calm.__slots__}, "missed_ticks": 480,
                            "longest_stall_ms": 108.0})
    push(controller, make_tick(), health=stalled)  # longer than the sensor's 60 ms timeout
    assert chip.property("level") == "bad" and "missed 480 (stall 108 ms)" in words(chip)
    assert words(chip).startswith("LOOP / DEVICE PROBLEM") and bar.text().startswith("LOOP / DEVICE PROBLEM · ")
    assert bar.property("degraded") is True
    shorter = LoopHealth(**{**{f: getattr(calm, f) for f in calm.__slots__}, "missed_ticks": 40,
                            "longest_stall_ms": 30.0})
    panel = HealthPanel(SafetyLimits())
    panel.show_health(shorter)
    assert panel.level("missedTicks") == "watch" and panel.overall()[1].startswith("Loop:\u00a0check")


def test_a_double_click_on_the_tissue_sends_the_probe_there_only_off_the_tissue(window, controller):
    tissue = window.findChild(WholeTissueView)
    push(controller, make_tick(phase=Phase.APPROACH, force_measured_N=0.8))
    tissue.move_requested.emit(0.020, 0.010)
    assert controller.sent == [] and "Lift the TSI off the tissue" in window.statusBar().currentMessage()
    push(controller, make_tick(phase=Phase.APPROACH))
    tissue.move_requested.emit(0.020, 0.010)
    assert controller.sent == [Jog(pytest.approx((0.020 - 0.036, 0.010 - 0.015, 0.0)))]  # at its current height
    push(controller, make_tick(phase=Phase.HOLD, fault=FaultKind.ESTOP))
    tissue.move_requested.emit(0.030, 0.010)
    assert len(controller.sent) == 1 and "a fault holds the robot" in window.statusBar().currentMessage()


def area(region, x, tumour=False):
    """The events of an area palpated at three levels and done, over a tumour 1.5x as stiff if ``tumour``."""
    from control.messages import RegionDone
    from session.synthetic import level_record

    records = [level_record(region, k, f, (x, 0.015), noise=0.02, seed=31 * region + k, t_s=10.0 * region + k,
                            tumours_xy_m=((x, 0.015),) if tumour else (), tumour_factor=1.5)
               for k, f in enumerate((1.0, 2.0, 3.0))]
    return [LevelRecorded(r.t_s, r) for r in records] + [RegionDone(10.0 * region + 3, region, 3)]


def test_region_done_says_what_the_area_showed(window, controller):
    import math
    import re

    push(controller, make_tick(t_s=1.0), events=area(0, 0.012))
    assert "findings from the 4th area on" in label(window, "regionFindings").text()
    for region, x in ((1, 0.020), (2, 0.028)):
        push(controller, make_tick(t_s=1.0 + region), events=area(region, x))
    tissue = window.findChild(WholeTissueView)
    assert tissue.quantity() == "pressure_pa"
    asked = []

    class DepthModel:  # what the composition root gives (session.depth); it sees what the reviewer's would
        def estimate(self, tumour, levels, contrast):
            asked.append((tumour.source, len(levels), contrast.map))
            return 3.1e-3, 2.25e-3, 4.4e-3

    window.set_depth_model(DepthModel())
    told = []
    window.findings_told.connect(told.append)
    push(controller, make_tick(t_s=4.0), events=area(3, 0.036, tumour=True))
    (text,) = told  # for the session: what the surgeon was told (issue 50), whole
    # and under the flag in a line, so that F_d, F_ts and the depth stay in a laptop's view
    assert re.fullmatch(r"Area 4: tumour at x [\d.]+, y [\d.]+ mm, 3\.1 \[2\.2, 4\.4\] mm deep \(model\)",
                        label(window, "regionFindings").text())
    found = re.match(r"Area 4: stiffness map: tumour at x ([\d.]+) mm, y ([\d.]+) mm, first at 1 N, depth [\d.]+ mm "
                     r"\(paper's rule\), 3\.1 \[2\.2, 4\.4\] mm \(model, 90 % interval\), z [\d.]+", text)
    assert found and math.hypot(float(found[1]) - 36.0, float(found[2]) - 15.0) < 1.0
    assert asked and all(records == 12 and map_name == "stiffness" for _, records, map_name in asked)
    assert any(line.endswith(text) for line in window.messages().lines())
    assert tissue.quantity() == "stiffness_contrast"  # turned to once it could be had, nobody having chosen
    assert np.nanmax(tissue.shown_values()) > 0.3  # over homogeneous tissue, over the tumour
    assert tissue.spot_count() == 1
    assert tissue.depth_labels() == ["3.1 mm"]  # the depth told, beside its circle (issue 50)
    table = window.findChild(FindingsTable)  # and a row of the findings table, a double-click from the TSI
    cells = [table.item(0, c).text() for c in range(table.columnCount())]
    assert table.rowCount() == text.count(" map: tumour at") and cells[:2] == ["4", "stiffness"]
    assert cells[5] == "3.1 [2.2, 4.4]"
    moved = []
    table.move_requested.connect(lambda x, y: moved.append((x, y)))
    table.cellDoubleClicked.emit(0, 3)
    assert len(moved) == 1 and math.hypot(moved[0][0] - 0.036, moved[0][1] - 0.015) < 1e-3
    push(controller, make_tick(t_s=5.0), events=area(4, 0.044))
    assert label(window, "regionFindings").text() == "Area 5: nothing significant up to 7 N"
    assert told == [text, "Area 5: nothing significant up to 7 N"]


class Physics(QtCore.QObject):
    """What the composition root gives (app.live_physics), answered by hand; no plan says where the tissue
    ends."""

    ready = QtCore.Signal(int, object, str)
    failed = QtCore.Signal(str)
    progress = QtCore.Signal(int, float, str)
    ends_known = False
    busy = False

    def __init__(self):
        super().__init__()
        self.asked = []

    def request(self, levels):
        self.asked.append(levels)

    def hold(self, held):
        self.held = held

    def answer(self, explained: bool = False):
        """Homogeneous tissue pressing every element alike, exactly known; ``explained``: tissue that
        presses each element as hard as it was measured to, a tumour's elements included."""
        from types import SimpleNamespace

        levels = self.asked.pop(0)
        share = levels["pressure_pa"] if explained else np.ones(levels["pressure_pa"].shape)
        pattern = SimpleNamespace(share=share, sigma=0.0 * share, modes=None)
        self.ready.emit(len(levels), {"stiffness": pattern, "force": pattern}, "a test's flat block")


def test_findings_wait_for_the_physics_of_the_areas_palpated_and_go_without_it_when_it_fails(window, controller):
    physics = Physics()
    window.set_live_physics(physics)
    tissue = window.findChild(WholeTissueView)
    tissue.set_quantity("stiffness_pa")  # the operator's choice stands once the contrast can be had
    for phase, held in ((Phase.SETTLING, True), (Phase.DONE, False), (Phase.SEEK_CONTACT, True),
                        (Phase.APPROACH, False)):
        push(controller, make_tick(phase=phase))
        assert physics.held is held  # its solves wait while the loop controls force
    for region, x in enumerate((0.012, 0.020, 0.028, 0.036)):
        push(controller, make_tick(t_s=1.0 + region), events=area(region, x, tumour=region == 3))
    assert [len(levels) for levels in physics.asked] == [3, 6, 9, 12]  # after every area, every level so far
    assert label(window, "regionFindings").text() == "Area 4: computing findings…"
    physics.asked = physics.asked[-1:]
    assert tissue.spot_count() == 0  # nothing is judged without it
    physics.answer()
    assert label(window, "regionFindings").text().startswith("Area 4: tumour at x 36")
    assert tissue.spot_count() == 1
    told = [line.split("  ", 1)[-1].strip() for line in window.messages().lines()]
    assert sum(line.startswith("Area 4: stiffness map") for line in told) == 1
    unsure = ("nothing significant up to 7 N so far (where the tissue ends is not known: a tumour near this area's "
              "edges may show once the areas beside it are palpated)")
    assert all(f"Area {n}: {unsure}" in told for n in (1, 2, 3))  # the first areas' too

    push(controller, make_tick(t_s=6.0), events=area(4, 0.044))
    assert label(window, "regionFindings").text() == "Area 5: computing findings…"
    assert tissue.spot_count() == 1  # the areas the physics covers are still judged
    physics.failed.emit("the palpated areas span too much")
    assert label(window, "regionFindings").text() == "Area 5: nothing significant up to 7 N"
    assert any("Tissue model of the palpated areas unavailable: the palpated areas span too much" in line
               for line in window.messages().lines())
    push(controller, make_tick(t_s=7.0), events=area(5, 0.052))
    assert len(physics.asked) == 1  # not asked again once it failed
    assert label(window, "regionFindings").text() == "Area 6: nothing significant up to 7 N"
    assert tissue.quantity() == "stiffness_pa"


def test_while_the_tissue_model_is_computed_the_console_says_so_and_how_far(window, controller):
    physics = Physics()
    window.set_live_physics(physics)
    panel = window.findChild(FindingsPanel)
    for region, x in enumerate((0.012, 0.020, 0.028)):
        push(controller, make_tick(t_s=1.0 + region), events=area(region, x))
    physics.progress.emit(9, 0.5, "the face's contact on record 5 of 9")  # three areas: no findings can come yet
    assert label(window, "regionFindings").text().startswith("Area 3: findings once 4 areas are palpated")
    assert panel.progress_text() == "Computing findings… 50 %: Tissue model of the 3 areas palpated: the face's " \
                                    "contact on record 5 of 9"
    push(controller, make_tick(t_s=4.0), events=area(3, 0.036, tumour=True))
    assert label(window, "regionFindings").text() == "Area 4: computing findings…"
    physics.busy = True
    physics.progress.emit(12, 0.0, "starting")
    physics.progress.emit(12, 0.4, "the face's contact on record 5 of 12")
    assert label(window, "regionFindings").text() == "Area 4: computing findings… 40%"
    assert panel.progress_text().startswith("Computing findings… 40 %: Tissue model of the 4 areas palpated")
    told = [line.split("  ", 1)[-1].strip() for line in window.messages().lines()]
    assert told.count("Computing the findings: the tissue model of the 4 areas palpated…") == 1
    physics.busy = False
    physics.asked = physics.asked[-1:]
    physics.answer()
    assert panel.progress_text() is None
    assert label(window, "regionFindings").text().startswith("Area 4: tumour at x 36")


def test_a_tumour_an_area_shows_only_once_the_areas_beside_it_are_palpated_is_told_then(window, controller):
    physics = Physics()
    window.set_live_physics(physics)
    for region, x in enumerate((0.012, 0.020, 0.028, 0.036)):
        push(controller, make_tick(t_s=1.0 + region), events=area(region, x, tumour=region == 3))
    physics.asked = physics.asked[-1:]
    physics.answer(explained=True)  # the model of four areas explains the tumour's load away
    assert label(window, "regionFindings").text().startswith("Area 4: nothing significant up to 7 N so far")
    push(controller, make_tick(t_s=6.0), events=area(4, 0.044))
    physics.asked = physics.asked[-1:]
    physics.answer()  # with the fifth area, it does not

    def told():
        return [line.split("  ", 1)[-1].strip() for line in window.messages().lines()]

    later = [line for line in told() if line.startswith("Area 4, with the areas palpated since: ")]
    assert [line.split(": ")[1] for line in later] == ["stiffness map", "force map"]
    assert all("tumour at x 36.0 mm, y 15.0 mm, first at 1 N" in line for line in later)
    assert label(window, "regionFindings").text().startswith("Area 5: nothing significant")
    push(controller, make_tick(t_s=7.0), events=area(5, 0.052))
    physics.asked = physics.asked[-1:]
    physics.answer()
    assert [line for line in told() if line.startswith("Area 4, with")] == later  # told once


def test_a_reference_palpation_is_saved_from_the_console_and_gives_findings_from_the_first_area(
        window, controller, tmp_path):
    import json

    from control.messages import RegionDone
    from session.synthetic import level_record

    def area(region, x, tumour=False):
        records = [level_record(region, k, f, (x, 0.015), noise=0.02, seed=17 * region + k, t_s=10.0 * region + k,
                                tumours_xy_m=((x, 0.015),) if tumour else (), tumour_factor=1.5)
                   for k, f in enumerate((1.0, 2.0, 3.0))]
        return [LevelRecorded(r.t_s, r) for r in records] + [RegionDone(10.0 * region + 3, region, 3)]

    path = tmp_path / "reference.json"
    assert not window.save_reference(path)  # nothing palpated yet
    assert window.messages().lines()[-1].endswith("Reference palpation not saved: no level recorded yet: palpate "
                                                  "tumour-free tissue first")
    for region, x in ((0, 0.012), (1, 0.020)):  # tumour-free tissue
        push(controller, make_tick(t_s=1.0 + region), events=area(region, x))
    assert window.save_reference(path)
    assert json.loads(path.read_text())["physics"] is False

    # a later patient: with the reference, the very first area says what it showed
    window.clear_reference()
    assert window.load_reference(path)
    tissue = window.findChild(WholeTissueView)
    tissue.set_reference(tissue.reference())  # still usable after a reload
    push(controller, make_tick(t_s=4.0), events=area(2, 0.028, tumour=True))
    assert "tumour at x 28" in label(window, "regionFindings").text()

    # one made over the finite-element physics cannot serve the live maps, and says so
    data = json.loads(path.read_text())
    data["physics"] = True
    path.write_text(json.dumps(data))
    assert not window.load_reference(path)
    assert "made over the finite-element physics" in window.messages().lines()[-1]


def test_the_live_maps_show_the_frame_flat_fielded_with_its_significant_spot_circled(window, controller):
    from control.messages import RegionDone
    from session.synthetic import level_record
    from widgets.tactile_map import NO_CONTRAST_TEXT

    face = np.array([2.2, 1.0, 1.0, 2.2])[:, None]  # the rigid face's edge rows read high on healthy tissue

    def record(region, k, force, x, tumour=False):
        r = level_record(region, k, force, (x, 0.015), noise=0.02, seed=7 * region + k, t_s=10.0 * region + k,
                         tumours_xy_m=((x, 0.015),) if tumour else (), tumour_factor=1.6)
        return dataclasses.replace(r, pressure_pa=r.pressure_pa * face, stiffness_pa=r.stiffness_pa * face)

    def frame_of(r):
        frame = empty_frame()
        frame["sensor_seq"] = 100 + r.level  # each a new frame
        frame["tsi_position_m"] = r.tsi_position_m
        frame["pressure_pa"], frame["stiffness_pa"], frame["dL_m"] = r.pressure_pa, r.stiffness_pa, r.dL_m
        return frame

    pressure = window.findChild(TactileMapWidget, "pressureMap")
    stiffness = window.findChild(TactileMapWidget, "stiffnessMap")
    pressure.findChild(QtWidgets.QCheckBox, "contrastView").setChecked(True)
    stiffness.set_contrast_view(True)
    push(controller, make_tick(t_s=0.5), frame=frame_of(record(9, 0, 2.0, 0.060)))
    assert pressure.findChild(QtWidgets.QCheckBox, "contrastView").isChecked() and pressure.contrast_view()
    assert not pressure.findChild(QtWidgets.QCheckBox, "lockRange").isEnabled()
    assert pressure.findChild(QtWidgets.QDoubleSpinBox, "levelMax").isHidden()  # no kPa beside a % map
    plot = pressure.findChild(QtWidgets.QGraphicsView, "plot")
    text_item = next(i for i in plot.scene().items()
                     if isinstance(i, QtCore.QObject) and i.objectName() == "noDataText")
    assert text_item.isVisible() and text_item.textItem.toPlainText() == NO_CONTRAST_TEXT
    for region, x in enumerate((0.012, 0.020, 0.028, 0.036)):
        events = [LevelRecorded(10.0 * region + k, record(region, k, f, x)) for k, f in enumerate((1.0, 2.0, 3.0))]
        push(controller, make_tick(t_s=1.0 + region), events=events + [RegionDone(10.0 * region + 3, region, 3)])

    push(controller, make_tick(t_s=6.0), frame=frame_of(record(9, 1, 2.0, 0.044)))  # healthy tissue
    assert not text_item.isVisible() and pressure.contrast_spots() == ()
    assert float(label(pressure, "maxLabel").text().split()[1].rstrip("%")) < 10  # no edge rows left
    push(controller, make_tick(t_s=7.0), frame=frame_of(record(9, 2, 3.0, 0.052, tumour=True)))
    for widget in (pressure, stiffness):
        assert len(widget.contrast_spots()) == 1
        (i, j), = widget.contrast_spots()
        assert abs(i - 1.5) <= 1 and abs(j - 7) <= 1  # under the face's centre, where the tumour is
    pressure.set_contrast_view(False)
    assert pressure.contrast_spots() == () and label(pressure, "maxLabel").text().endswith("kPa")
    assert pressure.findChild(QtWidgets.QCheckBox, "lockRange").isEnabled()
    assert not pressure.findChild(QtWidgets.QDoubleSpinBox, "levelMax").isHidden()


def test_the_file_menu_calibrates_the_array_from_a_session_of_presses_on_a_cushion(window, tmp_path, monkeypatch):
    from control.messages import LevelRecorded
    from hardware.array_calibration import ArrayCalibration
    from session.synthetic import level_record
    from session.writer import SessionRecorder
    from tests.session.test_recorder import INFO

    # three presses of five levels on a uniform layer, read through one fixed 5 % pattern of sensitivities
    recorder = SessionRecorder(tmp_path / "cushion.h5", INFO)
    records = [level_record(press, level, 1.0 + level, (0.02, 0.015), noise=0.05, seed=7)
               for press in range(3) for level in range(5)]
    recorder.add_events([LevelRecorded(float(k), r) for k, r in enumerate(records)])
    recorder.close()
    out = tmp_path / "tsi.toml"
    monkeypatch.setattr(QtWidgets.QFileDialog, "getOpenFileName", lambda *a, **k: (str(tmp_path / "cushion.h5"), ""))
    monkeypatch.setattr(QtWidgets.QFileDialog, "getSaveFileName", lambda *a, **k: (str(out), ""))
    window.findChild(QtGui.QAction, "calibrateArrayAction").trigger()
    pattern = records[0].pressure_pa / records[0].pressure_pa.mean()
    np.testing.assert_allclose(ArrayCalibration.load(out).gain, pattern, rtol=1e-6)
    assert f"Array calibration saved to {out} (3 presses" in window.messages().lines()[-1]
    # a session that cannot give one is said in one line, and nothing is written
    assert not window.calibrate_array(tmp_path / "missing.h5", tmp_path / "other.toml")
    assert "Array not calibrated: " in window.messages().lines()[-1] and not (tmp_path / "other.toml").exists()


def test_every_term_of_the_console_explains_itself_in_a_tooltip(window):
    """issue 50: S_z, F_ts, ε, RMSE and the rest were on the screen with nothing to explain them."""
    from widgets.glossary import GLOSSARY

    for name in ("szTitle", "forceDesired", "forceMeasured", "rmseLabel", "indentation", "contactArea",
                 "peakPressure", "centreOfPressure", "regionDone", "phaseLabel"):
        tip = window.findChild(QtWidgets.QWidget, name).toolTip()
        assert tip and any(meaning in tip for meaning in GLOSSARY.values()), name
    assert window.findChild(LevelLadder).toolTip() == GLOSSARY["ladder"]
