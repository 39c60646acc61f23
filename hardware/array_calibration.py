"""The tactile array's calibration: each element's sensitivity against the array's, measured by pressing a
uniform reference, kept in a file, applied to every frame the loop sees and recorded in every session.

Why: a capacitive array's elements differ in sensitivity as a fixed pattern, 6-8 % between elements of a
real one (CySkin, Scimeca et al., Autonomous Robots 2020; docs/phantoms.md, section 2, item 12). That is as
large as the contrast of a deep tumour, and it is the same in every session, so a lab measures it once and
takes it out, as users of tactile arrays do (Tekscan's and PPS's "equilibration": every element loaded with
the same pressure, each one's reading compared with the array's).

The fit (written down once, here). The reference is a fluid cushion or a thin pad larger than the face, which
presses every element with the same pressure whatever the face's tilt; a thick block does not (a rigid face
on it reads high at its edges, and that pattern would be taken for the array's). It is pressed ``presses``
times, each press a force ramp of several levels, and each level's record holds every element's mean over
its settled window. For record ``r`` (press ``a``, level ``k``) element ``e`` reads

    reading[r, e] = gain[e] * (P[r] + offset[a, e])

where ``P[r]`` is the reference's pressure there (not known: the face's own mean reading, each element
divided by its gain, stands for it) and ``offset[a, e]`` is the press's own error: pressing the same spot again
reads differently, as if the indentation were offset, and the first press after a pause reads high, both by
3-20 % of full scale at partial press on the real array; on a linear reference that is a pressure added for
the whole press once contact has formed (``LINEAR_FROM``). Within a press the slope of an element's readings
against ``P`` is its gain whatever that offset, so ``gain`` is the pooled within-press least-squares slope,
``P`` and ``gain`` found in turn until they agree, and the gains normalised to a mean of one: the array's mean
sensitivity (its factory scale) is kept, only the pattern is taken out. ``gain_sigma`` is each slope's
standard error from its residuals.

It works on what the array's own driver delivers, in pascals, whichever backend that is: a serial array's
counts-to-pascals calibration and equilibration CSV (hardware/serial_tactile/calibration.py) come first, and
what this fit measures is whatever pattern remains after them, so the two never correct the same thing twice
as long as the array is calibrated with the driver settings it is used with.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from hardware.interfaces import TactileFrame, TactileSensor
from hardware.settings import ConfigError
from tissue.files import UnreadableFile, read_toml

CALIBRATION_FORMAT = "palpation-console-array-calibration"
# An element whose sensitivity departs this far from the array's is broken, or was not on a uniform
# reference (a face on a thick block reads 20-40 % high at its edge rows): refuse the fit rather than
# carry that into every session.
GAIN_RANGE = (0.7, 1.3)
MIN_PRESSES = 2
MIN_LEVELS = 3  # per press: a slope needs a spread of pressures, and a third level checks it is one
# Each press's records from this share of its highest on: below it contact is still forming, where a real
# element is least linear and a press's error is not yet a constant (hardware/sim/sensor.py, PRESS_ONSET_M).
# With them the simulated realistic array's pattern came out 2.1 % wrong at worst, without them 0.11 %.
LINEAR_FROM = 0.4
# The loaded face's mean must span this many pascals within a press, or the slope is all noise.
MIN_SPAN_PA = 1000.0


class ArrayCalibrationError(ValueError):
    """A calibration that cannot be made or used; the message says why in one line."""


@dataclass(frozen=True)
class ArrayCalibration:
    gain: np.ndarray  # (rows, cols): each element's sensitivity over the array's mean
    gain_sigma: np.ndarray  # (rows, cols): its standard error, relative
    presses: int
    levels: int  # records the fit used
    pressure_range_pa: tuple[float, float]  # the reference's pressure over those records
    created_utc: str
    array: str = ""  # which array it was measured on, as the rig described it
    source: str = ""  # what it was measured from (a session file's name)

    def __post_init__(self):
        gain = np.asarray(self.gain, dtype=float)
        sigma = np.asarray(self.gain_sigma, dtype=float)
        if gain.ndim != 2 or sigma.shape != gain.shape:
            raise ArrayCalibrationError(f"gain and gain_sigma must be tables of the same shape, got {gain.shape} "
                                        f"and {sigma.shape}")
        lo, hi = GAIN_RANGE
        if not (np.all(np.isfinite(gain)) and np.all((gain >= lo) & (gain <= hi))):
            bad = np.argwhere(~((gain >= lo) & (gain <= hi)))[0]
            raise ArrayCalibrationError(f"element (row {bad[0]}, column {bad[1]}) has a sensitivity of "
                                        f"{gain[tuple(bad)]:.3g} times the array's: outside {lo}-{hi}, a broken "
                                        f"element or a reference that did not press every element alike")
        if not (np.all(np.isfinite(sigma)) and np.all(sigma >= 0) and np.all(sigma < 1)):
            raise ArrayCalibrationError("gain_sigma must be finite, relative and between 0 and 1")
        object.__setattr__(self, "gain", gain)
        object.__setattr__(self, "gain_sigma", sigma)

    @property
    def shape(self) -> tuple[int, int]:
        return self.gain.shape  # type: ignore[return-value]

    def summary(self) -> str:
        """One line for the operator: how the array's elements differ and how well that is known."""
        spread = float(np.std(self.gain))
        return (f"{self.presses} presses, {self.pressure_range_pa[0] / 1e3:.1f}-{self.pressure_range_pa[1] / 1e3:.1f}"
                f" kPa: element sensitivities spread {spread:.1%} (range {self.gain.min():.3f}-{self.gain.max():.3f}), "
                f"each known to {float(np.median(self.gain_sigma)):.2%} (median)")

    def to_mapping(self) -> dict[str, Any]:
        return {"format": CALIBRATION_FORMAT, "version": 1, "created_utc": self.created_utc, "array": self.array,
                "source": self.source, "presses": self.presses, "levels": self.levels,
                "pressure_range_pa": list(self.pressure_range_pa),
                "gain": np.round(self.gain, 6).tolist(), "gain_sigma": np.round(self.gain_sigma, 6).tolist()}

    @classmethod
    def from_mapping(cls, data: Any, where: str = "calibration") -> ArrayCalibration:
        if not isinstance(data, dict) or data.get("format") != CALIBRATION_FORMAT:
            raise ArrayCalibrationError(f"{where}: not a Palpation Console array calibration")
        if data.get("version") != 1:
            raise ArrayCalibrationError(f"{where}: calibration version {data.get('version')!r}; this console reads 1")
        try:
            lo, hi = (float(v) for v in data["pressure_range_pa"])
            made = cls(gain=np.asarray(data["gain"], dtype=float),
                       gain_sigma=np.asarray(data["gain_sigma"], dtype=float), presses=_count(data["presses"]),
                       levels=_count(data["levels"]), pressure_range_pa=(lo, hi),
                       created_utc=str(data["created_utc"]), array=str(data.get("array", "")),
                       source=str(data.get("source", "")))
        except KeyError as err:
            raise ArrayCalibrationError(f"{where}: damaged (no {err.args[0]!r})") from None
        except ArrayCalibrationError as err:
            raise ArrayCalibrationError(f"{where}: {err}") from None
        except (TypeError, ValueError) as err:
            raise ArrayCalibrationError(f"{where}: damaged ({err})") from None
        return made

    def save(self, path: str | Path) -> None:
        import tomli_w

        data = self.to_mapping()
        tables = {name: data.pop(name) for name in ("gain", "gain_sigma")}
        text = ("# The tactile array's element sensitivities (palpation-console calibrate; "
                "hardware/array_calibration.py)\n" + tomli_w.dumps(data))
        for name, rows in tables.items():  # a row of the array per line, as it lies on the face
            text += f"{name} = [\n" + "".join(f"    {row!r},\n" for row in rows) + "]\n"
        try:
            Path(path).write_text(text, encoding="utf-8")
        except OSError as err:
            raise ArrayCalibrationError(f"{path}: cannot write the calibration ({err.strerror or err})") from None

    @classmethod
    def load(cls, path: str | Path) -> ArrayCalibration:
        try:
            data = read_toml(Path(path), "calibration file")
        except UnreadableFile as err:
            raise ArrayCalibrationError(str(err)) from None
        return cls.from_mapping(data, str(path))

    def check_fits(self, shape: tuple[int, int]) -> None:
        if self.shape != tuple(shape):
            raise ConfigError("rig.calibration", f"made for an array of {self.shape[0]} x {self.shape[1]} elements, "
                                                 f"this one has {shape[0]} x {shape[1]}")


def _count(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"a count must be a whole number, got {value!r}")
    return value


def fit_gains(pressure_pa: np.ndarray, press: np.ndarray, *, array: str = "", source: str = "",
              now: datetime | None = None) -> ArrayCalibration:
    """The calibration records of a uniform reference give (module docstring): ``pressure_pa`` (records,
    rows, cols) each level's settled mean, ``press`` (records,) which press each record belongs to."""
    readings = np.asarray(pressure_pa, dtype=float)
    press = np.asarray(press)
    if readings.ndim != 3 or press.shape != readings.shape[:1]:
        raise ArrayCalibrationError(f"expected (records, rows, cols) readings and a press per record, got "
                                    f"{readings.shape} and {press.shape}")
    shape = readings.shape[1:]
    y = readings.reshape(len(readings), -1)
    groups = _presses(y, press)
    used = np.concatenate(groups)
    quiet = np.median(y[used], axis=0) <= MIN_SPAN_PA / 10
    if quiet.any():
        raise ArrayCalibrationError(f"element {_element(int(np.argmax(quiet)), shape)} did not feel the reference: "
                                    f"the face was not wholly on it")
    gain = np.ones(y.shape[1])
    for _ in range(50):
        ref = np.mean(y / gain, axis=1)  # the reference's pressure, in the array's mean sensitivity
        slopes = [(rc @ yc, float(rc @ rc)) for rc, yc in _centred(groups, ref, y)]
        new = sum(s for s, _ in slopes) / sum(d for _, d in slopes)
        if not np.all(np.isfinite(new) & (new > 0)):
            bad = int(np.argmax(~(np.isfinite(new) & (new > 0))))
            raise ArrayCalibrationError(f"element {_element(bad, shape)} does not follow the reference's pressure "
                                        f"(stuck or dead)")
        new /= new.mean()
        done = np.max(np.abs(new - gain)) < 1e-10
        gain = new
        if done:
            break
    ref = np.mean(y / gain, axis=1)
    residual_ss = np.zeros(y.shape[1])
    den = 0.0
    for rc, yc in _centred(groups, ref, y):
        residual_ss += np.sum((yc - np.outer(rc, gain)) ** 2, axis=0)
        den += float(rc @ rc)
    dof = max(len(used) - 2 * len(groups), 1)
    sigma = np.sqrt(residual_ss / dof / den) / gain
    stamp = (now or datetime.now(timezone.utc)).isoformat(timespec="seconds")
    try:
        return ArrayCalibration(gain.reshape(shape), sigma.reshape(shape), presses=len(groups), levels=len(used),
                                pressure_range_pa=(float(ref[used].min()), float(ref[used].max())),
                                created_utc=stamp, array=array, source=source)
    except ArrayCalibrationError as err:
        raise ArrayCalibrationError(f"the presses do not give a calibration: {err}") from None


def _presses(y: np.ndarray, press: np.ndarray) -> list[np.ndarray]:
    """The records of each usable press, from where its contact has formed (``LINEAR_FROM``)."""
    usable = np.all(np.isfinite(y), axis=1)
    face_mean = y.mean(axis=1)
    groups = []
    for a in np.unique(press[usable]):
        idx = np.flatnonzero(usable & (press == a))
        idx = idx[face_mean[idx] >= LINEAR_FROM * face_mean[idx].max()]
        if len(idx) >= MIN_LEVELS and np.ptp(face_mean[idx]) >= MIN_SPAN_PA:
            groups.append(idx)
    if len(groups) < MIN_PRESSES:
        raise ArrayCalibrationError(f"{len(groups)} usable press(es) of the reference: a calibration needs at least "
                                    f"{MIN_PRESSES}, each of {MIN_LEVELS} or more levels spanning "
                                    f"{MIN_SPAN_PA / 1e3:g} kPa")
    return groups


def _centred(groups: list[np.ndarray], ref: np.ndarray, y: np.ndarray):
    """Each press's reference pressures and readings about their own means: what takes its offset out."""
    for idx in groups:
        yield ref[idx] - ref[idx].mean(), y[idx] - y[idx].mean(axis=0)


def _element(flat_index: int, shape: tuple[int, ...]) -> str:
    return f"(row {flat_index // shape[1]}, column {flat_index % shape[1]})"


class CalibratedSensor(TactileSensor):
    """A tactile array whose frames have each element's sensitivity taken out (``ArrayCalibration.gain``): what
    the loop, its safety checks and the session all see. Everything else is the array's own."""

    def __init__(self, inner: TactileSensor, calibration: ArrayCalibration):
        calibration.check_fits(inner.constraints.shape)
        self.inner = inner
        self.calibration = calibration
        self.constraints = inner.constraints
        self.name = inner.name
        self._inverse = 1.0 / calibration.gain
        self._seen: TactileFrame | None = None
        self._frame: TactileFrame | None = None

    @property
    def connection(self):
        return self.inner.connection

    def open(self) -> None:
        self.inner.open()

    def close(self) -> None:
        self.inner.close()

    def poll(self, now_s: float) -> None:
        self.inner.poll(now_s)

    def tare(self) -> None:
        self.inner.tare()

    def latest(self) -> TactileFrame | None:
        frame = self.inner.latest()
        # once per frame, not per control tick: the loop asks every millisecond, frames come every ten
        if frame is not self._seen:
            self._seen = frame
            self._frame = None if frame is None else TactileFrame(
                frame.seq, frame.t_s, frame.pressure_pa * self._inverse, frame.saturated)
        return self._frame

    def __getattr__(self, name: str):
        # what the inner array offers beyond the interface (its status, a simulator's truth) stays reachable
        return getattr(self.__dict__["inner"], name)


def gain_error(fitted: ArrayCalibration, true_gain: np.ndarray) -> float:
    """The largest relative error of a fitted pattern against a known one (normalised alike)."""
    truth = np.asarray(true_gain, dtype=float)
    truth = truth / truth.mean()
    return float(np.max(np.abs(fitted.gain / truth - 1.0)))
