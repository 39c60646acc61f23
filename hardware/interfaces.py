"""Abstract device interfaces: the only way the control loop talks to hardware.

Conventions (the one place they are written down):

* SI units everywhere: m, N, Pa, s.
* Tissue frame: x along the phantom's length, y across it, z up from the table.
* The TSI pose is the position of the centre of its sensing face in the tissue frame; the face is
  level and its 15-element axis runs along y, its 4-element axis along x.
* Every tactile array is shaped ``(rows, cols) == (4, 15)``: row ``i`` is along x, column ``j`` along
  y. Element ``(i, j)`` is centred at ``((i - (rows-1)/2) * pitch, (j - (cols-1)/2) * pitch)`` from
  the TSI centre (:func:`tissue.face.element_offsets_m`, the one place the rule is written).
* Every reading carries the host-clock time it describes (``t_s``, the device timestamp mapped to
  the host's monotonic clock) and the device's sequence number, so the loop always knows its age.

Devices are polled: :meth:`Device.poll` does whatever non-blocking I/O (or, for a simulator,
physics) brings the device up to ``now_s`` and must return within a small fraction of a tick.
``latest()`` then returns the newest reading, or ``None`` if there has never been one.
"""

from __future__ import annotations

import enum
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from tissue.face import Face

Vec3 = tuple[float, float, float]


class DeviceError(RuntimeError):
    """A device failed in a way the caller should report (open failed, unplugged, bad frame)."""


def finite_vec3(what: str, value) -> Vec3:
    """``value`` as three finite floats, or a DeviceError "<what> must be three (finite) numbers, got ...":
    a reference that reaches the robot must never be NaN, inf or the wrong shape."""
    try:
        items = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise DeviceError(f"{what} must be three numbers, got {value!r}") from None
    if len(items) != 3 or not all(math.isfinite(v) for v in items):
        raise DeviceError(f"{what} must be three finite numbers, got {value!r}")
    return items  # type: ignore[return-value]


class ConnectionState(enum.IntEnum):
    DISCONNECTED = 0
    CONNECTING = 1
    CONNECTED = 2
    LOST = 3  # was connected, stopped answering or was unplugged


class Phase(enum.IntEnum):
    """States of the Fig. 4 flowchart as the operator sees them."""

    APPROACH = 0  # S_z = 1: the operator positions the TSI under position control
    SEEK_CONTACT = 1  # S_z = 0: force control at F_min, no element in contact yet
    SETTLING = 2  # S_z = 0: at level k, waiting for RMSE(F_d - F_ts) < eps
    RETRACT = 3  # S_z = 1: lifting the TSI off the tissue after the ramp, an abort or a fault
    DONE = 4  # region done: the ramp reached F_max; the operator may move to the next area
    HOLD = 5  # a fault latched a safe hold; cleared only by the operator

    @property
    def idle(self) -> bool:
        """The operator owns the z axis: the TSI may be moved and settings changed (between areas)."""
        return self in (Phase.APPROACH, Phase.DONE)


@dataclass(frozen=True, slots=True)
class TactileConstraints(Face):
    """A tactile array: its face's geometry (:class:`tissue.face.Face`) and what its electronics deliver."""

    full_scale_pa: float = 100e3
    frame_rate_hz: float = 100.0
    latency_s: float = 0.010  # from a frame's sampling instant to its being readable: the force loop's lag
    # How far the array's elastomer cover spreads an element's load sideways, as the array is specified (0: not
    # stated). Sessions record it as the array's calibration, and the analysis's physics takes it from there.
    cover_spread_m: float = 0.0


@dataclass(frozen=True, slots=True)
class TactileFrame:
    seq: int
    t_s: float
    pressure_pa: np.ndarray  # (rows, cols), calibrated and tared, >= 0 apart from noise
    # (rows, cols) bool: the element's converter is at its limit, so the true load is at least what it reads
    # and may be far more; None: the device cannot tell
    saturated: np.ndarray | None = None


# An unloaded capacitive element reads its baseline, a few % of full scale (1 % in the simulated array's
# defaults); a reading beyond this fraction is a load, and taking it as zero would hide that load.
TARE_MAX_FRACTION = 0.1


def tare_problem(untared_pa: np.ndarray, saturated: np.ndarray | None, full_scale_pa: float) -> str | None:
    """Why a frame cannot serve as the zero of an unloaded array (None: it can)."""
    if saturated is not None and saturated.any():
        i, j = np.argwhere(saturated)[0]
        return (f"{int(saturated.sum())} element(s) saturated (first: row {i}, column {j}); "
                f"an unloaded array cannot saturate")
    top = float(np.max(np.abs(untared_pa))) if untared_pa.size else 0.0
    if not top <= TARE_MAX_FRACTION * full_scale_pa:
        return (f"an element reads {top / 1e3:.1f} kPa, more than {TARE_MAX_FRACTION:.0%} of full scale "
                f"({full_scale_pa / 1e3:.0f} kPa): the array is loaded")
    return None


@dataclass(frozen=True, slots=True)
class SlaveConstraints:
    workspace_min_m: Vec3 = (-0.05, -0.05, 0.0)
    workspace_max_m: Vec3 = (0.15, 0.10, 0.12)
    max_speed_m_s: float = 0.1
    rate_hz: float = 1000.0


@dataclass(frozen=True, slots=True)
class SlaveState:
    seq: int
    t_s: float
    position_m: Vec3  # TSI face centre, from the robot's kinematics
    velocity_m_s: Vec3


@dataclass(frozen=True, slots=True)
class MasterConstraints:
    rate_hz: float = 1000.0
    has_sz_switch: bool = True


@dataclass(frozen=True, slots=True)
class MasterState:
    seq: int
    t_s: float
    position_m: Vec3  # in the master's own frame; the loop maps it to X_d
    sz_switch: bool | None = None  # True = position control; None = the device has no switch


@dataclass(slots=True)  # not frozen: built every tick, and frozen dataclasses are several times slower to build
class MasterFeedback:
    """What the operator is told back through the master each tick (a haptic master may render it)."""

    t_s: float
    phase: Phase
    region_done: bool
    force_measured_N: float
    faulted: bool


class Device(ABC):
    name: str = "device"

    @property
    @abstractmethod
    def connection(self) -> ConnectionState: ...

    @abstractmethod
    def open(self) -> None:
        """Connect; raise DeviceError with a sentence a user can act on if it cannot."""

    @abstractmethod
    def close(self) -> None:
        """Disconnect and release every OS resource; safe to call twice."""

    @abstractmethod
    def poll(self, now_s: float) -> None:
        """Non-blocking I/O (or simulation) up to ``now_s``; never blocks for long."""


class TactileSensor(Device):
    constraints: TactileConstraints

    @abstractmethod
    def latest(self) -> TactileFrame | None: ...

    @abstractmethod
    def tare(self) -> None:
        """Take the current unloaded reading as zero for every element.

        Raises DeviceError, changing nothing, when that reading is not one an unloaded array gives
        (:func:`tare_problem`) or there is none yet."""


class SlaveManipulator(Device):
    constraints: SlaveConstraints

    @abstractmethod
    def latest(self) -> SlaveState | None: ...

    @abstractmethod
    def command(self, position_m: Vec3, velocity_m_s: Vec3, now_s: float) -> None:
        """Send the reference pose for the robot's inner position loop."""

    @abstractmethod
    def hold(self, now_s: float) -> None:
        """Stop where it is (brakes or zero-velocity hold); used by the safety supervisor."""


class MasterDevice(Device):
    constraints: MasterConstraints

    @abstractmethod
    def latest(self) -> MasterState | None: ...

    def feedback(self, fb: MasterFeedback) -> None:
        """Tell the operator's side what the slave is doing; devices without a display ignore it."""
