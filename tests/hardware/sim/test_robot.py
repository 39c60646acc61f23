"""The simulated slave: inner-loop dynamics, rate limits, hold, readings and stalls, on a virtual clock."""

import math

import numpy as np
import pytest

from hardware.interfaces import ConnectionState, DeviceError
from hardware.sim.robot import SimSlave
from hardware.sim.settings import RobotSimSettings, SimSettings
from hardware.sim.world import SimWorld
from tissue.phantom import load_phantom
from tissue.winkler import WinklerTissue

T0 = 250.0  # a host-clock-like start, so nothing relies on time starting at zero
MS = 1e-3


def make_slave(**robot) -> SimSlave:
    phantom = load_phantom("flat")
    world = SimWorld(phantom, WinklerTissue(phantom), SimSettings(robot=RobotSimSettings(**robot)))
    slave = SimSlave(world)
    slave.open()
    slave.poll(T0)
    return slave


def run(slave: SimSlave, start_s: float, duration_s: float) -> list:
    """Poll at 1 kHz from start_s (exclusive) for duration_s; the readings, one per tick."""
    out = []
    for m in range(1, int(round(duration_s / MS)) + 1):
        slave.poll(start_s + m * MS)
        out.append(slave.latest())
    return out


def second_order_step(t: np.ndarray, bandwidth_hz: float, zeta: float) -> np.ndarray:
    wn = 2 * math.pi * bandwidth_hz
    wd = wn * math.sqrt(1 - zeta**2)
    return 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * t))


@pytest.mark.parametrize("bandwidth_hz, zeta", [(20.0, 0.7), (10.0, 0.5)])
def test_small_step_follows_the_configured_second_order_response(bandwidth_hz, zeta):
    slave = make_slave(bandwidth_hz=bandwidth_hz, damping_ratio=zeta)
    home = slave.latest().position_m
    step = 1e-4  # small enough that no speed or acceleration limit is reached
    slave.command((home[0], home[1], home[2] + step), (0.0, 0.0, 0.0), T0)
    readings = run(slave, T0, 0.4)
    t = np.array([r.t_s for r in readings]) - T0
    z = (np.array([r.position_m[2] for r in readings]) - home[2]) / step
    assert np.abs(z - second_order_step(t, bandwidth_hz, zeta)).max() < 0.02
    # and the check can tell a 20 % slower loop apart
    assert np.abs(z - second_order_step(t, 0.8 * bandwidth_hz, zeta)).max() > 0.05
    assert abs(z[-1] - 1) < 1e-3


def test_large_move_respects_speed_and_acceleration_limits_and_lands_without_overshoot():
    slave = make_slave(max_speed_m_s=0.2, max_accel_m_s2=4.0)
    home = np.array(slave.latest().position_m)
    target = home + np.array([0.05, 0.0, -0.03])
    slave.command(tuple(target), (0.0, 0.0, 0.0), T0)
    readings = run(slave, T0, 1.0)
    v = np.array([r.velocity_m_s for r in readings])
    x = np.array([r.position_m for r in readings])
    speed = np.linalg.norm(v, axis=1)
    accel = np.linalg.norm(np.diff(v, axis=0), axis=1) / MS
    assert speed.max() <= 0.2 * (1 + 1e-9)
    assert speed.max() > 0.199  # the limit is what shaped the move
    assert accel.max() <= 4.0 * (1 + 1e-6)
    direction = (target - home) / np.linalg.norm(target - home)
    progress = (x - home) @ direction
    assert progress.max() - np.linalg.norm(target - home) < 0.2e-3
    assert np.linalg.norm(x[-1] - target) < 1e-5


def test_hold_brakes_within_the_acceleration_limit_and_stays_put():
    slave = make_slave(max_speed_m_s=0.2, max_accel_m_s2=4.0)
    home = slave.latest().position_m
    slave.command((home[0] + 0.1, home[1], home[2]), (0.0, 0.0, 0.0), T0)
    moving = run(slave, T0, 0.1)
    v0 = moving[-1].velocity_m_s[0]
    assert v0 > 0.15
    t_hold = T0 + 0.1
    slave.hold(t_hold)
    readings = run(slave, t_hold, 0.5)
    v = np.array([r.velocity_m_s[0] for r in readings])
    x = np.array([r.position_m[0] for r in readings])
    assert np.abs(np.diff(v)).max() / MS <= 4.0 * (1 + 1e-6)
    assert abs(v[-1]) < 1e-6
    travelled = x[-1] - moving[-1].position_m[0]
    assert v0**2 / (2 * 4.0) <= travelled <= 1.2 * v0**2 / (2 * 0.6 * 4.0)
    assert x[-1] < home[0] + 0.1 - 0.02  # stopped, not carried on to the old reference
    still = run(slave, t_hold + 0.5, 0.2)
    assert abs(still[-1].position_m[0] - x[-1]) < 1e-9


def hold_every_tick(slave: SimSlave, start_s: float, duration_s: float) -> list:
    """What the control loop does while it holds: call hold() on every 1 kHz tick."""
    out = []
    for m in range(int(round(duration_s / MS))):
        slave.hold(start_s + m * MS)
        slave.poll(start_s + (m + 1) * MS)
        out.append(slave.latest())
    return out


@pytest.mark.parametrize("speed", [0.075, 0.094, 0.2])
def test_a_hold_repeated_every_tick_stops_within_the_braking_plan(speed):
    # Before the stop point was latched, each call re-planned it ahead of the moving robot: an e-stop
    # at 0.075 m/s travelled 4.2 mm against a 0.94 mm plan.
    slave = make_slave(max_speed_m_s=speed, max_accel_m_s2=5.0)
    home = slave.latest().position_m
    slave.command((home[0] + 0.1, home[1], home[2]), (0.0, 0.0, 0.0), T0)
    moving = run(slave, T0, 0.2)
    v0 = moving[-1].velocity_m_s[0]
    assert v0 > 0.99 * speed
    readings = hold_every_tick(slave, T0 + 0.2, 0.5)
    travelled = readings[-1].position_m[0] - moving[-1].position_m[0]
    plan = v0**2 / (2 * 0.6 * 5.0)
    assert abs(readings[-1].velocity_m_s[0]) < 1e-6
    assert travelled <= plan + 0.05e-3


def test_a_hold_near_the_workspace_limit_stops_inside_it():
    # From 0.25 m/s the re-planned hold once ran 40 mm past the robot's own workspace.
    slave = make_slave(max_speed_m_s=0.25, max_accel_m_s2=5.0, workspace_max_m=(0.15, 0.10, 0.12))
    home = slave.latest().position_m
    for m in range(1, 2000):  # a reference ramping at full speed, as the loop sends one each tick
        t = T0 + m * MS
        slave.command((home[0] + 0.25 * (m * MS), home[1], home[2]), (0.25, 0.0, 0.0), t)
        slave.poll(t)
        if slave.latest().position_m[0] > 0.15 - 8e-3:  # inside its 10 mm braking distance, at speed
            break
    assert slave.latest().velocity_m_s[0] > 0.2
    readings = hold_every_tick(slave, T0 + m * MS, 0.5)
    assert max(r.position_m[0] for r in readings) <= 0.15 + 1e-3
    assert abs(readings[-1].velocity_m_s[0]) < 1e-6


def test_readings_come_at_the_robot_rate_and_do_not_depend_on_how_it_is_polled():
    regular = make_slave()
    irregular = make_slave()
    home = regular.latest().position_m
    ref = (home[0] + 0.01, home[1] - 0.005, home[2])
    for slave in (regular, irregular):
        slave.command(ref, (0.0, 0.0, 0.0), T0)
    seen = run(regular, T0, 0.3)
    assert [r.seq for r in seen] == list(range(1, 301))
    assert all(abs(r.t_s - (T0 + r.seq * MS)) < 1e-9 for r in seen)

    rng = np.random.default_rng(3)
    t = T0
    by_seq = {r.seq: r for r in seen}
    while t < T0 + 0.3:
        t += rng.uniform(0.2e-3, 3e-3)
        irregular.poll(t)
        irregular.poll(t)  # polling twice at the same time changes nothing
        r = irregular.latest()
        if r.seq in by_seq:
            assert r.position_m == pytest.approx(by_seq[r.seq].position_m, abs=1e-12)
            assert r.velocity_m_s == pytest.approx(by_seq[r.seq].velocity_m_s, abs=1e-12)


def test_a_host_stall_is_integrated_and_a_long_one_is_skipped_without_blowing_up():
    steady, stalled = make_slave(), make_slave()
    home = steady.latest().position_m
    ref = (home[0] + 0.02, home[1], home[2] - 0.01)
    for slave in (steady, stalled):
        slave.command(ref, (0.0, 0.0, 0.0), T0)
    run(steady, T0, 0.13)
    run(stalled, T0, 0.03)
    stalled.poll(T0 + 0.13)  # a 100 ms stall of the host
    assert stalled.latest().seq == steady.latest().seq == 130
    assert stalled.world.t_s == pytest.approx(T0 + 0.13, abs=1e-9)
    assert stalled.latest().position_m == pytest.approx(steady.latest().position_m, abs=1e-12)

    stalled.poll(T0 + 30.0)  # a debugger pause
    world = stalled.world
    assert world.skipped_s == pytest.approx(30.0 - 0.13 - world.settings.max_catchup_s, abs=1e-3)
    assert stalled.latest().seq == 30000
    assert stalled.latest().position_m == pytest.approx(ref, abs=1e-9)


def test_the_reference_is_clamped_into_the_workspace():
    slave = make_slave(workspace_min_m=(-0.05, -0.05, 0.01))
    home = slave.latest().position_m
    slave.command((home[0], home[1], -0.02), (0.0, 0.0, -0.05), T0)
    readings = run(slave, T0, 1.0)
    assert min(r.position_m[2] for r in readings) > 0.01 - 1e-4
    assert readings[-1].position_m[2] == pytest.approx(0.01, abs=1e-7)


def test_bad_references_are_refused_and_nothing_reaches_a_disconnected_robot():
    slave = make_slave()
    with pytest.raises(DeviceError, match="finite"):
        slave.command((0.0, math.nan, 0.0), (0.0, 0.0, 0.0), T0)
    with pytest.raises(DeviceError, match="three"):
        slave.command((0.0, 0.0), (0.0, 0.0, 0.0), T0)
    home = slave.latest().position_m
    slave.close()
    assert slave.connection == ConnectionState.DISCONNECTED
    slave.command((home[0] + 0.05, home[1], home[2]), (0.0, 0.0, 0.0), T0)
    slave.poll(T0 + 0.5)
    assert slave.latest().seq == 0  # no readings while closed
    slave.open()
    slave.poll(T0 + 0.5)
    assert slave.latest().position_m == pytest.approx(home, abs=1e-12)


def test_unplugging_stops_the_readings_and_the_watchdog_brakes_the_robot():
    slave = make_slave()
    home = slave.latest().position_m
    slave.command((home[0] + 0.1, home[1], home[2]), (0.0, 0.0, 0.0), T0)
    run(slave, T0, 0.05)
    last = slave.latest()
    slave.simulate_unplug()
    assert slave.connection == ConnectionState.LOST
    slave.poll(T0 + 1.0)
    assert slave.latest() is last
    x, v = slave.world.state_at(T0 + 1.0)
    assert np.linalg.norm(v) < 1e-6
    assert x[0] < home[0] + 0.05


@pytest.mark.parametrize("move_m", [(2e-4, 0.0, -1e-4), (0.005, 0.0, -0.003), (0.05, 0.01, -0.03)])
def test_the_1ms_world_grid_moves_the_robot_as_a_fine_grid_does(move_m):
    # exact steps where no limit acts, Euler sub-steps where one does: either way the trajectory must not
    # depend on the world's grid
    trajectories = []
    for substep in (1e-3, 5e-5):
        phantom = load_phantom("flat")
        world = SimWorld(phantom, WinklerTissue(phantom), SimSettings(substep_s=substep))
        slave = SimSlave(world)
        slave.open()
        slave.poll(T0)
        home = np.array(slave.latest().position_m)
        slave.command(tuple(home + np.array(move_m)), (0.0, 0.0, 0.0), T0)
        trajectories.append(np.array([r.position_m for r in run(slave, T0, 0.6)]) - home)
    coarse, fine = trajectories
    scale = np.linalg.norm(move_m)
    assert np.abs(coarse - fine).max() < 0.005 * scale  # 1 ms Euler steps in the limited phase: 1 %
    assert np.linalg.norm(coarse[-1] - move_m) < 1e-3 * scale
