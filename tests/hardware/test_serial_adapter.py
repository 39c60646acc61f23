"""The serial tactile adapter on a real pseudo-terminal: calibration, clock, faults, unplug/replug, and the
control loop's watchdog holding when the sensor goes stale.

Time seen by the adapter is a virtual clock passed to ``poll``; only the bytes travel for real, and the
tests wait for them on the port's descriptor (select), never by sleeping.
"""

import select

import numpy as np
import pytest

from control.config import ControlConfig
from control.loop import ControlLoop
from control.messages import FaultKind, FaultRaised
from hardware.interfaces import ConnectionState, DeviceError, SlaveState
from hardware.serial_tactile import Calibration, SerialTactileSensor, SerialTactileSettings
from hardware.serial_tactile.driver import encode_frame
from hardware.serial_tactile.emulator import SerialSensorEmulator
from hardware.settings import ConfigError

T0 = 500.0
RNG = np.random.default_rng(3)


GAIN = 24.0 * (1.0 + 0.05 * RNG.standard_normal((4, 15)))
QUANTUM = float(GAIN.max())  # half a count in the frame, half in the tare


@pytest.fixture
def emulator(tmp_path):
    offset = RNG.integers(30, 80, (4, 15)).astype(float)
    cal = Calibration(GAIN, offset, np.ones((4, 15)), device="bench TSI")
    cal.save(tmp_path / "tsi.toml")
    with SerialSensorEmulator(cal, directory=tmp_path) as emu:
        yield emu


@pytest.fixture
def sensor(emulator, tmp_path):
    s = SerialTactileSensor(SerialTactileSettings(port=emulator.path, calibration=str(tmp_path / "tsi.toml"),
                                                  frame_timeout_s=0.05))
    s.open()
    yield s
    s.close()


def wait_readable(sensor, timeout_s=2.0) -> None:
    fd = sensor.fileno()
    assert fd is not None, "the port is not open"
    ready, _, _ = select.select([fd], [], [], timeout_s)
    assert ready, "the emulator's bytes never arrived"


def deliver(sensor, now_s, write) -> None:
    """Write through the emulator, wait until the bytes are at the port, poll once at ``now_s``."""
    write()
    wait_readable(sensor)
    sensor.poll(now_s)


def pressure(k: float) -> np.ndarray:
    return 1000.0 * k * (1.0 + np.arange(60).reshape(4, 15) / 60.0)


def test_frames_arrive_calibrated_tared_and_on_the_host_clock(emulator, sensor):
    assert sensor.connection == ConnectionState.CONNECTING
    for k in range(10):
        t = T0 + 0.01 * k
        deliver(sensor, t + 0.002, lambda k=k, t=t: emulator.send(pressure(k), t))
        frame = sensor.latest()
        assert frame.seq == k
        # zeroed at the first frame; 24 Pa counts, so within half a count per element
        assert np.allclose(frame.pressure_pa, pressure(k) - pressure(0), atol=QUANTUM)
        # the device clock (5000 s off) mapped back: sampled at t, seen at the earliest 2 ms later
        assert frame.t_s == pytest.approx(t + 0.002, abs=1e-5)
    assert sensor.connection == ConnectionState.CONNECTED
    assert sensor.stats["frames"] == 10 and sensor.stats["crc_errors"] == 0


def test_garbage_truncated_and_corrupt_frames_are_survived_and_counted(emulator, sensor):
    deliver(sensor, T0, lambda: emulator.send(pressure(1), T0))
    good = emulator.device.frame_bytes(pressure(2), T0 + 0.01)
    corrupt = bytearray(emulator.device.frame_bytes(pressure(3), T0 + 0.02))
    corrupt[60] ^= 0xFF
    truncated = emulator.device.frame_bytes(pressure(4), T0 + 0.03)[:90]
    last = emulator.device.frame_bytes(pressure(5), T0 + 0.04)
    junk = b"\x00\xffnoise\xa5\x00" * 20
    deliver(sensor, T0 + 0.05, lambda: emulator.write(junk + good + bytes(corrupt) + truncated + last))
    while sensor.latest().seq != 4:  # the pty may hand the burst over in pieces
        wait_readable(sensor)
        sensor.poll(T0 + 0.05)
    st = sensor.stats
    assert (st["frames"], st["crc_errors"], st["truncated"]) == (3, 1, 1)
    assert st["garbage_bytes"] >= len(junk) and st["frames_lost"] == 2
    assert np.allclose(sensor.latest().pressure_pa, pressure(5) - pressure(1), atol=QUANTUM)
    assert sensor.connection == ConnectionState.CONNECTED


def test_unplug_stops_the_readings_and_a_replug_resumes_them_with_the_tare_kept(emulator, sensor):
    deliver(sensor, T0, lambda: emulator.send(pressure(1), T0))
    deliver(sensor, T0 + 0.01, lambda: emulator.send(pressure(2), T0 + 0.01))
    before = sensor.latest()

    emulator.unplug()
    sensor.poll(T0 + 0.02)
    assert sensor.connection == ConnectionState.LOST
    assert "unplugged" in sensor.stats["last_error"] and sensor.stats["disconnects"] == 1
    for now in (T0 + 0.1, T0 + 0.6, T0 + 1.2):  # retries every 0.5 s; the port is gone meanwhile
        sensor.poll(now)
        assert sensor.latest() is before and sensor.connection == ConnectionState.LOST
    assert "there is no serial port" in sensor.stats["last_error"]

    emulator.replug()
    sensor.poll(T0 + 1.25)  # before the next retry: nothing happens yet
    assert sensor.fileno() is None
    sensor.poll(T0 + 1.75)
    assert sensor.connection == ConnectionState.CONNECTING and sensor.stats["reconnects"] == 1
    deliver(sensor, T0 + 1.80, lambda: emulator.send(pressure(3), T0 + 1.79))
    assert sensor.connection == ConnectionState.CONNECTED
    assert sensor.latest().seq > before.seq
    assert np.allclose(sensor.latest().pressure_pa, pressure(3) - pressure(1), atol=QUANTUM)  # same zero as before
    assert sensor.latest().t_s == pytest.approx(T0 + 1.80, abs=1e-5)  # the clock was re-learnt


def test_a_device_slower_than_the_loop_goes_stale_and_the_loop_holds(emulator, sensor):
    config = ControlConfig()
    loop = ControlLoop(config, sensor.constraints, has_master=False)
    here = (0.03, 0.015, 0.06)
    events = []
    frame_every = 100  # ticks: 10 frames/s, while the loop's limit is 60 ms and the adapter's 50 ms
    for tick in range(1500):
        now = T0 + tick * 1e-3
        if tick % frame_every == 0:
            emulator.send(pressure(0.1), now - 0.001)
            wait_readable(sensor)
        sensor.poll(now)
        slave = SlaveState(tick, now, here, (0.0, 0.0, 0.0))
        result = loop.step(now, sensor.latest(), slave, None)
        events += result.events
        if tick in (51, 151):
            assert sensor.connection == ConnectionState.LOST  # over 50 ms after the last frame
            assert "no good frame" in sensor.stats["last_error"]
        elif tick in (100, 200):
            assert sensor.connection == ConnectionState.CONNECTED  # a good frame again
    faults = [e for e in events if isinstance(e, FaultRaised)]
    assert faults and faults[0].kind == FaultKind.SENSOR_STALE
    # the first frame, read at tick 0, is over the loop's 60 ms limit at tick 61
    assert faults[0].t_s - T0 == pytest.approx(0.061, abs=1.5e-3)
    assert sensor.stats["stale_episodes"] >= 2 and sensor.stats["frame_rate_hz"] == pytest.approx(10.0, rel=0.05)


def test_a_line_that_cannot_keep_up_shows_as_lost_frames_and_device_overruns(emulator, sensor):
    deliver(sensor, T0, lambda: emulator.send(pressure(1), T0))
    for k in range(2000):  # 272 kB while nobody reads: the line fills and drops frames
        emulator.send(pressure(1), T0 + 0.001 * k)
    assert emulator.port.dropped_bytes > 0
    while True:  # drain what the line kept, 4 kB per poll
        sensor.poll(T0 + 3)
        ready, _, _ = select.select([sensor.fileno()], [], [], 0.05)
        if not ready:
            break
    deliver(sensor, T0 + 3, lambda: emulator.send(pressure(2), T0 + 2.9))
    st = sensor.stats
    assert st["device_overruns"] >= 1 and st["frames_lost"] > 0
    assert sensor.latest().seq == 2001 and sensor.connection == ConnectionState.CONNECTED


def test_tare_zeroes_the_current_reading(emulator, sensor):
    deliver(sensor, T0, lambda: emulator.send(pressure(1), T0))
    deliver(sensor, T0 + 0.01, lambda: emulator.send(pressure(2), T0 + 0.01))
    sensor.tare()
    deliver(sensor, T0 + 0.02, lambda: emulator.send(pressure(2), T0 + 0.02))
    assert np.allclose(sensor.latest().pressure_pa, 0.0, atol=QUANTUM)


def test_a_saturated_first_frame_is_not_taken_as_zero_and_saturation_is_flagged(emulator, sensor):
    # Issue 14, finding 3: a saturated first frame was the zero, and a true 48 N load then read -336 N.
    deliver(sensor, T0, lambda: emulator.send(np.full((4, 15), 150e3), T0))
    assert "not tared on opening" in sensor.stats["last_error"] and "saturated" in sensor.stats["last_error"]
    load = np.full((4, 15), 200e3)  # 48 N over the array, twice its full scale
    deliver(sensor, T0 + 0.01, lambda: emulator.send(load, T0 + 0.01))
    frame = sensor.latest()
    assert frame.saturated.all()
    assert frame.pressure_pa.sum() * 4e-6 > 45.0  # what the load reads is never less than what it is
    with pytest.raises(DeviceError, match="not tared: 60 element.s. saturated"):
        sensor.tare()
    deliver(sensor, T0 + 0.02, lambda: emulator.send(np.zeros((4, 15)), T0 + 0.02))
    assert not sensor.latest().saturated.any()
    sensor.tare()  # clear of the tissue, the operator tares
    deliver(sensor, T0 + 0.03, lambda: emulator.send(pressure(1), T0 + 0.03))
    assert np.allclose(sensor.latest().pressure_pa, pressure(1), atol=QUANTUM)


def test_open_failures_are_sentences_a_user_can_act_on(emulator, tmp_path):
    with pytest.raises(DeviceError, match="there is no serial port .*plugged in"):
        SerialTactileSensor(SerialTactileSettings(port=str(tmp_path / "nothing"))).open()
    first = SerialTactileSensor(SerialTactileSettings(port=emulator.path))
    first.open()
    try:
        with pytest.raises(DeviceError, match="in use by another program"):
            SerialTactileSensor(SerialTactileSettings(port=emulator.path)).open()
    finally:
        first.close()
    with pytest.raises(DeviceError, match="calibration.*no such calibration file"):
        SerialTactileSensor(SerialTactileSettings(port=emulator.path, calibration=str(tmp_path / "none.toml")))


@pytest.mark.parametrize("table, key, problem", [
    ({}, "hardware.sensor.port", "non-empty"),
    ({"port": "/dev/ttyACM0", "baud": 9600}, "hardware.sensor.baud", "at most 7 frames/s"),
    ({"port": "/dev/ttyACM0", "bauds": 9600}, "hardware.sensor.bauds", "unknown key"),
    ({"port": "/dev/ttyACM0", "frame_timeout_s": 0.01}, "hardware.sensor.frame_timeout_s", "two frames"),
    ({"port": "/dev/ttyACM0", "tare_on_open": "yes"}, "hardware.sensor.tare_on_open", "true or false"),
    ({"port": "/dev/ttyACM0", "cover_spread_m": 0.005}, "hardware.sensor.cover_spread_m", "between 0 and 0.002"),
])
def test_bad_settings_name_the_key(table, key, problem):
    with pytest.raises(ConfigError, match=problem) as err:
        SerialTactileSettings.from_mapping(table, "hardware.sensor.")
    assert err.value.key == key


def test_the_cover_the_array_is_specified_with_goes_into_its_sessions_calibration():
    """issue 48: a lab states its array's cover, and the analysis's physics reads it from the session."""
    from session.info import calibration_of

    stated = SerialTactileSettings.from_mapping({"port": "/dev/ttyACM0", "cover_spread_m": 0.8e-3}, "hardware.sensor.")
    assert calibration_of(stated.constraints(), 0.0)["cover_spread_m"] == 0.8e-3
    unstated = SerialTactileSettings.from_mapping({"port": "/dev/ttyACM0"}, "hardware.sensor.")
    assert calibration_of(unstated.constraints(), 0.0)["cover_spread_m"] == 0.0


def test_the_stream_of_frames_is_the_documented_encoding(emulator, sensor):
    # what a firmware author would send by hand, straight from the documented layout
    counts = emulator.device.calibration.counts_for(pressure(1))
    raw = encode_frame(77, 123_456_789, counts)
    deliver(sensor, T0, lambda: emulator.write(raw))
    assert sensor.latest().seq == 0 and sensor.stats["frames"] == 1
