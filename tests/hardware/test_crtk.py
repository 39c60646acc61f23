"""The CRTK backend against the fake dVRK arm, in a process of its own, on the loopback only."""

import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from hardware.crtk import dds
from hardware.crtk import messages as M
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
