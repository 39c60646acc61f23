from __future__ import annotations

import numpy as np
import pytest
from PySide6 import QtCore, QtWidgets

from control.config import RampSettings
from control.messages import (ClearFault, CommandRefused, EStop, FaultCleared, FaultKind, FaultRaised, Phase,
                              SetSz)
from control.telemetry import LiveSnapshot, LoopHealth, empty_frame, empty_tick
from widgets.live_window import LiveWindow
from widgets.sz_switch import SzSwitch
from widgets.tactile_map import TactileMapWidget


class FakeController(QtCore.QObject):
    """The two members LiveWindow uses of app.bridge.ControllerBridge."""

    snapshot = QtCore.Signal(object)

    def __init__(self):
        super().__init__()
        self.sent = []

    def send(self, command):
        self.sent.append(command)


def make_tick(**fields):
    tick = empty_tick()
    tick["sz"] = 1
    for name, value in fields.items():
        tick[name] = value
    return tick


def make_frame(seq=1, peak_pa=30e3):
    frame = empty_frame()
    frame["sensor_seq"] = seq
    i, j = np.meshgrid(np.arange(4), np.arange(15), indexing="ij")
    frame["pressure_pa"] = 1e3 + peak_pa * np.exp(-((i - 1.5) ** 2 + (j - 9.0) ** 2 / 3.0))
    stiffness = np.full((4, 15), 25e3, dtype=np.float32)
    stiffness[:, :3] = np.nan  # not in contact
    frame["stiffness_pa"] = stiffness
    return frame


HEALTH = LoopHealth(rate_hz=999.6, late_over_0_5ms_pct=0.42, p99_abs_jitter_us=41.0, missed_ticks=3,
                    longest_stall_ms=4.5, rt_priority=False, cpu=1)


@pytest.fixture
def controller():
    return FakeController()


@pytest.fixture
def window(qtbot, controller):
    win = LiveWindow(controller, ramp=RampSettings(rmse_threshold_N=0.1))
    qtbot.addWidget(win)
    win.resize(1300, 800)
    win.show()
    qtbot.waitExposed(win)
    win.activateWindow()
    qtbot.waitUntil(win.isActiveWindow)
    return win


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
    assert label(window, "levelLabel").text() == "level 3 of 7"
    assert label(window, "rmseLabel").text() == "RMSE 0.042 N < ε 0.100 N"
    assert label(window, "forceDesired").text() == "3.00 N"
    assert label(window, "forceMeasured").text() == "2.97 N"
    assert label(window, "indentation").text() == "2.4 mm"

    push(controller, make_tick(phase=Phase.SETTLING, sz=0, level=2, n_levels=7, rmse_N=0.25))
    assert label(window, "rmseLabel").text() == "RMSE 0.250 N ≥ ε 0.100 N"
    window.set_ramp(RampSettings(rmse_threshold_N=0.3))
    push(controller, make_tick(phase=Phase.SETTLING, sz=0, level=2, n_levels=7, rmse_N=0.25))
    assert label(window, "rmseLabel").text() == "RMSE 0.250 N < ε 0.300 N"

    push(controller, make_tick(phase=Phase.APPROACH))  # no contact, outside the ramp
    assert label(window, "phaseLabel").text() == "APPROACH"
    assert label(window, "levelLabel").text() == "" and label(window, "rmseLabel").text() == ""
    assert label(window, "indentation").text() == "—"


def test_region_done_is_unmistakable(window, controller):
    done = label(window, "regionDone")
    push(controller, make_tick(phase=Phase.SETTLING, sz=0, level=6, n_levels=7))
    assert done.property("done") is False and "REGION DONE" not in done.text()
    push(controller, make_tick(phase=Phase.DONE, sz=0, region_done=1, level=6, n_levels=7))
    assert done.property("done") is True and "REGION DONE" in done.text()
    assert label(window, "phaseLabel").text() == "DONE"
    assert label(window, "levelLabel").text() == "all 7 levels recorded"
    push(controller, make_tick(phase=Phase.APPROACH, region_done=0))
    assert done.property("done") is False


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
    # The click alone changes nothing but the "pending" mark: the controller has not confirmed it.
    assert switch.state() is True and position.property("active") is True
    assert switch.pending() is False and force.property("pending") is True
    push(controller, make_tick(sz=1))
    assert switch.state() is True and switch.pending() is False

    push(controller, make_tick(sz=0, phase=Phase.SEEK_CONTACT))
    assert switch.state() is False and switch.pending() is None
    assert force.property("active") is True and force.property("pending") is False
    qtbot.mouseClick(force, QtCore.Qt.MouseButton.LeftButton)  # already in force control: no request
    assert controller.sent == [SetSz(position_control=False)]

    qtbot.keyClick(window, QtCore.Qt.Key.Key_S)
    assert controller.sent[-1] == SetSz(position_control=True)
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Space)  # Space must not toggle S_z next to a robot
    assert len(controller.sent) == 2


def test_unconfirmed_request_lapses(qtbot, controller):
    switch = SzSwitch(pending_timeout_ms=50)
    qtbot.addWidget(switch)
    switch.set_state(True)
    with qtbot.waitSignal(switch.toggled) as request:
        qtbot.mouseClick(switch.findChild(QtWidgets.QPushButton, "szForce"), QtCore.Qt.MouseButton.LeftButton)
    assert request.args == [False] and switch.pending() is False
    qtbot.waitUntil(lambda: switch.pending() is None, timeout=5000)
    assert switch.state() is True


def test_emergency_stop_from_button_and_escape(qtbot, window, controller):
    qtbot.mouseClick(button(window, "estopButton"), QtCore.Qt.MouseButton.LeftButton)
    assert controller.sent == [EStop()]
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Escape)
    assert controller.sent == [EStop(), EStop()]


def test_fault_banner_shows_the_message_and_clears(qtbot, window, controller):
    banner = window.findChild(QtWidgets.QFrame, "faultBanner")
    assert not banner.isVisible()
    message = "F_ts 12.4 N exceeded the 12.0 N ceiling; robot held"
    push(controller, make_tick(phase=Phase.HOLD, fault=FaultKind.FORCE_CEILING),
         events=[FaultRaised(1.0, FaultKind.FORCE_CEILING, message)])
    assert banner.isVisible()
    assert label(window, "faultText").text() == f"FAULT: force ceiling — {message}"
    assert label(window, "phaseLabel").text() == "HOLD"
    qtbot.mouseClick(button(window, "clearFault"), QtCore.Qt.MouseButton.LeftButton)
    assert controller.sent == [ClearFault()]
    push(controller, make_tick(phase=Phase.HOLD, fault=FaultKind.FORCE_CEILING))  # still held
    assert banner.isVisible()
    push(controller, make_tick(phase=Phase.APPROACH, fault=0), events=[FaultCleared(2.0, FaultKind.FORCE_CEILING)])
    assert not banner.isVisible()
    # A fault whose event was not seen still names its kind.
    push(controller, make_tick(phase=Phase.HOLD, fault=FaultKind.SENSOR_STALE))
    assert banner.isVisible() and label(window, "faultText").text() == "FAULT: sensor stale"


def test_maps_show_new_frames_only(window, controller):
    pressure = window.findChild(TactileMapWidget, "pressureMap")
    stiffness = window.findChild(TactileMapWidget, "stiffnessMap")
    assert np.isnan(pressure.data_pa()).all()  # before the first frame: no data, not zeros
    frame = make_frame(seq=5)
    push(controller, make_tick(), frame=frame)
    np.testing.assert_allclose(pressure.data_pa(), frame["pressure_pa"], rtol=1e-6)
    shown_stiffness = stiffness.data_pa()
    assert np.isnan(shown_stiffness[:, :3]).all()
    np.testing.assert_allclose(shown_stiffness[:, 3:], 25e3, rtol=1e-6)

    same_seq = make_frame(seq=5, peak_pa=90e3)  # a snapshot repeating the frame it already showed
    push(controller, make_tick(), frame=same_seq)
    np.testing.assert_allclose(pressure.data_pa(), frame["pressure_pa"], rtol=1e-6)
    newer = make_frame(seq=6, peak_pa=90e3)
    push(controller, make_tick(), frame=newer)
    np.testing.assert_allclose(pressure.data_pa(), newer["pressure_pa"], rtol=1e-6)


def test_loop_health_and_messages_reach_the_status_bar(window, controller):
    health = label(window, "loopHealth")
    push(controller, make_tick(), health=HEALTH)
    assert "1000 Hz" in health.text() and "0.42 %" in health.text() and "missed 3" in health.text()
    assert health.property("degraded") is False
    warned = LoopHealth(**{**{f: getattr(HEALTH, f) for f in HEALTH.__slots__},
                           "warning": "SCHED_FIFO not permitted"})
    push(controller, make_tick(), health=warned)
    assert "SCHED_FIFO not permitted" in health.text() and health.property("degraded") is True

    push(controller, make_tick(), events=[CommandRefused(3.0, "SetSz", "a fault holds the robot")])
    assert window.statusBar().currentMessage() == "SetSz refused: a fault holds the robot"


def test_colour_ranges_start_from_the_ramp_and_tissue_scale(window):
    pressure = window.findChild(TactileMapWidget, "pressureMap")
    stiffness = window.findChild(TactileMapWidget, "stiffnessMap")
    face_m2 = 60 * 4e-6
    assert pressure.auto_floor_pa() == pytest.approx(1.5 * 7.0 / face_m2)  # default F_max = 7 N
    window.set_ramp(RampSettings(force_min_N=2.0, force_max_N=12.0, force_step_N=2.0))
    assert pressure.auto_floor_pa() == pytest.approx(1.5 * 12.0 / face_m2)
    assert stiffness.auto_floor_pa() == pytest.approx(100e3)
