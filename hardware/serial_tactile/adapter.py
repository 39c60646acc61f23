"""The serial tactile array as a :class:`~hardware.interfaces.TactileSensor` (pyserial).

The port is read without blocking on every :meth:`poll` (pyserial with ``timeout=0``: one ``select``
and one ``read`` system call, tens of µs), at most ``max_read_bytes`` per poll so a backlog is worked
off over a few ticks instead of stalling one.

Connection states: CONNECTING from opening the port until the first good frame; CONNECTED while good
frames arrive; LOST when the port fails (unplugged: the read errors) or when no good frame has arrived
for ``frame_timeout_s`` (a device that hangs, sends garbage or sends too slowly). While LOST the last
frame stays where it was, ageing, so the loop's watchdog latches its hold; a failed port is reopened
every ``reconnect_interval_s`` (a udev ``/dev/serial/by-id/...`` name survives a replug), and frames
resume publishing as soon as they are good again. :attr:`stats` has every counter for the console's
device-health display.
"""

from __future__ import annotations

import errno
from dataclasses import dataclass
from typing import Any

import serial

from hardware.interfaces import ConnectionState, DeviceError
from hardware.serial_tactile.calibration import Calibration
from hardware.serial_tactile.config import integer, text
from hardware.serial_tactile.driver import frame_size
from hardware.serial_tactile.stream import StreamedTactileSensor, TactileSettings
from hardware.settings import ConfigError

BITS_PER_BYTE = 10  # 8N1 framing on the wire


@dataclass(frozen=True)
class SerialTactileSettings(TactileSettings):
    port: str = ""  # e.g. /dev/serial/by-id/usb-...-if00 (stable across replugs), /dev/ttyACM0, COM3
    baud: int = 460800
    max_read_bytes: int = 4096  # per poll

    def __post_init__(self):
        super().__post_init__()
        self._set("port", text("port", self.port))
        self._set("baud", integer("baud", self.baud, 1200, 12_000_000))
        self._set("max_read_bytes", integer("max_read_bytes", self.max_read_bytes, 256, 1 << 20))
        needed = frame_size(4, 15) * BITS_PER_BYTE * self.frame_rate_hz
        if self.baud < needed:
            raise ConfigError("baud", f"{self.baud} baud carries at most {self.baud / needed * self.frame_rate_hz:.0f} "
                                      f"frames/s of {frame_size(4, 15)} bytes; the sensor sends "
                                      f"{self.frame_rate_hz:g}/s (needs at least {needed:.0f} baud)")


def describe_open_error(port: str, err: BaseException) -> str:
    """A sentence a user can act on for a port that would not open."""
    code = getattr(err, "errno", None)
    if code == errno.ENOENT or isinstance(err, FileNotFoundError):
        return (f"there is no serial port {port}: is the sensor plugged in and powered? "
                f"`palpation-console devices` lists the ports this computer has")
    if code in (errno.EACCES, errno.EPERM):
        return (f"permission denied on {port}: add your user to the group that owns it (usually 'dialout': "
                f"sudo usermod -aG dialout $USER, then log in again)")
    if code in (errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK):
        return f"{port} is in use by another program (a serial terminal, another console?); close it first"
    return f"cannot open {port}: {err}"


class SerialTactileSensor(StreamedTactileSensor):
    name = "serial-tsi"

    def __init__(self, settings: SerialTactileSettings, calibration: Calibration | None = None):
        super().__init__(settings, calibration)
        self._port: serial.Serial | None = None
        self._retry_at = 0.0
        self.disconnects = 0
        self.reconnects = 0

    # ---- Device --------------------------------------------------------------------------------------

    def poll(self, now_s: float) -> None:
        if self._state == ConnectionState.DISCONNECTED:
            return
        if self._port is None:
            if now_s < self._retry_at or not self._reopen(now_s):
                return
        try:
            data = self._port.read(self.settings.max_read_bytes)
        except (serial.SerialException, OSError) as err:
            self._lose(now_s, f"the serial port failed ({err}); unplugged?")
            return
        self._fed(self._stream.feed(data, now_s) if data else 0, now_s)

    def fileno(self) -> int | None:
        """The open port's descriptor (to wait for data with select), None while it is not open."""
        return self._port.fileno() if self._port is not None else None

    # ---- health --------------------------------------------------------------------------------------

    @property
    def stats(self) -> dict[str, Any]:
        return {"device": self.name, "port": self.settings.port, "connection": self._state.name,
                "last_error": self.last_error or self._stream.tare_refused, "disconnects": self.disconnects,
                "reconnects": self.reconnects,
                "stale_episodes": self.stale_episodes, **self._stream.counters()}

    def describe(self) -> dict[str, Any]:
        return {"backend": "serial", "port": self.settings.port, "baud": self.settings.baud,
                "settings": self.settings.to_mapping(), "calibration": self.calibration.describe()}

    # ---- internals -----------------------------------------------------------------------------------

    def _connect(self) -> ConnectionState:
        try:
            self._port = self._open_port()
        except (serial.SerialException, OSError) as err:
            raise DeviceError(f"tactile sensor: {describe_open_error(self.settings.port, err)}") from None
        self._stream.start()
        return ConnectionState.CONNECTING

    def _open_port(self) -> serial.Serial:
        # timeout=0: read() returns at once with what is there; exclusive: a second console cannot steal frames
        return serial.Serial(self.settings.port, self.settings.baud, timeout=0, write_timeout=0, exclusive=True)

    def _disconnect(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass  # an unplugged port may fail to close; it is gone either way

    def _lose(self, now_s: float, why: str) -> None:
        self._disconnect()
        self._lost(why)
        self.disconnects += 1
        self._retry_at = now_s + self.settings.reconnect_interval_s

    def _reopen(self, now_s: float) -> bool:
        try:
            self._port = self._open_port()
        except (serial.SerialException, OSError) as err:
            self.last_error = describe_open_error(self.settings.port, err)
            self._retry_at = now_s + self.settings.reconnect_interval_s
            return False
        self._stream.link_reset()
        self.reconnects += 1
        self._state = ConnectionState.CONNECTING
        return True

    def _stale_reason(self, silent_s: float) -> str:
        p = self._stream.parser
        why = super()._stale_reason(silent_s)
        if p.header_errors:
            why += f" (last unexpected header: {p.last_header_problem})"
        return why
