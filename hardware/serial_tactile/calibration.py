"""Per-element calibration of a tactile array: counts to pascals, and the files that hold it.

For element (i, j) with raw converter reading ``c``::

    pressure_pa = gain_pa_per_count[i, j] * equilibration[i, j] * (c - offset_counts[i, j]) - tare_pa[i, j]

* ``gain_pa_per_count`` and ``offset_counts`` come from the calibration file (the manufacturer's or
  a bench calibration against known loads): a scalar for the whole array or one value per element.
* ``equilibration`` (dimensionless, about 1) evens out element-to-element sensitivity. It is measured
  by loading the whole array with one uniform pressure (a bladder or a flat weight) and computed by
  :func:`equilibrate`; it lives in its own CSV file because it is redone far more often than the
  calibration.
* ``tare_pa`` is taken at run time (:meth:`TactileSensor.tare`), not stored.

Calibration file (TOML)::

    format = "palpation-tsi-calibration"
    version = 1
    device = "TSI #7, calibrated 2024-05-02"     # free text, copied into the session file
    rows = 4
    cols = 15
    gain_pa_per_count = 24.4140625               # or 4 arrays of 15 numbers
    offset_counts = 41.0                         # or 4 arrays of 15 numbers

Equilibration file (CSV): ``rows`` lines of ``cols`` comma-separated factors, row i along x; lines
starting with ``#`` are comments.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

FORMAT = "palpation-tsi-calibration"
FORMAT_VERSION = 1
EQUILIBRATION_RANGE = (0.5, 2.0)  # beyond this an element is broken, not merely less sensitive


class CalibrationError(ValueError):
    """A calibration or equilibration file (or array) that cannot be used, with the reason."""


def _table(name: str, value: Any, shape: tuple[int, int], where: str) -> np.ndarray:
    if isinstance(value, bool):
        raise CalibrationError(f"{where}: {name} must be a number or {shape[0]} rows of {shape[1]} numbers")
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(
            f"{where}: {name} must be a number or {shape[0]} rows of {shape[1]} numbers") from None
    if arr.ndim == 0:
        arr = np.full(shape, float(arr))
    if arr.shape != shape:
        raise CalibrationError(f"{where}: {name} has shape {arr.shape}, expected {shape} (rows along x)")
    if not np.isfinite(arr).all():
        raise CalibrationError(f"{where}: {name} contains non-finite values")
    return arr


@dataclass(frozen=True)
class Calibration:
    gain_pa_per_count: np.ndarray
    offset_counts: np.ndarray
    equilibration: np.ndarray
    device: str = ""
    source: str = ""  # where it was loaded from, for the session file
    _scale: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        shape = np.shape(self.gain_pa_per_count)
        where = self.source or "calibration"
        if len(shape) != 2:
            raise CalibrationError(f"{where}: the gain must be a (rows, cols) array, got shape {shape}")
        gain = _table("gain_pa_per_count", self.gain_pa_per_count, shape, where)
        offset = _table("offset_counts", self.offset_counts, shape, where)
        eq = _table("equilibration", self.equilibration, shape, where)
        if (gain <= 0).any():
            raise CalibrationError(f"{where}: gain_pa_per_count must be > 0 for every element")
        lo, hi = EQUILIBRATION_RANGE
        bad = np.argwhere((eq < lo) | (eq > hi))
        if len(bad):
            i, j = bad[0]
            raise CalibrationError(f"{where}: equilibration factor {eq[i, j]:g} of element ({i}, {j}) is outside "
                                   f"[{lo:g}, {hi:g}]; that element is faulty, re-equilibrate or replace the array")
        for name, arr in (("gain_pa_per_count", gain), ("offset_counts", offset), ("equilibration", eq)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        scale = gain * eq
        scale.setflags(write=False)
        object.__setattr__(self, "_scale", scale)

    @property
    def shape(self) -> tuple[int, int]:
        return self.gain_pa_per_count.shape  # type: ignore[return-value]

    @classmethod
    def uniform(cls, gain_pa_per_count: float, offset_counts: float = 0.0, shape: tuple[int, int] = (4, 15),
                device: str = "") -> Calibration:
        return cls(np.full(shape, float(gain_pa_per_count)), np.full(shape, float(offset_counts)),
                   np.ones(shape), device=device)

    def pressure_pa(self, counts: np.ndarray) -> np.ndarray:
        """Calibrated (untared) pressure of a frame of raw counts."""
        return self._scale * (counts - self.offset_counts)

    def counts_for(self, pressure_pa: np.ndarray) -> np.ndarray:
        """The raw counts a device with this calibration sends for ``pressure_pa`` (emulators, checks)."""
        counts = np.rint(np.asarray(pressure_pa, dtype=float) / self._scale + self.offset_counts)
        return np.clip(counts, 0, 0xFFFF).astype(np.uint16)

    def with_equilibration(self, factors: np.ndarray, source: str = "") -> Calibration:
        return Calibration(self.gain_pa_per_count, self.offset_counts, factors, self.device,
                           f"{self.source} + {source}" if source else self.source)

    def describe(self) -> dict[str, Any]:
        """What the session file records about the calibration in use."""
        return {"device": self.device, "source": self.source,
                "gain_pa_per_count": self.gain_pa_per_count.tolist(),
                "offset_counts": self.offset_counts.tolist(), "equilibration": self.equilibration.tolist()}

    # ---- files ---------------------------------------------------------------------------------------

    @classmethod
    def load(cls, path: str | Path, shape: tuple[int, int] = (4, 15)) -> Calibration:
        path = Path(path)
        where = str(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise CalibrationError(f"{where}: no such calibration file") from None
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
            raise CalibrationError(f"{where}: cannot read the calibration file: {err}") from None
        if data.get("format") != FORMAT:
            raise CalibrationError(f"{where}: not a TSI calibration file (format = {data.get('format')!r}, "
                                   f"expected {FORMAT!r})")
        if data.get("version") != FORMAT_VERSION:
            raise CalibrationError(f"{where}: calibration format version {data.get('version')!r} is not "
                                   f"supported (this software reads version {FORMAT_VERSION})")
        known = {"format", "version", "device", "rows", "cols", "gain_pa_per_count", "offset_counts"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise CalibrationError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(sorted(known))})")
        file_shape = (data.get("rows"), data.get("cols"))
        if file_shape != shape:
            raise CalibrationError(f"{where}: calibrates a {file_shape[0]} x {file_shape[1]} array, "
                                   f"this sensor is {shape[0]} x {shape[1]}")
        if "gain_pa_per_count" not in data:
            raise CalibrationError(f"{where}: gain_pa_per_count is missing")
        gain = _table("gain_pa_per_count", data["gain_pa_per_count"], shape, where)
        offset = _table("offset_counts", data.get("offset_counts", 0.0), shape, where)
        device = data.get("device", "")
        if not isinstance(device, str):
            raise CalibrationError(f"{where}: device must be text")
        return cls(gain, offset, np.ones(shape), device=device, source=where)

    def save(self, path: str | Path) -> None:
        rows, cols = self.shape

        def table(arr: np.ndarray) -> str:
            if np.all(arr == arr.flat[0]):
                return repr(float(arr.flat[0]))
            lines = ",\n    ".join("[" + ", ".join(repr(float(v)) for v in row) + "]" for row in arr)
            return f"[\n    {lines},\n]"

        device = self.device.replace("\\", "\\\\").replace('"', '\\"')
        text = (f'format = "{FORMAT}"\nversion = {FORMAT_VERSION}\ndevice = "{device}"\n'
                f"rows = {rows}\ncols = {cols}\n"
                f"gain_pa_per_count = {table(self.gain_pa_per_count)}\n"
                f"offset_counts = {table(self.offset_counts)}\n")
        Path(path).write_text(text, encoding="utf-8")


def load_equilibration(path: str | Path, shape: tuple[int, int] = (4, 15)) -> np.ndarray:
    path = Path(path)
    where = str(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise CalibrationError(f"{where}: no such equilibration file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise CalibrationError(f"{where}: cannot read the equilibration file: {err}") from None
    rows = []
    for n, line in enumerate(lines, 1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        try:
            rows.append([float(v) for v in text.split(",")])
        except ValueError:
            raise CalibrationError(f"{where}, line {n}: expected comma-separated numbers, got {text!r}") from None
    if len(rows) != shape[0] or any(len(r) != shape[1] for r in rows):
        got = f"{len(rows)} rows of " + "/".join(sorted({str(len(r)) for r in rows}) or ["0"])
        raise CalibrationError(f"{where}: expected {shape[0]} rows of {shape[1]} factors, got {got}")
    factors = np.array(rows)
    if not np.isfinite(factors).all():
        raise CalibrationError(f"{where}: contains non-finite factors")
    return factors


def save_equilibration(path: str | Path, factors: np.ndarray, comment: str = "") -> None:
    lines = [f"# {line}" for line in comment.splitlines()] if comment else []
    lines += [",".join(repr(float(v)) for v in row) for row in np.asarray(factors, dtype=float)]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def equilibrate(counts: np.ndarray, calibration: Calibration) -> np.ndarray:
    """Equilibration factors from frames of raw counts taken under one uniform pressure.

    ``counts`` is (frames, rows, cols) or one (rows, cols) average. Each element's factor scales its
    calibrated reading onto the array's mean reading, so a uniform load reads uniform. Refuses a load
    too light to tell sensitivity from noise.
    """
    counts = np.asarray(counts, dtype=float)
    if counts.ndim == 3:
        counts = counts.mean(axis=0)
    if counts.shape != calibration.shape:
        raise CalibrationError(f"equilibration frames have shape {counts.shape}, expected {calibration.shape}")
    plain = Calibration(calibration.gain_pa_per_count, calibration.offset_counts, np.ones(calibration.shape))
    p = plain.pressure_pa(counts)
    mean = float(p.mean())
    if not math.isfinite(mean) or mean <= 0 or (p <= 0.1 * mean).any():
        raise CalibrationError("equilibration needs every element loaded: some read no pressure "
                               f"(mean {mean:.0f} Pa, lowest {float(p.min()):.0f} Pa); apply a uniform load")
    return mean / p
