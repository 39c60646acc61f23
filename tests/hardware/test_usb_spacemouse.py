"""A SpaceMouse as the master, through pyusb on an emulated bus: rate control, the S_z button, faults."""

import numpy as np
import pytest

from control.config import ControlConfig
from control.loop import ControlLoop
from control.messages import FaultKind, FaultRaised
from hardware.interfaces import (
    ConnectionState,
    DeviceError,
    MasterFeedback,
    Phase,
    SlaveState,
    TactileConstraints,
    TactileFrame,
)
from hardware.settings import ConfigError
from hardware.usb.emulator import EmulatedBackend, SpaceMouseDevice
from hardware.usb.spacemouse import ReportDecoder, SpaceMouseMaster, SpaceMouseSettings, pack_axes

T0 = 300.0
MS = 1e-3


def make(combined=False, **settings):
    device = SpaceMouseDevice(combined=combined)
    bus = EmulatedBackend(device)
    master = SpaceMouseMaster(SpaceMouseSettings(reconnect_interval_s=0.05, read_timeout_ms=20, **settings),
                              backend=bus)
    return device, bus, master


def deliver(master, device, now):
    """Poll at ``now`` until every report the device sent has been handled."""
    master.poll(now)
    while master.counters["reports"] + master.counters["ignored_reports"] < device.reports_sent:
        assert master.pipe.wait(2.0), "the reader thread delivered nothing"
        master.poll(now)


@pytest.fixture
def mouse():
    device, bus, master = make()
    master.open()
    master.pipe.wait(2.0)
    master.poll(T0)  # takes the "attached" marker
    yield device, bus, master
    master.close()


def run(master, start, ticks):
    for k in range(ticks):
        master.poll(start + k * MS)
    return master.latest()


def test_a_known_spacemouse_is_found_claimed_from_its_kernel_driver_and_reads_at_rest(mouse):
    device, bus, master = mouse
    assert master.connection == ConnectionState.CONNECTED
    assert not device.driver_bound[0] and 0 in device.claimed  # usbhid detached, interface claimed
    first = run(master, T0, 100)
    assert first.position_m == (0.0, 0.0, 0.0) and first.sz_switch is True
    assert first.t_s == T0 + 99 * MS  # a fresh sample every poll: a HID device is silent at rest


@pytest.mark.parametrize("combined", [False, True], ids=["split reports", "wireless report"])
def test_deflection_is_a_velocity_integrated_into_the_master_position(combined):
    device, _, master = make(combined)
    master.open()
    try:
        device.move((350, -175, 10), (30, 0, 0))  # full right, half towards the user, z in the deadband
        deliver(master, device, T0)
        state = run(master, T0 + MS, 200)  # 0.2 s
        x, y, z = state.position_m
        assert x == pytest.approx(0.02 * 0.2, rel=0.01)  # full speed, 20 mm/s
        shaped = (175 - 20) / (350 - 20)
        assert y == pytest.approx(+0.02 * shaped * 0.2, rel=0.01)  # towards the user is -y in the tissue frame
        assert z == 0.0
        assert master.decoder.rotation == (30, 0, 0)
        device.move((0, 0, 0))
        deliver(master, device, T0 + 0.3)
        assert run(master, T0 + 0.301, 100).position_m == pytest.approx(state.position_m, abs=0.02 * 0.1)
    finally:
        master.close()


def test_the_button_toggles_s_z_and_the_loop_hands_it_back(mouse):
    device, _, master = mouse
    device.buttons(0b01)
    device.buttons(0b00)
    deliver(master, device, T0)
    assert master.latest().sz_switch is False and master.stats["sz_presses"] == 1
    master.feedback(MasterFeedback(T0, int(Phase.SEEK_CONTACT), False, 0.0, False))
    master.poll(T0 + MS)
    assert master.latest().sz_switch is False  # force control, as asked
    master.feedback(MasterFeedback(T0, int(Phase.DONE), True, 0.0, False))
    master.poll(T0 + 2 * MS)
    assert master.latest().sz_switch is True  # the loop took z back: the next press asks again
    device.buttons(0b10)  # another button does nothing
    deliver(master, device, T0 + 3 * MS)
    assert master.latest().sz_switch is True


def test_a_cap_that_falls_silent_while_deflected_is_taken_as_released(mouse):
    device, _, master = mouse
    device.move((350, 0, 0))
    deliver(master, device, T0)
    moved = run(master, T0 + MS, 250).position_m[0]  # no report after the first
    held = run(master, T0 + 0.3, 300).position_m[0]
    assert held == moved and master.stats["report_timeouts"] == 1
    assert "taken as released" in master.stats["last_error"]


def test_unknown_and_short_reports_are_ignored_and_counted(mouse):
    device, _, master = mouse
    device.report(bytes([0x17, 100]))  # battery level
    device.report(bytes([1, 5, 0]))  # truncated translation
    device.report(pack_axes(1, (350, 0, 0)))
    deliver(master, device, T0)
    st = master.stats
    assert (st["unknown_reports"], st["short_reports"], st["ignored_reports"], st["reports"]) == (1, 1, 2, 1)


def test_unplugging_stops_the_readings_the_loop_lifts_and_holds_and_a_replug_does_not_jump(mouse):
    device, _, master = mouse
    loop = ControlLoop(ControlConfig(), TactileConstraints(), has_master=True)
    noise = np.random.default_rng(0)  # an array in air reads its noise (one that repeats itself is frozen)
    events = []

    def tick(k):
        now = T0 + k * MS
        master.poll(now)
        result = loop.step(now, TactileFrame(k, now, noise.normal(0.0, 30.0, (4, 15))),
                           SlaveState(k, now, (0.03, 0.015, 0.06), (0, 0, 0)), master.latest())
        events.extend(result.events)

    device.move((200, 0, 0))
    deliver(master, device, T0)
    for k in range(1, 100):
        tick(k)
    device.unplug()
    while master.connection != ConnectionState.LOST:
        assert master.pipe.wait(2.0)
        master.poll(T0 + 0.1)
    before = master.latest()
    for k in range(101, 200):
        tick(k)
    assert master.latest() is before and "stopped answering" in master.stats["last_error"]
    fault = next(e for e in events if isinstance(e, FaultRaised))
    assert fault.kind == FaultKind.MASTER_STALE

    device.replug()
    while master.connection != ConnectionState.CONNECTED:
        assert master.pipe.wait(2.0)
        master.poll(T0 + 0.2)
    after = run(master, T0 + 0.201, 50)
    assert after.position_m == before.position_m  # the cap starts centred; nothing jumped
    assert master.stats["reconnects"] == 1


def test_no_spacemouse_and_bad_settings_are_explained():
    with pytest.raises(DeviceError, match="no 3Dconnexion SpaceMouse is connected"):
        SpaceMouseMaster(backend=EmulatedBackend()).open()
    with pytest.raises(ConfigError, match="three of 1 or -1") as err:
        SpaceMouseSettings.from_mapping({"axis_signs": [1, 0, 1]}, "hardware.master.")
    assert err.value.key == "hardware.master.axis_signs"
    with pytest.raises(ConfigError, match="USB id like"):
        SpaceMouseSettings(vid_pid="spacemouse")
    with pytest.raises(ConfigError, match="velocity limit"):
        SpaceMouseSettings(speed_m_s=1.0)


def test_report_decoder_reads_the_documented_layouts():
    d = ReportDecoder()
    assert d.feed(bytes([1]) + (300).to_bytes(2, "little", signed=True) + (-2).to_bytes(2, "little", signed=True)
                  + (7).to_bytes(2, "little", signed=True))
    assert d.translation == (300, -2, 7)
    assert d.feed(bytes([3, 0x05, 0x00])) and d.buttons == 0b101
