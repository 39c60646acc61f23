"""The real-hardware rig as the config describes it, over the UDP link and its slave server."""

import select
import threading
import time
from types import SimpleNamespace

import pytest

from app.runtime import make_loop, run_tick
from control.config import ControlConfig
from hardware.interfaces import ConnectionState
from hardware.serial_tactile import SerialTactileSensor
from hardware.serial_tactile.emulator import SerialSensorEmulator, SimSensorFeed
from hardware.settings import ConfigError
from hardware.sim.rig import build_sim_rig
from hardware.udp import SlaveServer, SlaveServerSettings, UdpSlaveLink, UdpTactileSensor
from hardware.udp.rig import HardwareSettings, build_hardware_rig, build_rig
from hardware.usb.emulator import EmulatedBackend, SpaceMouseDevice
from hardware.usb.spacemouse import SpaceMouseMaster
from session.info import calibration_of


@pytest.mark.parametrize("table, key, problem", [
    ({"sensor": {"kind": "bluetooth"}}, "hardware.sensor.kind", "unknown kind 'bluetooth'"),
    ({"sensor": {"port": "/dev/ttyACM0"}}, "hardware.sensor.port", r"unknown key \(known: cover_spread_m\)"),
    ({"sensor": {"cover_spread_m": 0.005}}, "hardware.sensor.cover_spread_m", "between 0 and 0.002"),
    ({"sensor": {"kind": "serial"}}, "hardware.sensor.port", "non-empty"),
    ({"master": {"kind": "spacemouse", "speed": 1}}, "hardware.master.speed", "unknown key"),
    ({"slave": {"port": 70000}}, "hardware.slave.port", "within"),
    ({"slave": {"timeout_s": 0}}, "hardware.slave.timeout_s", "between 0.002 and 5"),
    ({"robot": {}}, "hardware.robot", "unknown table"),
])
def test_bad_hardware_tables_name_the_key(table, key, problem):
    with pytest.raises(ConfigError, match=problem) as err:
        HardwareSettings.from_mapping(table)
    assert err.value.key == key


def test_the_default_rig_is_the_slave_with_its_forwarded_sensor_and_the_console_jog():
    rig = build_rig(SimpleNamespace(hardware={}))
    assert isinstance(rig.slave, UdpSlaveLink) and isinstance(rig.sensor, UdpTactileSensor) and rig.master is None
    assert rig.description["hardware"]["sensor"] == {"kind": "udp", "cover_spread_m": 0.0}
    assert calibration_of(rig.sensor.constraints, 0.0)["cover_spread_m"] == 0.0  # none stated


def test_the_forwarded_arrays_cover_is_stated_in_the_config_and_recorded_for_the_analysis():
    # the slave's frames say nothing of the array's cover: a lab states it, as for an array the console reads
    rig = build_rig(SimpleNamespace(hardware={"sensor": {"kind": "udp", "cover_spread_m": 0.8e-3}}))
    assert isinstance(rig.sensor, UdpTactileSensor)
    assert calibration_of(rig.sensor.constraints, 0.0)["cover_spread_m"] == 0.8e-3
    assert rig.description["hardware"]["sensor"] == {"kind": "udp", "cover_spread_m": 0.8e-3}


def test_a_rig_of_real_backends_runs_the_loop(tmp_path):
    """Slave server on the simulated robot, its sensor on a serial line, a SpaceMouse on USB."""
    sim = build_sim_rig("flat")
    server = SlaveServer(sim.slave, SlaveServerSettings(port=0, forward_tactile=False), sensor=sim.sensor)
    server.open()
    emulator = SerialSensorEmulator(directory=tmp_path)
    feed = SimSensorFeed(sim.sensor, emulator.device)
    bus = EmulatedBackend(SpaceMouseDevice())
    settings = HardwareSettings.from_mapping({
        "slave": {"port": server.address[1]},
        "sensor": {"kind": "serial", "port": emulator.path},
        "master": {"kind": "spacemouse", "read_timeout_ms": 20},
    })
    rig = build_hardware_rig(settings, usb_backend=bus)
    assert isinstance(rig.sensor, SerialTactileSensor) and isinstance(rig.master, SpaceMouseMaster)
    loop = make_loop(ControlConfig(), rig)
    stop = threading.Event()
    serving = threading.Thread(target=server.serve, args=(stop,), kwargs={"on_step": feed.pump})
    rig.open()
    serving.start()
    frames_seen = set()
    try:
        deadline = time.monotonic() + 10.0
        # real time, paced by the sockets and the serial line: each tick waits for whichever speaks first
        while len(frames_seen) < 20 or rig.slave.connection != ConnectionState.CONNECTED:
            assert time.monotonic() < deadline, f"the rig never came up: {rig.sensor.stats} {rig.slave.stats}"
            select.select([rig.sensor.fileno(), rig.slave.fileno()], [], [], 1e-3)
            run_tick(loop, rig, time.monotonic())
            if rig.sensor.latest() is not None:
                frames_seen.add(rig.sensor.latest().seq)
        # (whether a tick is ever late here depends on the host: two ends in one process share the GIL;
        # the fault handling itself is tested on a virtual clock)
        assert rig.sensor.connection == ConnectionState.CONNECTED
        assert rig.master.connection == ConnectionState.CONNECTED and rig.master.latest() is not None
        assert loop.tick["sensor_seq"] == rig.sensor.latest().seq  # the loop reads the serial frames
        assert rig.slave.stats["force_N"] == pytest.approx(0.0, abs=0.05)  # the slave measures, in the air
    finally:
        stop.set()
        serving.join()
        rig.close()
        server.close()
        emulator.close()
