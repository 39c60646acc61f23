"""One IN endpoint of a USB device, read on a thread of its own, with hot-unplug and replug.

pyusb offers only blocking transfers (and libusb's timeout 0 means *forever*), so a read cannot sit in
the control loop's tick. :class:`UsbInPipe` runs the blocking reads on a thread (the ctypes call
releases the GIL while it waits) and only moves bytes: every transfer goes into a deque, in order with
``Lost`` / ``Attached`` markers, and the adapter's ``poll`` drains it without blocking. All protocol work
happens in ``poll``, on the loop's clock.

The thread starts at the adapter's first ``poll``, not at ``open``: a thread inherits its creator's
scheduling policy and CPU, and ``poll`` runs on the control loop's thread after it has claimed its
real-time priority and CPU (the controller opens the rig before that). A reader left at normal priority
on another CPU could be preempted while holding the GIL and stall the loop for milliseconds.

Unplug: a read failing with ENODEV (or EIO, which some platforms report instead) puts a ``Lost`` marker
in the queue, drops the device, and the thread looks for it again every ``reconnect_interval_s``; a
STALL is cleared and counted; an overflow (a transfer longer than the buffer) is counted and dropped.
"""

from __future__ import annotations

import errno
import threading
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

import usb.core
import usb.util

from hardware.interfaces import DeviceError


@dataclass(frozen=True, slots=True)
class Lost:
    reason: str


@dataclass(frozen=True, slots=True)
class Attached:
    description: str


def describe_usb_error(ids: str, what: str, err: BaseException) -> str:
    code = getattr(err, "errno", None)
    if code in (errno.EACCES, errno.EPERM):
        return (f"permission denied on the USB {what} {ids}: install a udev rule giving your user access "
                f"(see docs/hardware.md), then replug it")
    if code == errno.EBUSY:
        return f"the USB {what} {ids} is claimed by another program or driver; close it or unbind the driver"
    return f"USB {what} {ids}: {err}"


class UsbInPipe:
    def __init__(self, vendor_id: int, product_id: int, what: str, *, interface: int = 0, endpoint: int = 0x81,
                 serial_number: str = "", backend=None, read_timeout_ms: int = 50,
                 reconnect_interval_s: float = 0.5, read_size: int | None = None):
        if read_timeout_ms <= 0:
            raise ValueError("read_timeout_ms must be > 0 (libusb waits forever on 0)")
        self.ids = f"{vendor_id:04x}:{product_id:04x}"
        self.vendor_id, self.product_id = vendor_id, product_id
        self.what = what
        self.interface = interface
        self.endpoint = endpoint
        self.serial_number = serial_number
        self.backend = backend
        self.read_timeout_ms = read_timeout_ms
        self.reconnect_interval_s = reconnect_interval_s
        self._read_size = read_size
        self.queue: deque[bytes | Lost | Attached] = deque()
        self._arrived = threading.Condition()
        self._dev = None
        self._size = 64
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.counters = dict.fromkeys(("transfers", "bytes", "stalls", "overflows", "errors", "disconnects",
                                       "reconnects"), 0)
        self.last_error = ""
        self.description = ""

    def wait(self, timeout_s: float) -> bool:
        """Block until something is queued (for event-driven callers; the loop never waits)."""
        with self._arrived:
            return self._arrived.wait_for(lambda: bool(self.queue), timeout_s)

    def take(self, most: int) -> Iterator[bytes | Lost | Attached]:
        """Up to ``most`` of what the reader queued, oldest first, without waiting (an adapter's poll: a
        backlog is worked off over a few polls)."""
        queue = self.queue
        for _ in range(most):
            try:
                yield queue.popleft()
            except IndexError:
                return

    def _put(self, item: bytes | Lost | Attached) -> None:
        with self._arrived:
            self.queue.append(item)
            self._arrived.notify_all()

    def open(self) -> None:
        """Find and claim the device now, raising a DeviceError a user can act on; :meth:`start` reads."""
        if self._dev is None and self._thread is None:
            self._attach()

    def start(self) -> None:
        """Start the reader thread (idempotent); call it from the thread whose priority it should share."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"usb-{self.what}-{self.ids}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join()
        self._detach()
        self.queue.clear()

    # ---- the thread ----------------------------------------------------------------------------------

    def _run(self) -> None:
        stop = self._stop
        c = self.counters
        while not stop.is_set():
            dev = self._dev
            if dev is None:
                if stop.wait(self.reconnect_interval_s):
                    return
                try:
                    self._attach()
                except DeviceError as err:
                    self.last_error = str(err)
                    continue
                c["reconnects"] += 1
                continue
            try:
                data = dev.read(self.endpoint, self._size, self.read_timeout_ms)
            except usb.core.USBTimeoutError:
                continue
            except usb.core.USBError as err:
                self._on_error(dev, err)
                continue
            c["transfers"] += 1
            c["bytes"] += len(data)
            self._put(data.tobytes())

    def _on_error(self, dev, err: usb.core.USBError) -> None:
        c = self.counters
        if err.errno == errno.EPIPE:
            c["stalls"] += 1
            try:
                dev.clear_halt(self.endpoint)
                return
            except usb.core.USBError as again:
                err = again
        if err.errno == errno.EOVERFLOW:
            c["overflows"] += 1
            return
        if err.errno not in (errno.ENODEV, errno.EIO, errno.ENOENT, errno.ESHUTDOWN):
            c["errors"] += 1
        c["disconnects"] += 1
        self.last_error = f"the USB {self.what} {self.ids} stopped answering ({err}); unplugged?"
        self._detach()
        self._put(Lost(self.last_error))

    # ---- finding and claiming ------------------------------------------------------------------------

    def _find(self):
        kwargs = {"idVendor": self.vendor_id, "idProduct": self.product_id}
        if self.backend is not None:
            kwargs["backend"] = self.backend
        try:
            found = list(usb.core.find(find_all=True, **kwargs))
        except usb.core.NoBackendError:
            raise DeviceError("no USB library found: install libusb-1.0 (e.g. apt install libusb-1.0-0)") from None
        if self.serial_number:
            found = [d for d in found if _serial(d) == self.serial_number]
        if not found:
            which = f" with serial number {self.serial_number!r}" if self.serial_number else ""
            raise DeviceError(f"no USB {self.what} {self.ids}{which} is connected: is it plugged in? "
                              f"`palpation-console devices` lists what this computer sees")
        return found[0]

    def _attach(self) -> None:
        dev = self._find()
        try:
            try:
                if dev.is_kernel_driver_active(self.interface):
                    dev.detach_kernel_driver(self.interface)
            except NotImplementedError:
                pass  # platforms without kernel drivers to detach
            try:
                dev.get_active_configuration()
            except usb.core.USBError:
                dev.set_configuration()
            usb.util.claim_interface(dev, self.interface)
            ep = self._endpoint(dev)
        except usb.core.USBError as err:
            usb.util.dispose_resources(dev)
            raise DeviceError(describe_usb_error(self.ids, self.what, err)) from None
        if ep is None:
            usb.util.dispose_resources(dev)
            raise DeviceError(f"the USB {self.what} {self.ids} has no IN endpoint 0x{self.endpoint:02x} on "
                              f"interface {self.interface}; check the endpoint in the configuration")
        self._size = self._read_size or ep.wMaxPacketSize
        product = _string(dev, "product")
        self.description = f"{self.ids} {product}".strip() + f" (bus {dev.bus}, address {dev.address})"
        self._dev = dev
        self.last_error = ""
        self._put(Attached(self.description))

    def _endpoint(self, dev):
        cfg = dev.get_active_configuration()
        for intf in cfg:
            if intf.bInterfaceNumber != self.interface:
                continue
            ep = usb.util.find_descriptor(intf, bEndpointAddress=self.endpoint)
            if ep is not None and usb.util.endpoint_direction(ep.bEndpointAddress) == usb.util.ENDPOINT_IN:
                return ep
        return None

    def _detach(self) -> None:
        dev, self._dev = self._dev, None
        if dev is not None:
            usb.util.dispose_resources(dev)  # releases what it can; an unplugged device's errors are ignored


def _string(dev, name: str) -> str:
    try:
        return getattr(dev, name) or ""
    except (usb.core.USBError, ValueError, NotImplementedError):
        return ""


def _serial(dev) -> str:
    return _string(dev, "serial_number")
