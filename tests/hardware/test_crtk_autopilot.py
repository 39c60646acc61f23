"""The console on a CRTK arm: the autopilot palpating the flat phantom through the fake dVRK arm, with the
simulated array riding on the arm's pose, and the palpation on the ROS 2 bus as it happens."""

import math

import numpy as np
import pytest

from app.bridge import ControllerBridge
from app.cli import build_parser, config_overrides
from app.controller import ControllerProcess, ControllerStartError, PacingOptions
from app.crtk_sim import ArmPoseWorld
from app.realtime import read_clocks
from app.rigs import RigSpec, bus_publisher, plan_for_rig
from app.ros_bus import EVENTS, LEVELS, STATE, TACTILE, BusPublisher, qos
from control.autopilot import Autopilot, AutopilotState
from control.config import ControlConfig, MasterMapping, RampSettings, SafetyLimits
from control.messages import FaultKind, FaultRaised, LevelRecord, LevelRecorded, PhaseChanged, RegionDone
from control.telemetry import FRAME_DTYPE, TICK_DTYPE, LoopHealth
from hardware.crtk import dds
from hardware.crtk import messages as M
from hardware.crtk.rig import build_rig as build_crtk_rig
from hardware.interfaces import DeviceError, Phase, SlaveConstraints, SlaveState
from hardware.settings import ConfigError
from session import mcap_export as bag
from session.format import rows_for_event
from tests.hardware import test_crtk

# the fake arm on a domain of this worker's own, and a participant of the test's (test_crtk's fixtures)
domain, fake_arm, listener = test_crtk.domain, test_crtk.fake_arm, test_crtk.listener

PLAIN = PacingOptions(realtime=False, pin_cpu=False)
# A short ramp: two levels, so that an area takes seconds of real time. The fake arm runs unprivileged on a
# machine the suite shares: its readings, and the array's frames made from them, are taken as stale (by the
# loop and by the slave's own watchdog) only after a second, the longest the loop allows, not after the 10 ms a
# 1 kHz robot is given, lest a stall of the host end the run (the whole suite on two loaded cores once left the
# arm silent for 251 ms).
STALE_S = 1.0
CONFIG = ControlConfig(ramp=RampSettings(force_min_N=0.5, force_max_N=1.0, force_step_N=0.5),
                       master=MasterMapping(jog_speed_m_s=0.04),
                       safety=SafetyLimits(slave_timeout_s=STALE_S, sensor_timeout_s=STALE_S))
# The phantom's corner 36 mm, 15 mm off the arm's base axis and 150 mm below it: the fake arm's home, 100 mm
# below its base, is 50 mm above the middle of the phantom (25 mm thick).
TISSUE_IN_BASE_M = [-0.036, -0.015, -0.15]
LAST_AREA = 8


def spec(domain, **slave) -> RigSpec:
    return RigSpec(backend="crtk", phantom="flat", hardware={
        "slave": {"domain": domain, "tissue_in_base_m": TISSUE_IN_BASE_M, "timeout_s": STALE_S, **slave},
        "sensor": {"kind": "sim"}})


class Rows:
    """A sink keeping every row the console received."""

    def __init__(self):
        self.ticks, self.frames, self.events = [np.zeros(0, TICK_DTYPE)], [np.zeros(0, FRAME_DTYPE)], []

    def driver_started(self):
        pass

    def add_rows(self, ticks, frames, events):
        self.ticks.append(ticks.copy())
        self.frames.append(frames.copy())
        self.events += events

    def driver_stopped(self, failure):
        pass


def test_the_autopilot_palpates_through_the_arm_and_the_bus_carries_the_palpation(qtbot, domain, fake_arm,
                                                                                   listener):
    fake_arm("--floor-z-m", "-0.125")  # the arm's own wrench from the phantom's surface
    rig = spec(domain)
    types = {topic: M.ros_message_type(name, bag.DEFINITIONS) for topic, name in bag.TOPICS}
    # a reader keeping everything, as `ros2 bag record` does
    keep = dds.Qos(dds.Policy.Reliability.Reliable(max_blocking_time=0), dds.Policy.History.KeepAll, dds.XCDR1)
    readers = {topic: listener.reader(dds.ros_topic(topic), types[topic], keep)
               for topic in (TACTILE, STATE, LEVELS, EVENTS)}
    holds = listener.reader(dds.ros_topic("PSM1/hold"), M.Empty, dds.COMMANDS)
    its_console = listener.writer(dds.ros_topic("PSM1/state_command"), M.StringStamped, dds.COMMANDS)

    autopilot = Autopilot(plan_for_rig(rig, CONFIG))
    bridge = ControllerBridge.for_process(CONFIG, rig, PLAIN)
    rows, publisher = Rows(), bus_publisher(rig)
    bridge.add_sink(rows)
    bridge.add_sink(publisher)
    bridge.snapshot.connect(lambda snapshot: [bridge.send(c) for c in autopilot.update(snapshot.tick,
                                                                                         snapshot.events)])
    try:
        with qtbot.waitSignal(bridge.started, timeout=30_000):
            bridge.start()
        for command in autopilot.start(LAST_AREA):
            bridge.send(command)
        qtbot.waitUntil(lambda: autopilot.state != AutopilotState.RUNNING, timeout=60_000)
        assert autopilot.state == AutopilotState.FINISHED, autopilot.message
        assert [e.region for e in rows.events if isinstance(e, RegionDone)] == [LAST_AREA]
        assert sum(isinstance(e, LevelRecorded) for e in rows.events) == 2
        assert not [e for e in rows.events if isinstance(e, FaultRaised)]
        assert not dds.take(holds, 10)

        # the arm disabled from its own console: a fault, and the arm is told to hold
        its_console.write(M.StringStamped(string="disable"))
        qtbot.waitUntil(lambda: any(isinstance(e, FaultRaised) for e in rows.events), timeout=10_000)
        qtbot.waitUntil(lambda: len(dds.take(holds, 10)) > 0, timeout=10_000)
        fault = next(e for e in rows.events if isinstance(e, FaultRaised))
        # the arm's readings stop, and the array made from them with them: whichever the loop sees first
        assert fault.kind in (FaultKind.SLAVE_STALE, FaultKind.SENSOR_STALE), fault
        with qtbot.waitSignal(bridge.stopped, timeout=10_000):
            bridge.stop()
    finally:
        bridge.shutdown()

    ticks, frames = np.concatenate(rows.ticks), np.concatenate(rows.frames)
    assert ticks["phase"].min() == Phase.APPROACH and Phase.SETTLING in ticks["phase"]
    # every frame the console had, in order, on the bus: its pressures, and stamps as far apart as its times
    images = [s for s in dds.take(readers[TACTILE], 100_000)]
    assert len(images) == len(frames) > 100
    pressures = np.array([np.frombuffer(bytes(s.data), "<f4").reshape(s.height, s.width) for s in images])
    np.testing.assert_array_equal(pressures, frames["pressure_pa"])
    assert pressures.max() > 1e3, "the array never pressed the phantom"
    stamps = np.array([M.seconds(s.header.stamp) for s in images])
    np.testing.assert_allclose(stamps - stamps[0], frames["t_s"] - frames["t_s"][0], atol=1e-3)
    assert {s.encoding for s in images} == {"32FC1"} and {s.header.frame_id for s in images} == {bag.TSI_FRAME}
    # and the loop's state whenever it changed, phase by phase
    states = dds.take(readers[STATE], 100_000)
    changed, _ = bag.state_changes(ticks, None)
    assert [(s.phase, s.level, s.fault) for s in states] == \
        [(int(ticks["phase"][k]), int(ticks["level"][k]), int(ticks["fault"][k])) for k in changed]
    # and every level and event as the session file records them, as they came
    levels = dds.take(readers[LEVELS], 100)
    recorded = [e.record for e in rows.events if isinstance(e, LevelRecorded)]
    assert [(m.region, m.level, m.force_desired) for m in levels] == \
        [(r.region, r.level, r.force_desired_N) for r in recorded]
    np.testing.assert_array_equal([m.stiffness for m in levels], [r.stiffness_pa.ravel() for r in recorded])
    kinds = [rows_for_event(e)[0][2].decode() for e in rows.events if rows_for_event(e)[0] is not None]
    assert [m.kind for m in dds.take(readers[EVENTS], 100_000)] == kinds
    assert {"phase", "level", "region_done", "fault"} <= set(kinds)
    assert publisher.published["/palpation/force"] == len(ticks) and not publisher.problem


def test_the_console_refuses_an_arm_it_may_not_home(domain, fake_arm, listener):
    fake_arm()
    test_crtk.await_arm(listener)
    controller = ControllerProcess(CONFIG, spec(domain, home=False, open_timeout_s=1.0), PLAIN)
    with pytest.raises(ControllerStartError, match=r"arm PSM1 \(DDS domain \d+\) is ENABLED but not homed; the "
                                                    r"console drives it only ENABLED and homed"):
        controller.start()
    assert not controller.is_alive


def test_the_bag_s_encoding_is_the_dds_type_s():
    # what BusPublisher writes as bytes must be what a DDS reader of the declared type reads
    image = M.ros_message_type("sensor_msgs/Image", bag.DEFINITIONS)
    state = M.ros_message_type("palpation_console_msgs/LoopState", bag.DEFINITIONS)
    assert image.__idl_typename__ == "sensor_msgs::msg::dds_::Image_"
    assert M.ros_message_type("geometry_msgs/WrenchStamped", bag.DEFINITIONS) is M.WrenchStamped
    pressure = np.arange(60, dtype=np.float32).reshape(1, 4, 15)
    encoded = bag.encode_images(np.array([1_700_000_000_123_456_789]), pressure)[0]
    assert image.deserialize(encoded).serialize(use_version_2=False) == encoded
    tick = np.zeros(1, TICK_DTYPE)[0]
    tick["phase"], tick["level"], tick["n_levels"] = Phase.SETTLING, 1, 2
    encoded = bag.encode_state(1_700_000_000_000_000_000, tick)
    decoded = state.deserialize(encoded)
    assert (decoded.phase_name, decoded.level, decoded.n_levels) == ("SETTLING", 1, 2)
    assert decoded.serialize(use_version_2=False) == encoded
    with pytest.raises(ValueError, match="cannot read the field 'int32 x = 3'"):
        M.ros_message_type("a/B", {"a/B": "int32 x = 3\n"})


def test_publishing_is_on_with_the_crtk_rig_and_switchable():
    assert bus_publisher(RigSpec()) is None
    assert bus_publisher(RigSpec(backend="crtk", hardware={"sensor": {"kind": "sim"}})).domain == 0
    assert bus_publisher(RigSpec(backend="crtk", hardware={"sensor": {"kind": "sim"}, "bus": {"publish": False}})) \
        is None
    args = build_parser().parse_args(["run", "--backend", "crtk", "--no-publish"])
    assert config_overrides(args)["hardware"] == {"bus": {"publish": False}}
    with pytest.raises(ConfigError, match="--publish: is about the CRTK rig's ROS 2 bus"):
        config_overrides(build_parser().parse_args(["run", "--publish"]))
    with pytest.raises(ConfigError, match="hardware.bus.publish: must be true or false"):
        bus_publisher(RigSpec(backend="crtk", hardware={"sensor": {"kind": "sim"}, "bus": {"publish": "yes"}}))
    assert qos(STATE) != qos(TACTILE)  # the state is transient-local: a late subscriber has the phase at once


class Arm:
    """The readings an arm gave, one at a time."""

    constraints = SlaveConstraints(rate_hz=1000.0)

    def __init__(self):
        self.reading = None

    def latest(self):
        return self.reading


def test_the_array_s_world_interpolates_the_arm_s_readings():
    arm = Arm()
    world = ArmPoseWorld(arm, tissue=None, settings=None)
    world.advance(10.0)
    with pytest.raises(DeviceError, match="no reading of the arm's pose yet"):
        world.state_at(10.0)
    arm.reading = SlaveState(seq=0, t_s=10.0, position_m=(0.0, 0.0, 0.02), velocity_m_s=(0.0, 0.0, -0.01))
    world.advance(10.001)
    arm.reading = SlaveState(seq=1, t_s=10.002, position_m=(0.002, 0.0, 0.01), velocity_m_s=(0.0, 0.0, -0.03))
    world.advance(10.0025)
    arm.reading = SlaveState(seq=2, t_s=10.001, position_m=(9.0, 9.0, 9.0), velocity_m_s=(0.0, 0.0, 0.0))
    world.advance(10.003)  # stamped before the reading before it: nothing to interpolate
    position, velocity = world.state_at(10.0005)
    assert position == pytest.approx((0.0005, 0.0, 0.0175)) and velocity == pytest.approx((0.0, 0.0, -0.015))
    assert world.state_at(9.0)[0] == (0.0, 0.0, 0.02) and world.state_at(11.0)[0] == (0.002, 0.0, 0.01)
    assert world.instant_index(100.0) == 0 and world.instant_s(3, 100.0) == pytest.approx(10.03)
    world.advance(10.0301)
    assert world.instant_index(100.0) == 0, "a frame sampled after the arm's newest reading"
    arm.reading = SlaveState(seq=3, t_s=10.0302, position_m=(0.002, 0.0, 0.0), velocity_m_s=(0.0, 0.0, 0.0))
    world.advance(10.031)
    assert world.instant_index(100.0) == 3


def test_the_crtk_rig_needs_the_console_to_build_a_simulated_array():
    with pytest.raises(ConfigError, match="hardware.sensor.kind: the simulated array is built by the console"):
        build_crtk_rig(RigSpec(backend="crtk", hardware={"sensor": {"kind": "sim"}}))


def test_a_bus_that_fails_stops_publishing_and_says_so(domain):
    publisher = BusPublisher(domain)
    publisher.driver_started()
    ticks, frames = np.zeros(3, TICK_DTYPE), np.zeros(2, FRAME_DTYPE)
    ticks["t_s"], frames["t_s"] = (1.0, 1.001, 1.002), (1.0, 1.01)
    publisher.add_rows(ticks, frames, [])
    assert publisher.published == {"/palpation/tsi_pose": 3, "/palpation/force": 3, "/palpation/force_desired": 3,
                                   STATE: 1, TACTILE: 2, LEVELS: 0, EVENTS: 0}
    publisher._bus.close()  # the participant gone under it (what a DDS failure leaves)
    publisher.add_rows(ticks, frames, [])
    assert publisher.problem.startswith("The palpation is not published on the ROS 2 bus (")
    assert publisher._bus is None
    publisher.driver_stopped(None)


def grid(value: float) -> np.ndarray:
    return np.full((4, 15), value)


def test_levels_and_events_go_on_the_bus_as_they_come(qtbot, domain, listener):
    """What the session file records of the loop's events: a level as its /levels row and its /events row, other
    events as their /events rows, each stamped with the UTC of its loop time; the health reports the sinks are
    also handed, nothing."""
    keep = dds.Qos(dds.Policy.Reliability.Reliable(max_blocking_time=0), dds.Policy.History.KeepAll, dds.XCDR1)
    readers = {topic: listener.reader(dds.ros_topic(topic), M.ros_message_type(dict(bag.TOPICS)[topic],
                                                                               bag.DEFINITIONS), keep)
               for topic in (LEVELS, EVENTS)}
    publisher = BusPublisher(domain)
    publisher.driver_started()
    try:
        qtbot.waitUntil(lambda: all(r.get_matched_publications() for r in readers.values()), timeout=10_000)
        now_s, now_ns = read_clocks()
        stiffness = grid(40e3)
        stiffness[0, 0] = math.nan  # an element not in contact
        record = LevelRecord(region=2, level=1, t_s=now_s + 0.5, force_desired_N=2.0, force_measured_N=1.98,
                             rmse_N=0.01, settle_time_s=0.7, tsi_position_m=(0.012, 0.004, 0.021), indentation_m=0.002,
                             pressure_pa=grid(25e3), pressure_std_pa=grid(300.0), window_frames=30,
                             element_force_N=grid(0.1), onset_height_m=grid(0.023), L0_m=grid(0.02), dL_m=grid(0.002),
                             stiffness_pa=stiffness)
        health = LoopHealth(rate_hz=1000.0, late_over_0_5ms_pct=0.0, p99_abs_jitter_us=20.0, missed_ticks=0,
                            longest_stall_ms=0.4, rt_priority=True, cpu=1)
        publisher.add_rows(np.zeros(0, TICK_DTYPE), np.zeros(0, FRAME_DTYPE),
                           [PhaseChanged(now_s, Phase.SETTLING, 1, 3), health, LevelRecorded(now_s + 0.5, record)])
        publisher.add_rows(np.zeros(0, TICK_DTYPE), np.zeros(0, FRAME_DTYPE),
                           [FaultRaised(now_s + 1.0, FaultKind.FORCE_CEILING, "F_ts 7.6 N over the ceiling")])
        got: dict[str, list] = {LEVELS: [], EVENTS: []}

        def arrived() -> bool:
            for topic, reader in readers.items():
                got[topic] += dds.take(reader, 10)
            return len(got[LEVELS]) == 1 and len(got[EVENTS]) == 3

        qtbot.waitUntil(arrived, timeout=10_000)
    finally:
        publisher.driver_stopped(None)
    assert publisher.published[LEVELS] == 1 and publisher.published[EVENTS] == 3 and not publisher.problem
    events = got[EVENTS]
    assert [(e.kind, e.region, e.level, e.code, e.text) for e in events] == [
        ("phase", -1, 1, int(Phase.SETTLING), "SETTLING"), ("level", 2, 1, 0, ""),
        ("fault", -1, -1, int(FaultKind.FORCE_CEILING), "F_ts 7.6 N over the ceiling")]
    assert events[1].value == 2.0 and math.isnan(events[2].value)
    stamps_ns = [e.header.stamp.sec * 10**9 + e.header.stamp.nanosec for e in events]
    for stamp, after_s in zip(stamps_ns, (0.0, 0.5, 1.0)):  # UTC now, and as far after as the loop's times
        assert abs(stamp - (now_ns + after_s * 1e9)) < 5e6
    level = got[LEVELS][0]
    assert (level.region, level.level, level.force_measured, level.window_frames, level.rows, level.cols) == \
        (2, 1, 1.98, 30, 4, 15)
    assert (level.tsi_position.x, level.tsi_position.z, level.header.frame_id) == (0.012, 0.021, bag.TISSUE_FRAME)
    np.testing.assert_array_equal(level.stiffness, stiffness.ravel())
    np.testing.assert_array_equal(level.pressure, record.pressure_pa.ravel())
    assert level.header.stamp == events[1].header.stamp
