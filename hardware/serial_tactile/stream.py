"""From wire-format bytes to calibrated, tared, host-timed frames: what every tactile transport shares.

A transport (serial port, USB endpoint) hands :meth:`TactileStream.feed` whatever bytes it read and the
host time it read them at; the stream parses them (:class:`~hardware.serial_tactile.driver.FrameParser`),
checks the sequence numbers, maps the device clock onto the host clock
(:class:`~hardware.serial_tactile.clock.DeviceClock`), calibrates and tares. It never blocks and holds no
OS resource, so it is tested without any port.

Sequence numbers: a gap is frames the device sampled that never arrived (``frames_lost``); a repeat is
ignored (``duplicates``); a step back means the device restarted (``device_restarts``: its clock is
re-learnt). The published ``seq`` keeps increasing across restarts and reconnections, so the loop
always recognises a new frame. The tare survives reconnections: re-taring a probe that may be pressing
on tissue would hide that force from the safety supervisor. For the same reason a first frame that an
unloaded array cannot give (saturated, or loaded beyond a fraction of full scale) is not taken as zero on
opening: the frames are then published untared (the baseline reads as a small force, which is the safe
side) and ``tare_refused`` says why.

An element whose calibrated reading is at or beyond full scale is flagged saturated in the frame.

:class:`StreamedTactileSensor` is the device around a stream, which the serial and USB adapters are: its
frames, its tare and the stale-data rule.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hardware.connection import Connection
from hardware.interfaces import DeviceError, TactileConstraints, TactileFrame, TactileSensor, tare_problem
from hardware.serial_tactile.calibration import Calibration, CalibrationError, load_equilibration
from hardware.serial_tactile.clock import DeviceClock
from hardware.serial_tactile.config import boolean, optional_path
from hardware.serial_tactile.driver import U32, FrameParser, RawFrame
from hardware.settings import ConfigError, Settings, bounded
from tissue.face import MAX_COVER_SPREAD_M

CONVERTER_BITS = 12  # an uncalibrated device: full scale over a 12-bit converter


@dataclass(frozen=True)
class TactileSettings(Settings):
    """What every tactile transport shares: calibration files, tare, rate, and when to call it lost."""

    calibration: str | None = None  # TOML calibration file; none: full scale over 12 bits, zero offset
    equilibration: str | None = None  # CSV of per-element factors
    tare_on_open: bool = True  # the first frame after opening is zero (never after a reconnection)
    frame_rate_hz: float = 100.0  # what the device sends
    full_scale_pa: float = 100e3
    # how far the array's elastomer cover spreads an element's load sideways, as its maker states it (0: not
    # stated); sessions record it, and the analysis's expected pattern is blurred by it
    cover_spread_m: float = 0.0
    frame_timeout_s: float = 0.25  # no good frame for this long: LOST
    reconnect_interval_s: float = 0.5

    def __post_init__(self):
        self._set("calibration", optional_path("calibration", self.calibration))
        self._set("equilibration", optional_path("equilibration", self.equilibration))
        self._set("tare_on_open", boolean("tare_on_open", self.tare_on_open))
        self._set("frame_rate_hz", bounded("frame_rate_hz", self.frame_rate_hz, 1.0, 1000.0))
        self._set("full_scale_pa", bounded("full_scale_pa", self.full_scale_pa, 1e3, 10e6))
        self._set("cover_spread_m", bounded("cover_spread_m", self.cover_spread_m, 0.0, MAX_COVER_SPREAD_M))
        self._set("frame_timeout_s", bounded("frame_timeout_s", self.frame_timeout_s, 0.01, 10.0))
        self._set("reconnect_interval_s", bounded("reconnect_interval_s", self.reconnect_interval_s, 0.05, 60.0))
        if self.frame_timeout_s * self.frame_rate_hz < 2:
            raise ConfigError("frame_timeout_s", f"must span at least two frames at {self.frame_rate_hz:g} frames/s")

    def constraints(self) -> TactileConstraints:
        return TactileConstraints(full_scale_pa=self.full_scale_pa, frame_rate_hz=self.frame_rate_hz,
                                  cover_spread_m=self.cover_spread_m)

    def load_calibration(self) -> Calibration:
        """The calibration the settings name (with its equilibration), or the uncalibrated default."""
        shape = self.constraints().shape
        try:
            if self.calibration is None:
                cal = Calibration.uniform(self.full_scale_pa / ((1 << CONVERTER_BITS) - 1), 0.0, shape,
                                          device=f"uncalibrated: full scale over {CONVERTER_BITS} bits")
            else:
                cal = Calibration.load(self.calibration, shape)
            if self.equilibration is not None:
                cal = cal.with_equilibration(load_equilibration(self.equilibration, shape), self.equilibration)
        except CalibrationError as err:
            raise DeviceError(f"tactile sensor calibration: {err}") from None
        return cal


class TactileStream:
    def __init__(self, constraints: TactileConstraints, calibration: Calibration, tare_on_open: bool = True):
        if calibration.shape != constraints.shape:
            raise ValueError(f"the calibration is for a {calibration.shape} array, the sensor is {constraints.shape}")
        self.constraints = constraints
        self.calibration = calibration
        self.tare_on_open = tare_on_open
        self.parser = FrameParser(constraints.rows, constraints.cols)
        self.clock = DeviceClock()
        self.latest: TactileFrame | None = None
        self.last_rx_s: float | None = None  # host time of the newest good frame
        self.frames_lost = 0
        self.duplicates = 0
        self.overruns = 0
        self.device_restarts = 0
        self._raw_seq: int | None = None
        self._seq = -1
        self._zero: np.ndarray | None = None
        self._untared: np.ndarray | None = None
        self._saturated: np.ndarray | None = None
        self.tare_refused = ""  # why the first frame was not taken as zero on opening ("" if it was, or not asked)
        self._rate_t0: float | None = None
        self._rate_n = 0
        self.frame_rate_hz = float("nan")  # measured over the last second or so

    def start(self) -> None:
        """A fresh connection: the first frame is taken as zero if ``tare_on_open``."""
        self._zero = None if self.tare_on_open else np.zeros(self.constraints.shape)
        self.tare_refused = ""
        self.link_reset()

    def link_reset(self) -> None:
        """The transport was reopened: drop a partial frame and re-learn the device's clock and counter."""
        self.parser.reset()
        self.clock.reset()
        self._raw_seq = None
        self._rate_t0 = None

    def tare(self) -> None:
        """Zero every element at its latest reading; DeviceError (nothing changed) if there is none or it is
        not a reading of an unloaded array."""
        if self._untared is None:
            raise DeviceError("tactile sensor: no frame has arrived yet to take as zero")
        problem = tare_problem(self._untared, self._saturated, self.constraints.full_scale_pa)
        if problem is not None:
            raise DeviceError(f"tactile sensor: not tared: {problem}")
        self._zero = self._untared.copy()

    def feed(self, data: bytes | bytearray | memoryview, now_s: float) -> int:
        """Parse ``data`` read by ``now_s``; returns how many new frames were accepted."""
        accepted = 0
        for raw in self.parser.feed(data):
            if self._accept(raw, now_s):
                accepted += 1
        return accepted

    def _accept(self, raw: RawFrame, now_s: float) -> bool:
        if self._raw_seq is None:
            step = 1
        else:
            step = (raw.seq - self._raw_seq) % U32
            if step == 0:
                self.duplicates += 1
                return False
            if step >= U32 // 2:
                self.device_restarts += 1
                self.clock.reset()
                step = 1
            else:
                self.frames_lost += step - 1
        self._raw_seq = raw.seq
        self._seq += step
        if raw.overrun:
            self.overruns += 1
        t_s = self.clock.map(raw.device_time_us, now_s)
        untared = self.calibration.pressure_pa(raw.counts)
        saturated = untared >= self.constraints.full_scale_pa
        self._untared, self._saturated = untared, saturated
        if self._zero is None:
            problem = tare_problem(untared, saturated, self.constraints.full_scale_pa)
            if problem is None:
                self._zero = untared.copy()
            else:
                self._zero = np.zeros_like(untared)
                self.tare_refused = f"not tared on opening: {problem}"
        self.latest = TactileFrame(seq=self._seq, t_s=t_s, pressure_pa=untared - self._zero, saturated=saturated)
        self.last_rx_s = now_s
        self._count_rate(now_s)
        return True

    def _count_rate(self, now_s: float) -> None:
        if self._rate_t0 is None:
            self._rate_t0, self._rate_n = now_s, 0
            return
        self._rate_n += 1
        span = now_s - self._rate_t0
        if span >= 1.0:
            self.frame_rate_hz = self._rate_n / span
            self._rate_t0, self._rate_n = now_s, 0

    def counters(self) -> dict[str, int | float]:
        p = self.parser
        return {"frames": p.frames, "frames_lost": self.frames_lost, "crc_errors": p.crc_errors,
                "truncated": p.truncated, "header_errors": p.header_errors, "garbage_bytes": p.garbage_bytes,
                "duplicates": self.duplicates, "device_overruns": self.overruns,
                "device_restarts": self.device_restarts, "frame_rate_hz": self.frame_rate_hz}


class StreamedTactileSensor(Connection, TactileSensor):
    """A tactile array whose transport hands its bytes to a :class:`TactileStream` (the serial and USB
    adapters): its frames and tare, and the stale-data rule, LOST once no good frame has come for
    ``frame_timeout_s`` (``stale_episodes`` counts those)."""

    def __init__(self, settings: TactileSettings, calibration: Calibration | None):
        super().__init__()
        self.settings = settings
        self.constraints = settings.constraints()
        self.calibration = calibration if calibration is not None else settings.load_calibration()
        self._stream = TactileStream(self.constraints, self.calibration, settings.tare_on_open)
        self.stale_episodes = 0

    def latest(self) -> TactileFrame | None:
        return self._stream.latest

    def tare(self) -> None:
        self._stream.tare()

    def _fed(self, fresh: int, now_s: float) -> None:
        """A poll fed the stream ``fresh`` good frames (none while the device is away)."""
        if fresh:
            self._heard()
        elif self._silent(now_s, self._stream.last_rx_s, self.settings.frame_timeout_s, self._stale_reason):
            self.stale_episodes += 1

    def _stale_reason(self, silent_s: float) -> str:
        return f"no good frame for {silent_s * 1e3:.0f} ms"
