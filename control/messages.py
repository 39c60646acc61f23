"""Typed commands into the control loop and events out of it.

Commands and events are small frozen dataclasses that cross the process boundary by pickling; the loop
dispatches on their type, never on strings. Every command the loop does not simply carry out is answered
with an event naming it: :class:`CommandApplied` for settings and tare, :class:`CommandRefused` with the
reason for a refusal, so the console never matches on message text.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

from control.config import ImpedanceGains, RampSettings
from hardware.interfaces import Phase

Vec3 = tuple[float, float, float]


class FaultKind(enum.IntEnum):
    NONE = 0
    FORCE_CEILING = 1
    PRESSURE_CEILING = 2
    INDENTATION_CEILING = 3
    VELOCITY_LIMIT = 4
    WORKSPACE = 5
    SENSOR_STALE = 6
    MASTER_STALE = 7
    SLAVE_STALE = 8
    ESTOP = 9
    CONTROLLER = 10  # the controller process itself (crash, stall) as seen from outside
    SENSOR_IMPLAUSIBLE = 11  # the tactile array reads what no contact can give (far below zero)
    TISSUE_TOO_STIFF = 12  # stiffer than force control is stable for (SafetyLimits.tissue_stiffness_max_N_m)
    SLAVE_IMPLAUSIBLE = 13  # the robot's position reading jumps where no robot can go


class Source(enum.IntEnum):
    OPERATOR = 0  # GUI or keyboard
    MASTER = 1  # the switch on the master device
    CONTROLLER = 2  # the palpation state machine or the safety supervisor


# ---- commands ---------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SetSz:
    """S_z = 1 (position control in z) or 0 (force control: starts the Fig. 4 ramp for this area)."""

    position_control: bool
    source: Source = Source.OPERATOR


@dataclass(frozen=True, slots=True)
class AbortRegion:
    reason: str = "aborted by the operator"


@dataclass(frozen=True, slots=True)
class EStop:
    reason: str = "emergency stop pressed"


@dataclass(frozen=True, slots=True)
class ClearFault:
    pass


@dataclass(frozen=True, slots=True)
class Tare:
    pass


@dataclass(frozen=True, slots=True)
class SetRamp:
    ramp: RampSettings


@dataclass(frozen=True, slots=True)
class SetGains:
    gains: ImpedanceGains


@dataclass(frozen=True, slots=True)
class Jog:
    """Move X_d by a delta (console jog when no master device is attached)."""

    delta_m: Vec3


@dataclass(frozen=True, slots=True)
class CancelJog:
    """Stop a jog under way where X_d is now (what is left of it is dropped)."""


@dataclass(frozen=True, slots=True)
class SetRegion:
    """Name the area being palpated next (the index used in records and stitching)."""

    index: int


Command = SetSz | AbortRegion | EStop | ClearFault | Tare | SetRamp | SetGains | Jog | CancelJog | SetRegion


# ---- events -----------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class LevelRecord:
    """One recorded force level of one region (the data behind Figs. 6-11)."""

    region: int
    level: int
    t_s: float
    force_desired_N: float
    force_measured_N: float
    rmse_N: float
    settle_time_s: float
    tsi_position_m: Vec3
    indentation_m: float  # TSI indentation depth: mean dL over elements in contact (NaN if none)
    pressure_pa: np.ndarray  # (4, 15), mean over the settle window
    pressure_std_pa: np.ndarray  # (4, 15), standard deviation of the frames over the settle window (NaN: one frame)
    window_frames: int  # frames averaged over the settle window
    element_force_N: np.ndarray  # (4, 15)
    onset_height_m: np.ndarray  # (4, 15) TSI height at each element's contact onset (NaN: never)
    L0_m: np.ndarray  # (4, 15) initial tissue thickness under each element
    dL_m: np.ndarray  # (4, 15) indentation of each element
    stiffness_pa: np.ndarray  # (4, 15) Eq. 1, NaN where not in contact


@dataclass(frozen=True, slots=True)
class SzChanged:
    t_s: float
    sz: int
    source: Source


@dataclass(frozen=True, slots=True)
class PhaseChanged:
    t_s: float
    phase: Phase
    level: int
    n_levels: int


@dataclass(frozen=True, slots=True)
class LevelRecorded:
    t_s: float
    record: LevelRecord


@dataclass(frozen=True, slots=True)
class LevelTimedOut:
    t_s: float
    region: int
    level: int
    force_desired_N: float
    rmse_N: float
    message: str


@dataclass(frozen=True, slots=True)
class RegionDone:
    t_s: float
    region: int
    n_levels: int  # levels recorded
    # the force of the last level when the ramp stopped short of F_max because the next level would have pressed
    # an element past the pressure ceiling or the face past the indentation ceiling (NaN: the ramp reached F_max)
    capped_N: float = math.nan
    capped_why: str = ""  # which, in words (control.palpation's CAPPED_BY_...)

    def cap_text(self) -> str:
        """"capped at F N: why", or "" where the ramp reached F_max (the session's event text says it so)."""
        return f"capped at {self.capped_N:g} N: {self.capped_why}" if self.capped_N == self.capped_N else ""


@dataclass(frozen=True, slots=True)
class RegionAborted:
    t_s: float
    region: int
    reason: str


@dataclass(frozen=True, slots=True)
class FaultRaised:
    t_s: float
    kind: FaultKind
    message: str


@dataclass(frozen=True, slots=True)
class FaultCleared:
    t_s: float
    kind: FaultKind


@dataclass(frozen=True, slots=True)
class CommandApplied:
    """The loop took a command that changes its settings or the sensor (ramp, gains, next region, tare)."""

    t_s: float
    command: Command
    message: str  # what changed, in words, for the messages pane


@dataclass(frozen=True, slots=True)
class CommandRefused:
    """The loop refused a command; nothing changed. A refused ``SetSz`` means S_z stays as it was."""

    t_s: float
    command: Command
    reason: str

    @property
    def command_name(self) -> str:
        return type(self.command).__name__


@dataclass(frozen=True, slots=True)
class Notice:
    """Anything else the operator should read in the messages pane (a display that fell behind...)."""

    t_s: float
    message: str
    level: str = field(default="info")  # info | warning


Event = (SzChanged | PhaseChanged | LevelRecorded | LevelTimedOut | RegionDone | RegionAborted | FaultRaised
         | FaultCleared | CommandApplied | CommandRefused | Notice)
