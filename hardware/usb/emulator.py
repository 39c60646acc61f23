"""Emulated USB devices behind pyusb's own backend interface (:class:`usb.backend.IBackend`).

``usb.core.find(backend=EmulatedBackend(...))`` then works exactly as with libusb: pyusb builds its
``Device``/``Configuration``/``Interface``/``Endpoint`` objects from the descriptors here, claims
interfaces, routes ``read``/``write`` by endpoint type, fetches string descriptors with control
transfers, so the adapters' real pyusb code paths run in the tests.

Behaviour copied from libusb-1.0, because adapters must cope with it:

* a read waits up to its timeout in ms and raises :class:`usb.core.USBTimeoutError` (errno ETIMEDOUT);
  a timeout of 0 waits forever (so an adapter that passes 0 hangs its test, as it would hang the robot);
* one IN transfer returns one packet the device queued; a packet longer than the buffer raises
  LIBUSB_ERROR_OVERFLOW;
* :meth:`EmulatedDevice.unplug` wakes every pending read and makes every call on the device's handles
  raise LIBUSB_ERROR_NO_DEVICE (errno ENODEV), and it vanishes from enumeration; :meth:`replug` brings it
  back at a new address, as a new device the host must find and open again;
* an interface with a kernel driver (HID) reports it active until detached.
"""

from __future__ import annotations

import errno
import threading
from collections import deque
from dataclasses import dataclass, field

import usb.backend
import usb.core
import usb.util

from hardware.serial_tactile.emulator import TactileDeviceEmulator
from hardware.usb.spacemouse import pack_axes, pack_buttons

LIBUSB_ERROR_IO = -1
LIBUSB_ERROR_ACCESS = -3
LIBUSB_ERROR_NO_DEVICE = -4
LIBUSB_ERROR_NOT_FOUND = -5
LIBUSB_ERROR_BUSY = -6
LIBUSB_ERROR_TIMEOUT = -7
LIBUSB_ERROR_OVERFLOW = -8
LIBUSB_ERROR_PIPE = -9

_ERRORS = {
    LIBUSB_ERROR_IO: ("Input/output error", errno.EIO),
    LIBUSB_ERROR_ACCESS: ("Access denied (insufficient permissions)", errno.EACCES),
    LIBUSB_ERROR_NO_DEVICE: ("No such device (it may have been disconnected)", errno.ENODEV),
    LIBUSB_ERROR_NOT_FOUND: ("Entity not found", errno.ENOENT),
    LIBUSB_ERROR_BUSY: ("Resource busy", errno.EBUSY),
    LIBUSB_ERROR_OVERFLOW: ("Overflow", errno.EOVERFLOW),
    LIBUSB_ERROR_PIPE: ("Pipe error", errno.EPIPE),
}


def _fail(code: int):
    if code == LIBUSB_ERROR_TIMEOUT:
        raise usb.core.USBTimeoutError("Operation timed out", code, errno.ETIMEDOUT)
    message, err = _ERRORS[code]
    raise usb.core.USBError(message, code, err)


@dataclass
class EndpointSpec:
    address: int  # bEndpointAddress, 0x80 bit = IN
    transfer: int = usb.util.ENDPOINT_TYPE_INTR  # or ENDPOINT_TYPE_BULK
    max_packet: int = 64
    interval: int = 1


@dataclass
class InterfaceSpec:
    number: int = 0
    cls: int = 0xFF  # 0x03 HID, 0xFF vendor-specific
    subclass: int = 0
    protocol: int = 0
    endpoints: list[EndpointSpec] = field(default_factory=list)
    kernel_driver: bool = False  # a kernel driver (usbhid) is bound until detached


class _Desc:
    """A descriptor as pyusb expects one: plain attributes."""

    def __init__(self, **fields):
        self.__dict__.update(fields)


class EmulatedDevice:
    """One USB device: descriptors, strings, IN endpoint queues the test (or an emulator) fills."""

    def __init__(self, vendor_id: int, product_id: int, interfaces: list[InterfaceSpec], manufacturer: str = "",
                 product: str = "", serial_number: str = "", bcd_device: int = 0x0100):
        self.vendor_id, self.product_id = vendor_id, product_id
        self.interfaces = interfaces
        self.strings = [s for s in (manufacturer, product, serial_number)]
        self.bcd_device = bcd_device
        self.backend: EmulatedBackend | None = None
        self.address = 0
        self.out_packets: deque[tuple[int, bytes]] = deque()  # (endpoint, data) the host wrote
        self._queues: dict[int, deque[bytes]] = {}
        self.driver_bound = {i.number: i.kernel_driver for i in interfaces}  # interface -> kernel driver owns it
        self.claimed: set[int] = set()
        self.configuration = 1
        self.stall: set[int] = set()  # IN endpoints that answer with a STALL (pipe error)
        self.access_denied = False  # opening fails as without a udev rule

    @property
    def plugged(self) -> bool:
        return self.backend is not None and self in self.backend.devices

    def queue_in(self, endpoint: int, data: bytes) -> None:
        """The device has ``data`` ready as the next IN transfer on ``endpoint`` (dropped while unplugged)."""
        backend = self.backend
        if backend is None or not self.plugged:
            return
        with backend.cond:
            self._queues.setdefault(endpoint, deque()).append(bytes(data))
            backend.cond.notify_all()

    def unplug(self) -> None:
        if self.backend is not None:
            self.backend.unplug(self)

    def replug(self) -> None:
        if self.backend is not None:
            self.backend.plug(self)


class _Handle:
    def __init__(self, device: EmulatedDevice, address: int):
        self.device = device
        self.address = address  # the plug-in this handle belongs to


class EmulatedBackend(usb.backend.IBackend):
    """The bus: devices plug in and out; pyusb calls land here instead of in libusb."""

    def __init__(self, *devices: EmulatedDevice):
        super().__init__()
        self.cond = threading.Condition()
        self.devices: list[EmulatedDevice] = []
        self._next_address = 1
        for d in devices:
            self.plug(d)

    # ---- the bus (test side) -------------------------------------------------------------------------

    def plug(self, device: EmulatedDevice) -> None:
        with self.cond:
            if device in self.devices:
                return
            device.backend = self
            device.address = self._next_address
            self._next_address += 1
            device._queues.clear()
            device.claimed.clear()
            device.configuration = 1  # the OS configures a device when it enumerates it
            device.driver_bound = {i.number: i.kernel_driver for i in device.interfaces}
            self.devices.append(device)
            self.cond.notify_all()

    def unplug(self, device: EmulatedDevice) -> None:
        with self.cond:
            if device in self.devices:
                self.devices.remove(device)
                device._queues.clear()
                self.cond.notify_all()

    # ---- IBackend: descriptors -----------------------------------------------------------------------

    def enumerate_devices(self):
        with self.cond:
            return [(d, d.address) for d in self.devices]

    def get_parent(self, dev):
        return None

    def get_device_descriptor(self, dev):
        d, address = dev
        return _Desc(bLength=18, bDescriptorType=usb.util.DESC_TYPE_DEVICE, bcdUSB=0x0200, bDeviceClass=0,
                     bDeviceSubClass=0, bDeviceProtocol=0, bMaxPacketSize0=64, idVendor=d.vendor_id,
                     idProduct=d.product_id, bcdDevice=d.bcd_device, iManufacturer=1 if d.strings[0] else 0,
                     iProduct=2 if d.strings[1] else 0, iSerialNumber=3 if d.strings[2] else 0,
                     bNumConfigurations=1, address=address, bus=1, port_number=address, port_numbers=(address,),
                     speed=usb.util.SPEED_FULL)

    def get_configuration_descriptor(self, dev, config):
        d, _ = dev
        if config != 0:
            raise IndexError("configuration index out of range")
        total = 9 + sum(9 + 7 * len(i.endpoints) + (9 if i.cls == 3 else 0) for i in d.interfaces)
        return _Desc(bLength=9, bDescriptorType=usb.util.DESC_TYPE_CONFIG, wTotalLength=total,
                     bNumInterfaces=len(d.interfaces), bConfigurationValue=1, iConfiguration=0,
                     bmAttributes=0x80, bMaxPower=50, extra_descriptors=[])

    def get_interface_descriptor(self, dev, intf, alt, config):
        d, _ = dev
        if config != 0 or alt != 0 or not 0 <= intf < len(d.interfaces):
            raise IndexError("interface index out of range")
        i = d.interfaces[intf]
        return _Desc(bLength=9, bDescriptorType=usb.util.DESC_TYPE_INTERFACE, bInterfaceNumber=i.number,
                     bAlternateSetting=0, bNumEndpoints=len(i.endpoints), bInterfaceClass=i.cls,
                     bInterfaceSubClass=i.subclass, bInterfaceProtocol=i.protocol, iInterface=0,
                     extra_descriptors=[])

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        d, _ = dev
        e = d.interfaces[intf].endpoints[ep]
        return _Desc(bLength=7, bDescriptorType=usb.util.DESC_TYPE_ENDPOINT, bEndpointAddress=e.address,
                     bmAttributes=e.transfer, wMaxPacketSize=e.max_packet, bInterval=e.interval, bRefresh=0,
                     bSynchAddress=0, extra_descriptors=[])

    # ---- IBackend: handles ---------------------------------------------------------------------------

    def _live(self, handle: _Handle) -> EmulatedDevice:
        d = handle.device
        if d not in self.devices or d.address != handle.address:
            _fail(LIBUSB_ERROR_NO_DEVICE)
        return d

    def open_device(self, dev):
        d, address = dev
        with self.cond:
            handle = _Handle(d, address)
            self._live(handle)
            if d.access_denied:
                _fail(LIBUSB_ERROR_ACCESS)
            return handle

    def close_device(self, dev_handle):
        pass  # closing a handle to an unplugged device succeeds in libusb too

    def set_configuration(self, dev_handle, config_value):
        with self.cond:
            self._live(dev_handle).configuration = config_value

    def get_configuration(self, dev_handle):
        with self.cond:
            return self._live(dev_handle).configuration

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        with self.cond:
            self._live(dev_handle)

    def claim_interface(self, dev_handle, intf):
        with self.cond:
            d = self._live(dev_handle)
            if d.driver_bound.get(intf):
                _fail(LIBUSB_ERROR_BUSY)  # the kernel driver owns it
            d.claimed.add(intf)

    def release_interface(self, dev_handle, intf):
        with self.cond:
            d = self._live(dev_handle)
            d.claimed.discard(intf)

    def is_kernel_driver_active(self, dev_handle, intf):
        with self.cond:
            return bool(self._live(dev_handle).driver_bound.get(intf))

    def detach_kernel_driver(self, dev_handle, intf):
        with self.cond:
            d = self._live(dev_handle)
            if not d.driver_bound.get(intf):
                _fail(LIBUSB_ERROR_NOT_FOUND)
            d.driver_bound[intf] = False

    def attach_kernel_driver(self, dev_handle, intf):
        with self.cond:
            d = self._live(dev_handle)
            d.driver_bound[intf] = True

    def clear_halt(self, dev_handle, ep):
        with self.cond:
            self._live(dev_handle).stall.discard(ep)

    def reset_device(self, dev_handle):
        with self.cond:
            self._live(dev_handle)

    # ---- IBackend: transfers -------------------------------------------------------------------------

    def _read(self, dev_handle, ep, intf, buff, timeout):
        with self.cond:
            d = self._live(dev_handle)
            if intf not in d.claimed:
                _fail(LIBUSB_ERROR_IO)
            wait_s = None if timeout == 0 else timeout / 1000.0
            queue = d._queues.setdefault(ep, deque())

            def ready() -> bool:
                return bool(queue) or ep in d.stall or d not in self.devices or d.address != dev_handle.address

            if not self.cond.wait_for(ready, wait_s):
                _fail(LIBUSB_ERROR_TIMEOUT)
            self._live(dev_handle)
            if ep in d.stall:
                _fail(LIBUSB_ERROR_PIPE)
            data = queue.popleft()
        size = len(buff) * buff.itemsize
        if len(data) > size:
            _fail(LIBUSB_ERROR_OVERFLOW)
        memoryview(buff).cast("B")[: len(data)] = data
        return len(data)

    def _write(self, dev_handle, ep, intf, data, timeout):
        with self.cond:
            d = self._live(dev_handle)
            if intf not in d.claimed:
                _fail(LIBUSB_ERROR_IO)
            d.out_packets.append((ep, bytes(data)))
        return len(data) * data.itemsize

    bulk_read = intr_read = _read
    bulk_write = intr_write = _write

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        with self.cond:
            d = self._live(dev_handle)
        if usb.util.ctrl_direction(bmRequestType) == usb.util.CTRL_OUT:
            return len(data) * data.itemsize  # SET_IDLE, SET_REPORT, LED reports: accepted
        kind = bmRequestType & (3 << 5)
        if kind == usb.util.CTRL_TYPE_STANDARD and bRequest == 0x06 and wValue >> 8 == usb.util.DESC_TYPE_STRING:
            index = wValue & 0xFF
            if index == 0:
                payload = bytes([4, usb.util.DESC_TYPE_STRING, 0x09, 0x04])  # US English
            elif 1 <= index <= 3 and d.strings[index - 1]:
                text = d.strings[index - 1].encode("utf-16-le")
                payload = bytes([2 + len(text), usb.util.DESC_TYPE_STRING]) + text
            else:
                _fail(LIBUSB_ERROR_PIPE)
            n = min(len(payload), len(data) * data.itemsize)
            memoryview(data).cast("B")[:n] = payload[:n]
            return n
        _fail(LIBUSB_ERROR_PIPE)  # a request this device does not support: STALL


# ---- devices ---------------------------------------------------------------------------------------


class UsbTactileDevice(EmulatedDevice):
    """A TSI on USB: vendor-specific interface, one bulk (or interrupt) IN endpoint, the serial wire format.

    :attr:`electronics` samples pressures into frames on the device's own clock and calibration; a
    bulk endpoint carries a frame per transfer, an interrupt endpoint splits it into packets.
    """

    def __init__(self, vendor_id: int = 0x1209, product_id: int = 0x0001, *,
                 transfer: int = usb.util.ENDPOINT_TYPE_BULK, endpoint: int = 0x81, serial_number: str = "TSI-0001",
                 calibration=None, device_epoch_s: float = 7000.0):
        self.transfer = transfer
        self.ep = endpoint
        max_packet = 64
        super().__init__(vendor_id, product_id,
                         [InterfaceSpec(0, 0xFF, endpoints=[EndpointSpec(endpoint, transfer, max_packet)])],
                         manufacturer="Palpation Lab", product="TSI 4x15 tactile array", serial_number=serial_number)
        self.max_packet = max_packet
        self.electronics = TactileDeviceEmulator(self._transmit, calibration, device_epoch_s)

    def _transmit(self, data: bytes) -> int:
        if not self.plugged:
            return 0
        if self.transfer == usb.util.ENDPOINT_TYPE_BULK:
            self.queue_in(self.ep, data)
        else:
            for i in range(0, len(data), self.max_packet):
                self.queue_in(self.ep, data[i:i + self.max_packet])
        return len(data)

    def send(self, pressure_pa, t_s: float) -> bytes:
        return self.electronics.send(pressure_pa, t_s)


class SpaceMouseDevice(EmulatedDevice):
    """A 3Dconnexion SpaceMouse: HID interface (usbhid bound until detached), interrupt IN reports."""

    def __init__(self, vendor_id: int = 0x256F, product_id: int = 0xC635, *, combined: bool = False,
                 serial_number: str = ""):
        super().__init__(vendor_id, product_id,
                         [InterfaceSpec(0, 0x03, endpoints=[EndpointSpec(0x81, usb.util.ENDPOINT_TYPE_INTR, 16)],
                                        kernel_driver=True)],
                         manufacturer="3Dconnexion", product="SpaceMouse Compact", serial_number=serial_number)
        self.combined = combined  # report 1 carries translation and rotation (the wireless models)
        self.reports_sent = 0

    def move(self, translation: tuple[int, int, int], rotation: tuple[int, int, int] = (0, 0, 0)) -> None:
        if self.combined:
            self.report(pack_axes(1, translation, rotation))
        else:
            self.report(pack_axes(1, translation))
            self.report(pack_axes(2, rotation))

    def buttons(self, mask: int) -> None:
        self.report(pack_buttons(mask))

    def report(self, data: bytes) -> None:
        """Any raw report (unknown ids, truncated reports)."""
        self.queue_in(0x81, data)
        self.reports_sent += 1
