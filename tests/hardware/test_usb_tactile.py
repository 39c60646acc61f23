"""The USB tactile array through pyusb's real code paths, on an emulated bus (usb.backend.IBackend).

The reader thread runs for real; the tests wait for what it queues (a condition variable), and the
adapter sees a virtual clock through ``poll``.
"""

import errno

import numpy as np
import pytest
import usb.core
import usb.util

from hardware.interfaces import ConnectionState, DeviceError
from hardware.serial_tactile import Calibration
from hardware.serial_tactile.driver import encode_frame
from hardware.usb.emulator import EmulatedBackend, EmulatedDevice, UsbTactileDevice
from hardware.usb.tactile import UsbTactileSensor, UsbTactileSettings
from hardware.usb.transport import UsbInPipe

T0 = 200.0
CAL = Calibration(24.0 + np.arange(60).reshape(4, 15) * 0.01, np.full((4, 15), 45.0), np.ones((4, 15)))


QUANTUM = float(CAL.gain_pa_per_count.max())  # half a count in the frame, half in the tare


def pressure(k: float) -> np.ndarray:
    return 500.0 * k * np.ones((4, 15)) + np.arange(60).reshape(4, 15)


def make(transfer=usb.util.ENDPOINT_TYPE_BULK, **settings):
    device = UsbTactileDevice(transfer=transfer, calibration=CAL)
    bus = EmulatedBackend(device)
    sensor = UsbTactileSensor(UsbTactileSettings(reconnect_interval_s=0.05, read_timeout_ms=20, **settings),
                              calibration=CAL, backend=bus)
    return device, bus, sensor


def until(sensor, now, condition, timeout_s=2.0):
    """Poll at ``now`` whenever the reader thread queues something, until ``condition()``."""
    sensor.poll(now)
    while not condition():
        assert sensor.pipe.wait(timeout_s), "the reader thread delivered nothing"
        sensor.poll(now)


@pytest.fixture
def rig():
    device, bus, sensor = make()
    sensor.open()
    yield device, bus, sensor
    sensor.close()


def test_pyusb_sees_the_emulated_array_as_a_device():
    device, bus, _ = make()
    (dev,) = usb.core.find(find_all=True, backend=bus, idVendor=0x1209)
    assert (dev.idProduct, dev.product, dev.serial_number) == (0x0001, "TSI 4x15 tactile array", "TSI-0001")
    intf = dev[0][(0, 0)]
    assert intf.bInterfaceClass == 0xFF
    ep = usb.util.find_descriptor(intf, bEndpointAddress=0x81)
    assert usb.util.endpoint_type(ep.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK
    usb.util.dispose_resources(dev)


@pytest.mark.parametrize("transfer", [usb.util.ENDPOINT_TYPE_BULK, usb.util.ENDPOINT_TYPE_INTR],
                         ids=["bulk", "interrupt"])
def test_frames_arrive_calibrated_and_on_the_host_clock(transfer):
    device, _, sensor = make(transfer)
    sensor.open()
    try:
        for k in range(5):
            t = T0 + 0.01 * k
            device.send(pressure(k), t)
            until(sensor, t + 0.003, lambda k=k: sensor.latest() is not None and sensor.latest().seq == k)
            assert np.allclose(sensor.latest().pressure_pa, pressure(k) - pressure(0), atol=QUANTUM)
            assert sensor.latest().t_s == pytest.approx(t + 0.003, abs=1e-5)
        assert sensor.connection == ConnectionState.CONNECTED
        st = sensor.stats
        assert st["frames"] == 5 and st["crc_errors"] == st["truncated"] == 0
        assert st["transfers"] == (5 if transfer == usb.util.ENDPOINT_TYPE_BULK else 15)  # 64-byte packets
    finally:
        sensor.close()


def test_hot_unplug_stops_the_readings_and_a_replug_resumes_them(rig):
    device, bus, sensor = rig
    device.send(pressure(1), T0)
    until(sensor, T0, lambda: sensor.latest() is not None)
    device.send(pressure(2), T0 + 0.01)
    until(sensor, T0 + 0.01, lambda: sensor.latest().seq == 1)
    before = sensor.latest()

    device.unplug()
    until(sensor, T0 + 0.02, lambda: sensor.connection == ConnectionState.LOST)
    assert "stopped answering" in sensor.stats["last_error"] and sensor.stats["disconnects"] == 1
    sensor.poll(T0 + 0.5)
    assert sensor.latest() is before

    device.replug()  # at a new address: the reader thread has to find it again
    until(sensor, T0 + 0.6, lambda: sensor.connection == ConnectionState.CONNECTING)
    device.send(pressure(3), T0 + 0.61)
    until(sensor, T0 + 0.612, lambda: sensor.connection == ConnectionState.CONNECTED)
    st = sensor.stats
    assert st["reconnects"] == 1 and st["last_error"] == ""
    assert sensor.latest().seq == before.seq + 1
    assert np.allclose(sensor.latest().pressure_pa, pressure(3) - pressure(1), atol=QUANTUM)  # the tare is kept
    assert sensor.latest().t_s == pytest.approx(T0 + 0.612, abs=1e-5)


def test_a_silent_device_goes_stale_then_recovers(rig):
    device, _, sensor = rig
    device.send(pressure(1), T0)
    until(sensor, T0, lambda: sensor.latest() is not None)
    sensor.poll(T0 + 0.3)  # 250 ms without a frame
    assert sensor.connection == ConnectionState.LOST and sensor.stats["stale_episodes"] == 1
    device.send(pressure(1), T0 + 0.31)
    until(sensor, T0 + 0.31, lambda: sensor.connection == ConnectionState.CONNECTED)


def test_stalls_overflows_and_damaged_frames_are_survived_and_counted(rig):
    device, _, sensor = rig
    device.stall.add(0x81)  # the next read stalls; the reader clears the halt and reads on
    device.queue_in(0x81, bytes(3000))  # longer than the 1024-byte read: libusb reports an overflow
    damaged = bytearray(device.electronics.frame_bytes(pressure(1), T0))
    damaged[50] ^= 0x01
    device.queue_in(0x81, bytes(damaged))
    device.queue_in(0x81, b"garbage" * 10)
    device.send(pressure(2), T0 + 0.01)
    until(sensor, T0 + 0.01, lambda: sensor.latest() is not None)
    st = sensor.stats
    assert (st["stalls"], st["overflows"], st["crc_errors"], st["frames"], st["frames_lost"]) == (1, 1, 1, 1, 0)
    assert st["garbage_bytes"] >= 70 and sensor.connection == ConnectionState.CONNECTED


def test_open_failures_are_sentences_a_user_can_act_on():
    bus = EmulatedBackend()
    with pytest.raises(DeviceError, match="no USB tactile sensor 1209:0001 is connected: is it plugged in"):
        UsbTactileSensor(UsbTactileSettings(), CAL, backend=bus).open()
    device = UsbTactileDevice(calibration=CAL)
    bus.plug(device)
    with pytest.raises(DeviceError, match="serial number 'TSI-0002'"):
        UsbTactileSensor(UsbTactileSettings(serial_number="TSI-0002"), CAL, backend=bus).open()
    with pytest.raises(DeviceError, match="no IN endpoint 0x82"):
        UsbTactileSensor(UsbTactileSettings(endpoint=0x82), CAL, backend=bus).open()
    device.access_denied = True
    with pytest.raises(DeviceError, match="permission denied .*udev rule"):
        UsbTactileSensor(UsbTactileSettings(), CAL, backend=bus).open()


def test_a_device_without_the_endpoint_is_refused():
    device = EmulatedDevice(0x1209, 0x0001, [], product="busy")
    bus = EmulatedBackend(device)
    pipe = UsbInPipe(0x1209, 0x0001, "tactile sensor", backend=bus)
    with pytest.raises(DeviceError, match="no IN endpoint 0x81"):
        pipe.open()
    with pytest.raises(ValueError, match="waits forever"):
        UsbInPipe(0x1209, 0x0001, "tactile sensor", read_timeout_ms=0)


def test_the_emulated_bus_behaves_like_libusb():
    device = UsbTactileDevice(calibration=CAL)
    bus = EmulatedBackend(device)
    dev = usb.core.find(backend=bus, idVendor=0x1209)
    usb.util.claim_interface(dev, 0)
    with pytest.raises(usb.core.USBTimeoutError):
        dev.read(0x81, 64, 5)
    device.queue_in(0x81, encode_frame(0, 0, CAL.counts_for(pressure(1))))
    assert len(dev.read(0x81, 1024, 5)) == 136
    device.unplug()
    with pytest.raises(usb.core.USBError) as err:
        dev.read(0x81, 64, 5)
    assert err.value.errno == errno.ENODEV
    usb.util.dispose_resources(dev)
    assert usb.core.find(backend=bus, idVendor=0x1209) is None
