"""A 3Dconnexion SpaceMouse (6-DOF HID) as the master device: the cap drives X_d, a button toggles S_z.

Reports (HID, interrupt IN endpoint; values little-endian int16, about +-350 at full deflection):

* report 1: translation x, y, z (6 bytes); the wireless models append rotation (12 bytes in all);
* report 2: rotation rx, ry, rz (6 bytes) on the models that send it separately;
* report 3: buttons, one bit each (bit 0 = left button);
* anything else (battery level, LED state) is ignored and counted.

A SpaceMouse is a rate device: deflecting the cap asks for a velocity. The adapter integrates it into a
position in the master's frame, which the loop scales and offsets into X_d (``control.master``):
``velocity = axis_signs * speed_m_s * shaped(deflection)``, with a deadband so a resting hand does not
drift and a linear ramp to ``speed_m_s`` at ``full_scale_counts``. Rotation is read but not used: the
TSI's orientation is fixed in this application.

The S_z button toggles between position control and force control along z. The loop hands z back to
position control on its own (a region done, an abort, a fault); :meth:`SpaceMouseMaster.feedback` follows
it, so the next press always asks for force control when the loop is in position control.

Safety: a cap that stops reporting while deflected (a stuck device, lost reports) is taken as released
after ``report_timeout_s``; unplugging makes the readings stop (LOST), so the loop's master watchdog
lifts the probe and holds. After a replug the integrated position continues where it was: nothing jumps.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Any

import usb.core

from hardware.connection import Connection
from hardware.interfaces import (
    ConnectionState,
    DeviceError,
    MasterConstraints,
    MasterDevice,
    MasterFeedback,
    MasterState,
    Phase,
    Vec3,
)
from hardware.serial_tactile.config import format_vid_pid, integer, text, vid_pid
from hardware.settings import ConfigError, Settings, bounded
from hardware.usb.transport import Attached, Lost, UsbInPipe

KNOWN_SPACEMICE: dict[tuple[int, int], str] = {
    (0x046D, 0xC626): "3Dconnexion SpaceNavigator",
    (0x046D, 0xC627): "3Dconnexion SpaceExplorer",
    (0x046D, 0xC628): "3Dconnexion SpaceNavigator for Notebooks",
    (0x046D, 0xC62B): "3Dconnexion SpaceMouse Pro",
    (0x256F, 0xC62E): "3Dconnexion SpaceMouse Wireless (cabled)",
    (0x256F, 0xC631): "3Dconnexion SpaceMouse Pro Wireless (cabled)",
    (0x256F, 0xC632): "3Dconnexion SpaceMouse Pro Wireless (receiver)",
    (0x256F, 0xC635): "3Dconnexion SpaceMouse Compact",
    (0x256F, 0xC652): "3Dconnexion Universal Receiver",
}
_AXES = struct.Struct("<3h")
_FORCE_CONTROL = (Phase.SEEK_CONTACT, Phase.SETTLING)
MAX_REPORTS_PER_POLL = 256


class ReportDecoder:
    """The device's latest axes and buttons, from its raw HID reports (pure, no I/O)."""

    def __init__(self):
        self.translation = (0, 0, 0)
        self.rotation = (0, 0, 0)
        self.buttons = 0
        self.unknown = 0
        self.short = 0

    def feed(self, report: bytes) -> bool:
        """Apply one report; False if it was not an axes or button report (or too short to be one)."""
        if not report:
            self.short += 1
            return False
        rid = report[0]
        if rid in (1, 2):
            if len(report) < 1 + _AXES.size:
                self.short += 1
                return False
            axes = _AXES.unpack_from(report, 1)
            if rid == 1:
                self.translation = axes
                if len(report) >= 1 + 2 * _AXES.size:
                    self.rotation = _AXES.unpack_from(report, 1 + _AXES.size)
            else:
                self.rotation = axes
            return True
        if rid == 3:
            if len(report) < 2:
                self.short += 1
                return False
            self.buttons = int.from_bytes(report[1:5], "little")
            return True
        self.unknown += 1
        return False


def pack_axes(report_id: int, axes: tuple[int, int, int], more: tuple[int, int, int] | None = None) -> bytes:
    """A report 1 or 2 as the device sends it (emulators)."""
    data = bytes([report_id]) + _AXES.pack(*axes)
    return data + _AXES.pack(*more) if more is not None else data


def pack_buttons(mask: int, width: int = 2) -> bytes:
    return bytes([3]) + mask.to_bytes(width, "little")


@dataclass(frozen=True)
class SpaceMouseSettings(Settings):
    vid_pid: str = ""  # empty: the first known 3Dconnexion device connected
    serial_number: str = ""
    interface: int = 0
    endpoint: int = 0x81
    speed_m_s: float = 0.02  # TSI speed with the cap fully deflected
    full_scale_counts: float = 350.0
    deadband_counts: float = 20.0
    # HID axes: x to the right, y towards the user, z down; the tissue frame has y away, z up
    axis_signs: tuple[float, float, float] = (1.0, -1.0, -1.0)
    sz_button: int = 0  # bit of the button report that toggles S_z
    report_timeout_s: float = 0.25  # a deflected cap silent for this long is taken as released
    rate_hz: float = 1000.0  # the integrated position is sampled at every poll
    reconnect_interval_s: float = 0.5
    read_timeout_ms: int = 50

    def __post_init__(self):
        if self.vid_pid:
            self._set("vid_pid", format_vid_pid(vid_pid("vid_pid", self.vid_pid)))
        self._set("serial_number", text("serial_number", self.serial_number, allow_empty=True))
        self._set("interface", integer("interface", self.interface, 0, 255))
        self._set("endpoint", integer("endpoint", self.endpoint, 0x81, 0x8F))
        self._set("speed_m_s", bounded("speed_m_s", self.speed_m_s, 1e-4, 0.1, "the loop's velocity limit"))
        self._set("full_scale_counts", bounded("full_scale_counts", self.full_scale_counts, 10.0, 32767.0))
        self._set("deadband_counts", bounded("deadband_counts", self.deadband_counts, 0.0, self.full_scale_counts / 2))
        signs = self.axis_signs
        if isinstance(signs, (str, bytes)) or len(signs) != 3 or any(s not in (1, -1) for s in signs):
            raise ConfigError("axis_signs", f"must be three of 1 or -1, got {signs!r}")
        self._set("axis_signs", tuple(float(s) for s in signs))
        self._set("sz_button", integer("sz_button", self.sz_button, 0, 31))
        self._set("report_timeout_s", bounded("report_timeout_s", self.report_timeout_s, 0.02, 5.0))
        self._set("rate_hz", bounded("rate_hz", self.rate_hz, 10.0, 10e3))
        self._set("reconnect_interval_s", bounded("reconnect_interval_s", self.reconnect_interval_s, 0.05, 60.0))
        self._set("read_timeout_ms", integer("read_timeout_ms", self.read_timeout_ms, 1, 1000))

    def shaped(self, counts: int) -> float:
        """Deflection in [-1, 1] after the deadband."""
        a = abs(counts) - self.deadband_counts
        if a <= 0:
            return 0.0
        return math.copysign(min(a / (self.full_scale_counts - self.deadband_counts), 1.0), counts)


def find_spacemouse_ids(backend=None) -> tuple[int, int]:
    """The VID:PID of the first known SpaceMouse connected (for ``vid_pid = ""``)."""
    kwargs = {"backend": backend} if backend is not None else {}
    try:
        dev = usb.core.find(custom_match=lambda d: (d.idVendor, d.idProduct) in KNOWN_SPACEMICE, **kwargs)
    except usb.core.NoBackendError:
        raise DeviceError("no USB library found: install libusb-1.0 (e.g. apt install libusb-1.0-0)") from None
    if dev is None:
        raise DeviceError("no 3Dconnexion SpaceMouse is connected: plug one in, or set hardware.master.vid_pid "
                          "(`palpation-console devices` lists what this computer sees)")
    return dev.idVendor, dev.idProduct


class SpaceMouseMaster(Connection, MasterDevice):
    name = "spacemouse"

    def __init__(self, settings: SpaceMouseSettings | None = None, backend=None):
        super().__init__()
        self.settings = settings if settings is not None else SpaceMouseSettings()
        self.constraints = MasterConstraints(rate_hz=self.settings.rate_hz, has_sz_switch=True)
        self._backend = backend
        self.pipe: UsbInPipe | None = None
        self.decoder = ReportDecoder()
        self._position = [0.0, 0.0, 0.0]
        self._sz = True  # position control
        self._buttons = 0
        self._seq = -1
        self._latest: MasterState | None = None
        self._last_poll: float | None = None
        self._last_report: float | None = None
        self._timed_out = False
        self.counters = dict.fromkeys(("reports", "ignored_reports", "report_timeouts", "sz_presses"), 0)

    def _connect(self) -> ConnectionState:
        s = self.settings
        ids = vid_pid("vid_pid", s.vid_pid) if s.vid_pid else find_spacemouse_ids(self._backend)
        self.pipe = UsbInPipe(ids[0], ids[1], "master device", interface=s.interface, endpoint=s.endpoint,
                              serial_number=s.serial_number, backend=self._backend,
                              read_timeout_ms=s.read_timeout_ms, reconnect_interval_s=s.reconnect_interval_s)
        self.pipe.open()
        self.decoder = ReportDecoder()
        self._buttons = 0
        self._last_poll = None
        return ConnectionState.CONNECTED  # a HID device is silent at rest: claimed is connected

    def _disconnect(self) -> None:
        if self.pipe is not None:
            self.pipe.close()

    def poll(self, now_s: float) -> None:
        if self._state == ConnectionState.DISCONNECTED or self.pipe is None:
            return
        self.pipe.start()  # from the loop's thread: the reader shares its priority and CPU
        for item in self.pipe.take(MAX_REPORTS_PER_POLL):
            if isinstance(item, bytes):
                self._on_report(item, now_s)
            elif isinstance(item, Lost):
                self._lost(item.reason)
            elif isinstance(item, Attached) and self._state == ConnectionState.LOST:
                # a fresh start for the cap and buttons; the position carries on, so X_d does not jump
                self.decoder = ReportDecoder()
                self._buttons = 0
                self._last_report = None
                self._heard()
        if self._state != ConnectionState.CONNECTED:
            self._last_poll = None
            return
        dt = 0.0 if self._last_poll is None else min(max(now_s - self._last_poll, 0.0), 0.05)
        self._last_poll = now_s
        v = self.velocity_m_s(now_s)
        for i in range(3):
            self._position[i] += v[i] * dt
        self._seq += 1
        self._latest = MasterState(self._seq, now_s, (self._position[0], self._position[1], self._position[2]),
                                   self._sz)

    def velocity_m_s(self, now_s: float) -> Vec3:
        """What the cap asks for now (zero if it has gone quiet while deflected)."""
        s = self.settings
        t = self.decoder.translation
        if not any(t):
            return (0.0, 0.0, 0.0)
        if self._last_report is None or now_s - self._last_report > s.report_timeout_s:
            if not self._timed_out:
                self._timed_out = True
                self.counters["report_timeouts"] += 1
                self.last_error = (f"the SpaceMouse reported a deflection and then nothing for over "
                                   f"{s.report_timeout_s * 1e3:.0f} ms: taken as released")
            return (0.0, 0.0, 0.0)
        return tuple(s.axis_signs[i] * s.speed_m_s * s.shaped(t[i]) for i in range(3))  # type: ignore[return-value]

    def latest(self) -> MasterState | None:
        return self._latest

    def feedback(self, fb: MasterFeedback) -> None:
        if fb.phase not in _FORCE_CONTROL:
            self._sz = True  # the loop has z in position control, whatever the last press asked

    @property
    def stats(self) -> dict[str, Any]:
        pipe = self.pipe
        d = self.decoder
        return {"device": self.name, "usb": pipe.description if pipe else self.settings.vid_pid,
                "connection": self._state.name, "last_error": self.last_error or (pipe.last_error if pipe else ""),
                **self.counters, "unknown_reports": d.unknown, "short_reports": d.short,
                **(pipe.counters if pipe else {}), "sz_switch": self._sz}

    def describe(self) -> dict[str, Any]:
        return {"backend": "usb-spacemouse", "settings": self.settings.to_mapping()}

    def _on_report(self, report: bytes, now_s: float) -> None:
        if not self.decoder.feed(report):
            self.counters["ignored_reports"] += 1
            return
        self.counters["reports"] += 1
        self._last_report = now_s
        self._timed_out = False
        buttons = self.decoder.buttons
        pressed = buttons & ~self._buttons
        self._buttons = buttons
        if pressed >> self.settings.sz_button & 1:
            self._sz = not self._sz
            self.counters["sz_presses"] += 1
