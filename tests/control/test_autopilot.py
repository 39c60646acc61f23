"""The autopilot: plans from the phantom, and palpating areas in turn against the real loop (fast-forward)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.fastforward import FastForward
from app.rigs import RigSpec, build_rig, plan_for_rig
from control.autopilot import (
    ARRIVAL_TOLERANCE_M,
    Area,
    Autopilot,
    AutopilotError,
    AutopilotPlan,
    AutopilotState,
    plan_from_surface,
)
from control.config import ControlConfig, MasterMapping, RampSettings
from control.messages import CancelJog, CommandRefused, EStop, Jog, LevelRecorded, RegionDone, SetRegion, SetSz
from control.telemetry import empty_tick
from hardware.interfaces import Phase, TactileConstraints
from hardware.settings import ConfigError
from tissue.phantom import load_phantom

CONFIG = ControlConfig(ramp=RampSettings(force_min_N=0.5, force_max_N=1.0, force_step_N=0.5),
                       master=MasterMapping(jog_speed_m_s=0.04))
SPEC = RigSpec(master="none")
DISPLAY_TICKS = 16  # one update per display frame at 60 Hz


def drive(ff: FastForward, autopilot: Autopilot, until, timeout_s: float = 120.0) -> list:
    """Step the loop a display frame at a time, feeding the autopilot as the console does; returns the
    loop's events."""
    seen = []
    end = ff.now_s + timeout_s
    while not until() and ff.now_s < end:
        ff.step(DISPLAY_TICKS)
        for command in autopilot.update(ff.loop.tick, ff.events):
            ff.send(command)
        seen += ff.events
        ff.events = []
    assert until(), f"timed out: autopilot {autopilot.state.value}: {autopilot.message}"
    return seen


@pytest.fixture
def ff():
    driver = FastForward(CONFIG, build_rig(SPEC))
    yield driver
    driver.close()


def test_plan_from_the_flat_phantom_covers_it_in_strips():
    plan = plan_from_surface(load_phantom("flat"), TactileConstraints(), clearance_m=0.003, travel_z_m=0.045,
                             jog_speed_m_s=0.01)
    assert len(plan.areas) == 9 and [a.index for a in plan.areas] == list(range(9))
    assert [a.x_m for a in plan.areas] == pytest.approx([0.004 + 0.008 * k for k in range(9)])
    assert all(a.y_m == pytest.approx(0.015) for a in plan.areas)
    assert all(a.approach_z_m == pytest.approx(0.028) for a in plan.areas)  # 25 mm surface + 3 mm
    assert plan.phantom_extent_m == pytest.approx((0.0, 0.072, 0.0, 0.030))


def test_the_approach_height_clears_the_highest_point_under_the_face():
    phantom = load_phantom("uneven")
    plan = plan_from_surface(phantom, TactileConstraints(), clearance_m=0.003, travel_z_m=0.09, jog_speed_m_s=0.01)
    sensor = TactileConstraints()
    for area in plan.areas:
        x = np.linspace(area.x_m - 0.004, area.x_m + 0.004, 17)
        y = np.linspace(area.y_m - 0.015, area.y_m + 0.015, 61)
        top = float(np.max(phantom.surface_height_m(*np.meshgrid(x, y, indexing="ij"))))
        assert area.approach_z_m == pytest.approx(top + 0.003, abs=0.2e-3)
    assert sensor.size_m == (0.008, 0.030)


def test_plan_for_rig_uses_the_simulated_operator_settings_and_needs_a_phantom():
    plan = plan_for_rig(RigSpec(sim={"operator": {"travel_height_m": 0.05, "clearance_m": 0.004}}), CONFIG)
    assert plan.travel_z_m == 0.05 and plan.areas[0].approach_z_m == pytest.approx(0.029)
    assert plan.jog_speed_m_s == 0.04
    assert plan_for_rig(RigSpec(backend="udp"), CONFIG) is None
    with pytest.raises(ConfigError, match=r"sim.operator.travel_height_m: travel height 20.0 mm does not clear"):
        plan_for_rig(RigSpec(sim={"operator": {"travel_height_m": 0.02}}), CONFIG)


@pytest.mark.parametrize("kwargs, problem", [
    (dict(areas=()), "no areas"),
    (dict(travel_z_m=0.02), "does not clear the highest approach height 28.0 mm"),
    (dict(jog_speed_m_s=0.0), "jog speed must be > 0"),
    (dict(travel_z_m=math.nan), "not a finite number"),
])
def test_bad_plans_are_refused_with_the_reason(kwargs, problem):
    base = dict(areas=(Area(0, 0.004, 0.015, 0.028),), travel_z_m=0.045, jog_speed_m_s=0.01)
    with pytest.raises(AutopilotError, match=problem):
        AutopilotPlan(**{**base, **kwargs})


def test_start_checks_the_area_and_refuses_a_second_start():
    autopilot = Autopilot(plan_for_rig(SPEC, CONFIG))
    with pytest.raises(AutopilotError, match="no area 9 to start at: the plan has areas 0 to 8"):
        autopilot.start(9)
    autopilot.start(0)
    with pytest.raises(AutopilotError, match="already running"):
        autopilot.start(0)


def test_two_areas_are_palpated_in_turn_and_recorded_where_planned(ff):
    plan = plan_for_rig(SPEC, CONFIG)
    autopilot = Autopilot(plan)
    ff.run_for(0.1)
    autopilot.start(first_area=3)
    events = drive(ff, autopilot, lambda: len(autopilot.done_areas) == 2)
    records = [e.record for e in events if isinstance(e, LevelRecorded)]
    assert autopilot.running and autopilot.done_areas == [3, 4]
    assert [(r.region, r.level) for r in records] == [(3, 0), (3, 1), (4, 0), (4, 1)]
    for r in records:
        area = plan.areas[r.region]
        assert r.tsi_position_m[0] == pytest.approx(area.x_m, abs=0.5e-3)
        assert r.tsi_position_m[1] == pytest.approx(area.y_m, abs=0.5e-3)


def test_the_run_ends_at_the_travel_height(ff):
    plan = plan_for_rig(SPEC, CONFIG)
    autopilot = Autopilot(plan)
    ff.run_for(0.1)
    autopilot.start(first_area=8)
    drive(ff, autopilot, lambda: not autopilot.running)
    assert autopilot.state is AutopilotState.FINISHED and autopilot.message == "done: 1 areas palpated"
    tick = ff.loop.tick
    assert int(tick["phase"]) == Phase.DONE
    assert tick["x_slave_m"][2] == pytest.approx(plan.travel_z_m, abs=ARRIVAL_TOLERANCE_M)
    assert tick["x_slave_m"][0] == pytest.approx(plan.areas[8].x_m, abs=ARRIVAL_TOLERANCE_M)


def test_stop_cancels_the_rest_of_a_move(ff):
    autopilot = Autopilot(plan_for_rig(SPEC, CONFIG))
    ff.run_for(0.1)
    autopilot.start(first_area=0)
    drive(ff, autopilot, lambda: ff.loop.tick["x_des_m"][0] < 0.030)  # on its way from x = 36 mm to 4 mm
    commands = autopilot.stop()
    assert autopilot.state is AutopilotState.STOPPED and autopilot.message == "stopped by the operator"
    assert commands == [CancelJog()]
    for command in commands:
        ff.send(command)
    stopped_at = float(ff.loop.tick["x_des_m"][0])
    ff.run_for(2.0)
    assert float(ff.loop.tick["x_des_m"][0]) == pytest.approx(stopped_at, abs=1e-3)  # no further travel
    assert autopilot.update(ff.loop.tick, []) == []


def test_a_fault_stops_the_autopilot_with_its_explanation(ff):
    autopilot = Autopilot(plan_for_rig(SPEC, CONFIG))
    ff.run_for(0.1)
    autopilot.start(first_area=0)
    drive(ff, autopilot, lambda: ff.loop.tick["x_des_m"][0] < 0.030)
    ff.send(EStop("test"))
    drive(ff, autopilot, lambda: not autopilot.running, timeout_s=1.0)
    assert autopilot.state is AutopilotState.STOPPED
    assert autopilot.message.startswith("fault: Emergency stop: test.")


def synthetic_tick(phase=Phase.APPROACH, x=(0.036, 0.015, 0.06), tick=0):
    row = empty_tick()
    row["phase"] = phase
    row["x_des_m"] = row["x_slave_m"] = x
    row["tick"] = tick
    return row


def test_a_refused_command_or_someone_else_driving_stops_it():
    plan = AutopilotPlan((Area(0, 0.004, 0.015, 0.028),), travel_z_m=0.045, jog_speed_m_s=0.01)
    autopilot = Autopilot(plan)
    autopilot.start()
    assert autopilot.update(synthetic_tick()) == [Jog(pytest.approx((-0.032, 0.0, -0.015)))]
    refusal = CommandRefused(1.0, Jog((0.0, 0.0, 0.0)), "jog only while the operator holds position control")
    autopilot.update(synthetic_tick(), [refusal])
    assert autopilot.state is AutopilotState.STOPPED
    assert autopilot.message == "the controller refused Jog: jog only while the operator holds position control"

    autopilot.start()
    autopilot.update(synthetic_tick())
    autopilot.update(synthetic_tick(phase=Phase.SEEK_CONTACT))  # S_z switched by hand during the move
    assert autopilot.state is AutopilotState.STOPPED and "left position control (SEEK_CONTACT)" in autopilot.message


def test_palpation_starts_only_at_the_approach_height_and_waits_for_the_retract():
    plan = AutopilotPlan((Area(2, 0.004, 0.015, 0.028),), travel_z_m=0.045, jog_speed_m_s=0.01)
    autopilot = Autopilot(plan)
    autopilot.start()
    above = (0.004, 0.015, 0.045)
    autopilot.update(synthetic_tick(x=(0.004, 0.015, 0.06)))  # straight down to the travel height
    assert autopilot.update(synthetic_tick(x=above)) == [Jog(pytest.approx((0.0, 0.0, -0.017)))]
    low = (0.004, 0.015, 0.028)
    assert autopilot.update(synthetic_tick(x=low)) == [SetRegion(2), SetSz(position_control=False)]
    assert autopilot.update(synthetic_tick(Phase.SETTLING, low), []) == []
    autopilot.update(synthetic_tick(Phase.RETRACT, low, tick=10), [RegionDone(5.0, 2, 2)])
    # the first DONE tick still reports X_d from before the loop re-anchored it: wait for the next one
    assert autopilot.update(synthetic_tick(Phase.DONE, low, tick=11)) == []
    commands = autopilot.update(synthetic_tick(Phase.DONE, (0.004, 0.015, 0.033), tick=12))
    assert commands == [Jog(pytest.approx((0.0, 0.0, 0.012)))] and autopilot.done_areas == [2]


def test_a_move_is_timed_from_when_the_controller_takes_it_not_from_when_it_was_sent():
    plan = AutopilotPlan((Area(0, 0.004, 0.015, 0.028),), travel_z_m=0.045, jog_speed_m_s=0.01)
    autopilot = Autopilot(plan)
    autopilot.start()

    def at(t_s, x=(0.036, 0.015, 0.06)):
        row = synthetic_tick(x=x)
        row["t_s"] = t_s
        return row

    assert autopilot.update(at(0.0)) == [Jog(pytest.approx((-0.032, 0.0, -0.015)))]
    autopilot.update(at(20.0))  # the jog is slow to arrive (a loaded host): not a timeout yet
    assert autopilot.running
    autopilot.update(at(20.5, x=(0.035, 0.015, 0.0595)))  # taken: now the move's own clock runs
    autopilot.update(at(20.5 + 1.5 * 3.5 + 3.0 + 0.1, x=(0.035, 0.015, 0.0595)))
    assert autopilot.state is AutopilotState.STOPPED and "did not reach" in autopilot.message

    lost = Autopilot(plan)
    lost.start()
    lost.update(at(0.0))
    lost.update(at(31.0))
    assert lost.state is AutopilotState.STOPPED and "did not start the move" in lost.message
