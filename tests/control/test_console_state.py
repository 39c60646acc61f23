"""The console's policy without Qt: the fault banner, jog and tare availability, settings requested and answered."""

from __future__ import annotations

import math

from control.config import ControlConfig, ImpedanceGains, RampSettings
from control.console_state import ConsoleState, fault_name
from control.messages import (
    CommandApplied,
    CommandRefused,
    FaultCleared,
    FaultKind,
    FaultRaised,
    Jog,
    SetGains,
    SetRamp,
    SetSz,
)
from control.telemetry import empty_tick
from hardware.interfaces import Phase


def tick(phase=Phase.APPROACH, fault=0, sz=1, master_age_s=math.nan):
    row = empty_tick()
    row["phase"], row["fault"], row["sz"], row["master_age_s"] = phase, fault, sz, master_age_s
    return row


def test_the_banner_says_the_loops_explanation_and_a_stopped_controller_outranks_it():
    state = ConsoleState()
    assert state.fault() is None
    state.on_tick(tick(Phase.HOLD, FaultKind.SENSOR_STALE))
    assert state.fault() == (FaultKind.SENSOR_STALE, "FAULT: sensor stale")  # its event was not seen
    state.on_event(FaultRaised(1.0, FaultKind.SENSOR_STALE, "no frame for 80 ms"))
    assert state.fault() == (FaultKind.SENSOR_STALE, "FAULT: sensor stale — no frame for 80 ms")
    # the loop's words naming the fault themselves are not preceded by its name again
    state.on_event(FaultRaised(1.5, FaultKind.SENSOR_STALE, "Sensor stale: no frame for 80 ms"))
    assert state.fault() == (FaultKind.SENSOR_STALE, "FAULT: Sensor stale: no frame for 80 ms")
    state.on_event(FaultCleared(2.0, FaultKind.SENSOR_STALE))
    state.on_tick(tick())
    assert state.fault() is None
    state.crashed("killed by SIGKILL")
    kind, text = state.fault()
    assert kind == FaultKind.CONTROLLER and text.startswith("CONTROLLER STOPPED — killed by SIGKILL.")
    state.started()
    assert state.fault() is None
    assert fault_name(99) == "fault 99"


def test_jog_and_tare_are_offered_only_between_areas_with_nothing_holding_the_robot():
    state = ConsoleState()
    assert state.jog_unavailable() == "waiting for the controller" and not state.can_tare()
    state.on_tick(tick())
    assert state.jog_unavailable() is None and state.can_tare()
    assert state.jog_unavailable(autopilot_running=True) == "the autopilot is driving the TSI"
    state.on_tick(tick(Phase.SETTLING, sz=0))
    assert "between areas" in state.jog_unavailable() and not state.can_tare()
    state.on_tick(tick(Phase.DONE))
    assert state.jog_unavailable() is None and state.can_tare()
    state.on_tick(tick(Phase.HOLD, FaultKind.ESTOP))
    assert state.jog_unavailable() == "a fault holds the robot" and not state.can_tare()
    state.on_tick(tick(master_age_s=0.002))
    assert "master device" in state.jog_unavailable()
    state.crashed("gone")
    assert state.jog_unavailable() == "the controller is not running" and not state.can_tare()


def test_settings_stay_pending_until_the_controller_applies_or_refuses_them():
    config = ControlConfig()
    state = ConsoleState(config)
    assert state.ramp.applied == config.ramp and state.ramp.pending is None
    wanted = RampSettings(force_max_N=3.0)
    command = state.request(SetRamp(wanted))
    assert command == SetRamp(wanted) and state.ramp.pending == wanted
    state.on_event(CommandApplied(1.0, SetRamp(wanted), "Ramp set"))
    assert state.ramp.applied == wanted and state.ramp.pending is None and state.ramp.refusal is None

    gains = ImpedanceGains(stiffness_N_m=(1600.0, 1600.0, 2000.0))
    state.request(SetGains(gains))
    state.on_event(CommandRefused(2.0, Jog((0.0, 0.0, 1e-3)), "not this one"))  # about another command
    assert state.gains.pending == gains
    state.on_event(CommandRefused(2.0, SetGains(gains), "settings can change only between regions"))
    assert state.gains.pending is None and state.gains.applied == config.gains
    assert state.gains.refusal == "settings can change only between regions"


def test_a_refused_sz_stops_pending_at_once_and_an_accepted_one_when_the_tick_shows_it():
    state = ConsoleState()
    state.on_tick(tick(sz=1))
    assert state.sz.applied is True
    state.request(SetSz(position_control=False))
    assert state.sz.pending is False
    state.on_event(CommandRefused(1.0, SetSz(position_control=False), "clear the fault first"))
    assert state.sz.pending is None and state.sz.refusal == "clear the fault first"
    state.request(SetSz(position_control=False))
    state.on_tick(tick(Phase.SEEK_CONTACT, sz=0))
    assert state.sz.applied is False and state.sz.pending is None
    state.request(SetSz(position_control=True))
    state.stopped()  # nobody will answer now
    assert state.sz.pending is None
