"""The tactile array over USB: the serial wire format on a bulk or interrupt IN endpoint.

The device is a vendor-specific interface (class 0xFF) with one IN endpoint; each transfer carries a
piece of the byte stream (a whole 136-byte frame per bulk transfer, or 64-byte pieces on a full-speed
interrupt endpoint), so the same parser as on a serial line reassembles and checks the frames
(:mod:`hardware.serial_tactile.driver`), and calibration, tare and clock mapping are shared too
(:class:`~hardware.serial_tactile.stream.TactileStream`).

The device is found by VID:PID (and serial number, when several identical arrays are connected). Reads
happen on a thread (:class:`~hardware.usb.transport.UsbInPipe`); :meth:`UsbTactileSensor.poll` drains
what arrived without blocking. Connection states and the stale-data rule are the serial adapter's (both
are a :class:`~hardware.serial_tactile.stream.StreamedTactileSensor`): LOST on unplug or when no good frame
came for ``frame_timeout_s``; the thread looks for the device again and frames publish once good again.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hardware.interfaces import ConnectionState
from hardware.serial_tactile.calibration import Calibration
from hardware.serial_tactile.config import format_vid_pid, integer, text, vid_pid
from hardware.serial_tactile.stream import StreamedTactileSensor, TactileSettings
from hardware.usb.transport import Attached, Lost, UsbInPipe

# pid.codes' test id: firmware under development uses it; set your array's own id in the config.
DEFAULT_TACTILE_ID = "1209:0001"
MAX_ITEMS_PER_POLL = 64  # transfers handled per poll: a backlog is worked off over a few ticks


@dataclass(frozen=True)
class UsbTactileSettings(TactileSettings):
    vid_pid: str = DEFAULT_TACTILE_ID
    serial_number: str = ""  # pick one of several identical arrays; empty: the first found
    interface: int = 0
    endpoint: int = 0x81  # bulk or interrupt IN
    read_size: int = 1024  # bytes per read; a bulk transfer ends early at a short packet
    read_timeout_ms: int = 50  # how long the reader thread waits per read (also how fast it stops)

    def __post_init__(self):
        super().__post_init__()
        self._set("vid_pid", format_vid_pid(vid_pid("vid_pid", self.vid_pid)))
        self._set("serial_number", text("serial_number", self.serial_number, allow_empty=True))
        self._set("interface", integer("interface", self.interface, 0, 255))
        self._set("endpoint", integer("endpoint", self.endpoint, 0x81, 0x8F))
        self._set("read_size", integer("read_size", self.read_size, 64, 1 << 16))
        self._set("read_timeout_ms", integer("read_timeout_ms", self.read_timeout_ms, 1, 1000))

    @property
    def ids(self) -> tuple[int, int]:
        return vid_pid("vid_pid", self.vid_pid)


class UsbTactileSensor(StreamedTactileSensor):
    name = "usb-tsi"

    def __init__(self, settings: UsbTactileSettings | None = None, calibration: Calibration | None = None,
                 backend=None):
        super().__init__(settings if settings is not None else UsbTactileSettings(), calibration)
        s = self.settings
        vid, pid = s.ids
        self.pipe = UsbInPipe(vid, pid, "tactile sensor", interface=s.interface, endpoint=s.endpoint,
                              serial_number=s.serial_number, backend=backend, read_timeout_ms=s.read_timeout_ms,
                              reconnect_interval_s=s.reconnect_interval_s, read_size=s.read_size)
        self._unplugged = False

    def poll(self, now_s: float) -> None:
        if self._state == ConnectionState.DISCONNECTED:
            return
        self.pipe.start()  # from the loop's thread: the reader shares its priority and CPU
        stream = self._stream
        fresh = 0
        for item in self.pipe.take(MAX_ITEMS_PER_POLL):
            if isinstance(item, bytes):
                fresh += stream.feed(item, now_s)
            elif isinstance(item, Lost):
                self._unplugged = True
                self._lost(item.reason)
                fresh = 0
            elif isinstance(item, Attached) and self._unplugged:
                stream.link_reset()
                self._unplugged = False
                self._state = ConnectionState.CONNECTING
        self._fed(0 if self._unplugged else fresh, now_s)

    def _connect(self) -> ConnectionState:
        self._stream.start()
        self.pipe.open()
        self._unplugged = False
        return ConnectionState.CONNECTING

    def _disconnect(self) -> None:
        self.pipe.close()

    @property
    def stats(self) -> dict[str, Any]:
        return {"device": self.name, "usb": self.pipe.description or self.settings.vid_pid,
                "connection": self._state.name,
                "last_error": self.last_error or self.pipe.last_error or self._stream.tare_refused,
                "stale_episodes": self.stale_episodes, **self.pipe.counters, **self._stream.counters()}

    def describe(self) -> dict[str, Any]:
        return {"backend": "usb", "settings": self.settings.to_mapping(), "calibration": self.calibration.describe()}
