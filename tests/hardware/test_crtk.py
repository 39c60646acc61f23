"""The CRTK backend against the fake dVRK arm, in a process of its own, on the loopback only."""

import math
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from app.cli import build_parser, config_overrides
from app.config import load_config
from app.rigs import BACKENDS
from hardware.crtk import dds
from hardware.crtk import messages as M
from hardware.crtk.rig import CrtkHardwareSettings
from hardware.crtk.slave import CrtkSettings, CrtkSlave
from hardware.interfaces import ConnectionState, DeviceError
from hardware.settings import ConfigError

ROOT = Path(__file__).resolve().parents[2]


def until(predicate, timeout_s: float, what: str, step=None):
    """Call ``step`` (if any) and check ``predicate`` until it holds; fail saying ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        if step is not None:
            step()
        if predicate():
            return
        if time.monotonic() > deadline:
            pytest.fail(f"not within {timeout_s:g} s: {what}")
        time.sleep(0.001)


@pytest.fixture
def domain(worker_id):
    """A domain of this pytest-xdist worker's own, so that parallel tests never meet on the bus."""
    return 150 + (0 if worker_id == "master" else int(worker_id.removeprefix("gw")))


@pytest.fixture
def fake_arm(domain):
    """Start the fake arm (extra command-line options as arguments); stopped, and waited for, at the end."""
    started = []

    def start(*options):
        process = subprocess.Popen([sys.executable, "-m", "hardware.crtk.fake_arm", "--arm", "PSM1", "--domain",
                                    str(domain), *options], cwd=ROOT, stdout=subprocess.DEVNULL)
        started.append(process)
        return process

    yield start
    for process in started:
        if process.poll() is None:
            os.kill(process.pid, signal.SIGCONT)
            process.terminate()
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)
            pytest.fail("the fake arm did not stop on SIGTERM")


@pytest.fixture
def listener(domain):
    """A participant of the test's own on the domain, to see what the slave sends the arm."""
    bus = dds.Participant(domain)
    yield bus
    bus.close()


def await_arm(listener) -> None:
    """Until the fake arm's state is on the bus: a refusal is only about the arm once the arm is there (it starts
    in a second or two on a loaded machine; a test that waited a second for it was refused a silent arm)."""
    state = listener.reader(dds.ros_topic("PSM1/operating_state"), M.OperatingState, dds.LATCHED)
    until(lambda: bool(dds.take(state, 10)), 30.0, "the fake arm's operating_state")


def connected(domain, **settings) -> CrtkSlave:
    slave = CrtkSlave(CrtkSettings(domain=domain, **settings))
    slave.open()
    return slave


def pump(slave: CrtkSlave, target=None):
    """One tick of the console: poll, then command ``target`` (if any) when the arm can take it."""
    def step():
        now = time.monotonic()
        slave.poll(now)
        if target is not None and slave.connection == ConnectionState.CONNECTED:
            slave.command(target, (0.0, 0.0, 0.0), now)
    return step


def udp_sockets(pid: int) -> set[tuple[str, int]]:
    return {(c.laddr.ip, c.laddr.port) for c in psutil.Process(pid).net_connections(kind="udp")}


def test_participants_bind_to_the_loopback_only_and_join_no_multicast_group(domain, fake_arm, listener):
    # Cyclone's defaults would send from the machine's address and listen for multicast discovery on the
    # domain's port 7400 + 250 d on every interface: both are what must not be seen here.
    arm = fake_arm()
    ours = udp_sockets(os.getpid())
    until(lambda: len(udp_sockets(arm.pid)) >= 3, 10.0, "the fake arm's participant up")
    wildcard_ok = dds.unicast_ports(domain)
    for pid, sockets in ((os.getpid(), ours), (arm.pid, udp_sockets(arm.pid))):
        strays = {(ip, port) for ip, port in sockets if ip != "127.0.0.1" and not (ip == "0.0.0.0" and
                                                                                  port in wildcard_ok)}
        assert not strays, f"process {pid} bound {strays} besides the loopback"
        assert any(ip == "127.0.0.1" for ip, _ in sockets), "nothing sends from the loopback"
        assert dds.PORT_BASE + dds.DOMAIN_GAIN * domain not in {port for _, port in sockets}
    listener.close()
    assert not udp_sockets(os.getpid()), "closing the process's last participant left sockets open"


def test_a_participant_made_without_our_config_is_pinned_by_the_suite_s_environment(domain):
    # (tests/conftest.py sets CYCLONEDDS_URI: a library default or a participant made some other way)
    from cyclonedds.domain import DomainParticipant

    participant = DomainParticipant(domain + 50)
    try:
        sockets = udp_sockets(os.getpid())
        strays = {(ip, port) for ip, port in sockets if ip != "127.0.0.1" and not (
            ip == "0.0.0.0" and port in dds.unicast_ports(domain + 50))}
        assert sockets and not strays, f"bound {strays} besides the loopback"
    finally:
        participant.__del__()  # the binding deletes it once, now, not when the object is collected


def test_the_config_names_only_the_loopback():
    config = dds.loopback_config(7)
    for part in ('<Domain Id="7">', '<NetworkInterface name="lo" multicast="false"/>',
                 "<AllowMulticast>false</AllowMulticast>", '<Peer address="127.0.0.1"/>', 'AddLocalhost="false"'):
        assert part in config
    with pytest.raises(ConfigError, match="from 0 to 232"):
        dds.loopback_config(233)


def test_messages_are_ros2_types_in_xcdr1():
    assert M.PoseStamped.__idl_typename__ == "geometry_msgs::msg::dds_::PoseStamped_"
    assert M.OperatingState.__idl_typename__ == "crtk_msgs::msg::dds_::OperatingState_"
    sample = M.PoseStamped(header=M.Header(stamp=M.Time(1, 2), frame_id="b"),
                           pose=M.Pose(M.Point(0.5, -1.0, 2.0), M.Quaternion(0.0, 0.0, 0.0, 1.0)))
    # CDR little-endian: sec, nanosec, the frame's length and bytes with its NUL, padding to 8, seven doubles
    expected = (b"\x00\x01\x00\x00" + struct.pack("<iII", 1, 2, 2) + b"b\x00" + b"\x00\x00"
                + struct.pack("<7d", 0.5, -1.0, 2.0, 0.0, 0.0, 0.0, 1.0))
    assert sample.serialize(use_version_2=False) == expected
    for qos in (dds.STREAM, dds.LATCHED, dds.COMMANDS):
        assert dds.Policy.DataRepresentation(use_cdrv0_representation=True) in qos
    assert M.seconds(M.stamp(12.25)) == 12.25


def test_the_slave_refuses_a_disabled_or_unhomed_arm_in_one_line(domain, fake_arm, listener):
    fake_arm()
    await_arm(listener)
    with pytest.raises(DeviceError) as refused:
        connected(domain, enable=False, open_timeout_s=1.0)
    assert "arm PSM1 (DDS domain" in str(refused.value) and "is DISABLED and not homed" in str(refused.value)
    assert "\n" not in str(refused.value)
    with pytest.raises(DeviceError) as refused:
        connected(domain, home=False, open_timeout_s=1.0)
    assert "is ENABLED but not homed" in str(refused.value) and "hardware.slave.home = true" in str(refused.value)
    assert "\n" not in str(refused.value)


def test_a_silent_domain_is_refused_in_one_line(domain):
    with pytest.raises(DeviceError, match=r"no operating_state within 0.2 s.*ROS_DOMAIN_ID="):
        connected(domain, open_timeout_s=0.2)


def test_commands_reach_the_arm_in_its_base_frame_through_its_dynamics(domain, fake_arm, listener):
    fake_arm("--floor-z-m", "-0.12", "--floor-stiffness-N-m", "400")
    measured = listener.reader(dds.ros_topic("PSM1/measured_cp"), M.PoseStamped)
    # the tissue frame 0.2 m below the base, turned a quarter about z; the probe 10 mm below the tool
    slave = connected(domain, tissue_in_base_m=(0.01, 0.0, -0.2), tissue_in_base_rpy_deg=(0.0, 0.0, 90.0),
                      probe_in_tool_m=(0.0, 0.0, -0.01))
    try:
        start = slave.latest().position_m  # the fake arm's home, tool at (0, 0, -0.1) in the base frame
        assert start == pytest.approx((0.0, 0.01, 0.09), abs=1e-12)
        target = (0.002, 0.013, 0.085)
        seen = []
        until(lambda: math.dist(slave.latest().position_m, target) < 1e-6, 5.0, "the arm at the target",
              lambda: (pump(slave, target)(), seen.append(slave.latest().position_m[2])))
        # a few distinct places on the way: how many the polls catch depends on how busy the machine is (five,
        # with a study running on both cores), not on the arm; an arm that jumps to the goal shows none
        between = {z for z in seen if 0.085 + 1e-4 < z < 0.09 - 1e-4}
        assert len(between) >= 3, "the arm reached the goal without moving through the space between"
        tool = dds.take(measured, 1000)[-1].pose.position  # x_base = -y_tissue + 0.01, y_base = x_tissue
        assert (tool.x, tool.y, tool.z) == pytest.approx((-0.003, 0.002, -0.105), abs=1e-6)
        assert slave.force_N == 0.0
        pressed = (0.002, 0.013, 0.065)  # the probe at -0.135 in the base, the tool 5 mm into the floor at -0.12
        until(lambda: slave.force_N == pytest.approx(400 * 0.005, abs=1e-3), 5.0, "the floor's force",
              pump(slave, pressed))
        assert slave.connection == ConnectionState.CONNECTED and slave.stats["withheld"] == 0
    finally:
        slave.close()


def test_a_stalled_arm_is_lost_within_the_watchdog_and_held(domain, fake_arm, listener):
    arm = fake_arm()
    holds = listener.reader(dds.ros_topic("PSM1/hold"), M.Empty, dds.COMMANDS)
    slave = connected(domain, timeout_s=0.05)
    try:
        target = slave.latest().position_m
        until(lambda: slave.stats["servo_cp"] > 10, 2.0, "commands going out", pump(slave, target))
        assert not dds.take(holds, 10)
        os.kill(arm.pid, signal.SIGSTOP)
        stopped = time.monotonic()
        until(lambda: slave.connection == ConnectionState.LOST, 1.0, "LOST", pump(slave, target))
        # the arm's last reading may have been in flight when it stopped; beyond a tick or two, the watchdog's own
        assert time.monotonic() - stopped < 0.05 + 0.1
        assert "no measured_cp from arm PSM1" in slave.last_error
        until(lambda: len(dds.take(holds, 10)) == 1, 2.0, "one hold on the bus")
        sent = slave.stats["servo_cp"]
        pump(slave, target)()
        assert slave.stats["servo_cp"] == sent, "a servo_cp went out to a lost arm"
        os.kill(arm.pid, signal.SIGCONT)
        until(lambda: slave.connection == ConnectionState.CONNECTED, 2.0, "fresh readings again", pump(slave))
    finally:
        slave.close()


def test_an_arm_that_stops_being_enabled_is_a_fault_and_held(domain, fake_arm, listener):
    fake_arm()
    holds = listener.reader(dds.ros_topic("PSM1/hold"), M.Empty, dds.COMMANDS)
    its_console = listener.writer(dds.ros_topic("PSM1/state_command"), M.StringStamped, dds.COMMANDS)
    slave = connected(domain)
    try:
        its_console.write(M.StringStamped(string="disable"))
        until(lambda: slave.connection == ConnectionState.LOST, 2.0, "LOST", pump(slave))
        assert slave.last_error == "arm PSM1 is DISABLED and homed"
        until(lambda: len(dds.take(holds, 10)) == 1, 2.0, "one hold on the bus")
    finally:
        slave.close()


def test_close_sends_hold(domain, fake_arm, listener):
    fake_arm()
    holds = listener.reader(dds.ros_topic("PSM1/hold"), M.Empty, dds.COMMANDS)
    slave = connected(domain)
    pump(slave, slave.latest().position_m)()
    slave.close()
    until(lambda: len(dds.take(holds, 10)) == 1, 2.0, "the hold of close()")
    assert slave.connection == ConnectionState.DISCONNECTED
    slave.close()


@pytest.mark.parametrize("table, message", [
    ({"slave": {"domain": 300}}, "hardware.slave.domain: must be a whole number from 0 to 232"),
    ({"slave": {"arm": "PSM 1"}}, "hardware.slave.arm: must be a ROS namespace"),
    ({"slave": {"tissue_in_base_rpy_deg": [0, 90]}}, "hardware.slave.tissue_in_base_rpy_deg: must be three numbers"),
    ({"slave": {"probe_in_tool_m": [0, 0, 2]}}, r"hardware.slave.probe_in_tool_m\[2\]: must lie between -1 and 1"),
    ({"slave": {"timeout_s": 0}}, "hardware.slave.timeout_s: must lie between 0.002 and 5"),
    ({"slave": {"host": "x"}}, "hardware.slave.host: unknown key"),
    ({"sensor": {"kind": "sim", "port": "/dev/x"}}, "hardware.sensor.port: unknown key for kind .sim."),
    ({"sensor": {"kind": "sim"}, "bus": {"topics": 1}}, "hardware.bus.topics: unknown key"),
    ({"slave": {}}, "hardware.sensor.kind: the CRTK rig takes its tactile array from serial, usb or sim, got None"),
    ({"sensor": {"kind": "udp"}}, "hardware.sensor.kind: .* got 'udp'"),
    ({"sensor": {"kind": "serial", "port": "/dev/x"}, "robot": {}}, "hardware.robot: unknown table"),
])
def test_config_errors_are_one_line_naming_the_key(table, message):
    with pytest.raises(ConfigError, match=message) as err:
        CrtkHardwareSettings.from_mapping(table)
    assert "\n" not in str(err.value)


def test_the_command_line_drives_the_crtk_rig(tmp_path):
    args = build_parser().parse_args(["run", "--backend", "crtk", "--arm", "PSM2"])
    overrides = config_overrides(args)
    assert overrides == {"rig": {"backend": "crtk"}, "hardware": {"slave": {"arm": "PSM2"}}}
    config_file = tmp_path / "rig.toml"
    config_file.write_text('[hardware.sensor]\nkind = "serial"\nport = "/dev/ttyACM0"\n')
    config = load_config(config_file, overrides)
    rig = BACKENDS["crtk"](config.rig)
    assert rig.slave.settings.arm == "PSM2" and rig.description["backend"] == "crtk"
    with pytest.raises(ConfigError, match="--arm: names the arm of the CRTK rig"):
        config_overrides(build_parser().parse_args(["run", "--arm", "PSM1"]))
