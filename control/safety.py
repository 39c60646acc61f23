"""The safety supervisor: limits and watchdogs checked every tick, before anything else acts.

A fault latches until the operator clears it, and it is cleared only once its cause is gone. Each fault
kind comes with the safe reaction the loop applies while it is latched:

* retract: lift the probe off the tissue at the retract speed, then hold. Used when pushing on is the
  danger (force, pressure and indentation ceilings) or when the loop can no longer see what it pushes on
  (stale sensor or master data). Moving up, away from the tissue, is safe with a live slave.
* hold: stop where it is. Used when motion itself is the problem (e-stop, velocity, workspace) or when the
  slave cannot be commanded reliably (stale slave data).
"""

from __future__ import annotations

import math

from control.config import SafetyLimits
from control.messages import FaultKind

RETRACT_FAULTS = frozenset({
    FaultKind.FORCE_CEILING, FaultKind.PRESSURE_CEILING, FaultKind.INDENTATION_CEILING,
    FaultKind.SENSOR_STALE, FaultKind.MASTER_STALE, FaultKind.SENSOR_IMPLAUSIBLE, FaultKind.TISSUE_TOO_STIFF,
})
# What the force the tissue pushes with may be short of the ceiling where the loop stops the probe descending:
# the robot's own overshoot as its reference stops, and the array's noise
FORCE_RESERVE_N = 0.2


def blind_seek_depth_m(limits: SafetyLimits) -> float:
    """How deep a seek may go before the array confirms contact: where tissue of the stiffest kind force control
    accepts, beginning just below the seek's start, would push back the ceiling less the reserve. An array that
    reads nothing cannot tell tissue from air (a dead one reads air all the way down), so no deeper than this
    is safe whatever the array says; the probe must begin its seek within it of the tissue."""
    return (limits.force_ceiling_N - FORCE_RESERVE_N) / limits.tissue_stiffness_max_N_m
# A tared element cannot read far below zero: no contact pulls on the array, and its zero moves by less than
# this share of full scale within a session (rest offsets of capacitive arrays move about 2 % of full scale
# between days, so an array is tared each session). Below it, less its own noise's five standard deviations,
# the element is damaged or drifting, and what the array says of contact is void: an array drifting 15-19 kPa
# down, inside the 20 % this once was, hid 3.4-4.6 N from the force loop.
IMPLAUSIBLE_NEGATIVE_FRACTION = 0.03
# ... and before its noise is measured (the first frames after start-up), this share of full scale
UNMEASURED_NEGATIVE_FRACTION = 0.2

# Before the first reading of a device arrives, allow this long after start-up.
STARTUP_GRACE_S = 1.0


class SafetySupervisor:
    def __init__(self, limits: SafetyLimits):
        self.limits = limits
        self.fault = FaultKind.NONE
        self.message = ""

    @property
    def faulted(self) -> bool:
        return self.fault != FaultKind.NONE

    @property
    def retract(self) -> bool:
        return self.fault in RETRACT_FAULTS

    def latch(self, kind: FaultKind, message: str) -> bool:
        """Latch a fault; the first one wins until cleared. Returns True if this call latched it."""
        if self.faulted:
            return False
        self.fault, self.message = kind, message
        return True

    def check(
        self,
        *,
        uptime_s: float,
        x_ref_m,
        v_ref_m_s,
        force_N: float,
        max_pressure_pa: float,
        lowest_pa: float,
        negative_allowance_pa: float,
        saturated_elements: int,
        indentation_m: float,
        sensor_age_s: float,
        sensor_repeats: int,
        contradiction: str | None,
        too_stiff: str | None,
        position_problem: str | None,
        master_age_s: float | None,
        slave_age_s: float,
    ) -> tuple[FaultKind, str] | None:
        """Return the first violated limit as (kind, explanation), or None. Does not latch."""
        lim = self.limits
        grace = uptime_s < STARTUP_GRACE_S
        if not (slave_age_s <= lim.slave_timeout_s) and not (grace and math.isinf(slave_age_s)):
            return FaultKind.SLAVE_STALE, _stale("robot", slave_age_s, lim.slave_timeout_s,
                                                 "The robot was told to hold; check its controller and cable.")
        if position_problem is not None:
            return FaultKind.SLAVE_IMPLAUSIBLE, position_problem
        if not (sensor_age_s <= lim.sensor_timeout_s) and not (grace and math.isinf(sensor_age_s)):
            action = "The probe was lifted off the tissue because the force is unknown."
            if sensor_repeats and not math.isinf(sensor_age_s):
                return FaultKind.SENSOR_STALE, (
                    f"Frozen tactile array: its last {sensor_repeats + 1} frames ({sensor_age_s * 1e3:.0f} ms) were "
                    f"identical, element by element, as no array with noise gives (limit "
                    f"{lim.sensor_timeout_s * 1e3:.0f} ms). {action}")
            return FaultKind.SENSOR_STALE, _stale("tactile sensor", sensor_age_s, lim.sensor_timeout_s, action)
        if master_age_s is not None and not (master_age_s <= lim.master_timeout_s) \
                and not (grace and math.isinf(master_age_s)):
            return FaultKind.MASTER_STALE, _stale("master device", master_age_s, lim.master_timeout_s,
                                                  "The probe was lifted off the tissue and holds there.")
        if not force_N <= lim.force_ceiling_N:  # NaN included: an unknown force is not a safe one
            return FaultKind.FORCE_CEILING, (
                f"Force ceiling exceeded: the tactile sensor measured {force_N:.2f} N, above the "
                f"{lim.force_ceiling_N:.2f} N limit. The probe was lifted off the tissue.")
        if not lowest_pa >= -negative_allowance_pa:
            return FaultKind.SENSOR_IMPLAUSIBLE, (
                f"Implausible tactile data: an element read {lowest_pa / 1e3:.1f} kPa, far below zero (a tared "
                f"element stays above {-negative_allowance_pa / 1e3:.1f} kPa); what the array says of contact "
                f"cannot be trusted. The probe was lifted off the tissue.")
        if saturated_elements:  # the force is at least what is read, and could be any amount more
            return FaultKind.FORCE_CEILING, (
                f"Force unknown: {saturated_elements} tactile element(s) saturated, so the force is at least "
                f"the {force_N:.2f} N measured and may be far more. The probe was lifted off the tissue.")
        if not max_pressure_pa <= lim.element_pressure_ceiling_pa:
            return FaultKind.PRESSURE_CEILING, (
                f"Pressure ceiling exceeded: one element read {max_pressure_pa / 1e3:.1f} kPa, above the "
                f"{lim.element_pressure_ceiling_pa / 1e3:.1f} kPa limit (the sensor saturates there). "
                f"The probe was lifted off the tissue.")
        if indentation_m > lim.indentation_ceiling_m:
            return FaultKind.INDENTATION_CEILING, (
                f"Indentation ceiling exceeded: the probe is {indentation_m * 1e3:.1f} mm into the tissue, "
                f"deeper than the {lim.indentation_ceiling_m * 1e3:.1f} mm limit. The probe was lifted off the tissue.")
        if contradiction is not None:
            return FaultKind.SENSOR_IMPLAUSIBLE, contradiction
        if too_stiff is not None:
            return FaultKind.TISSUE_TOO_STIFF, too_stiff
        speed = math.sqrt(v_ref_m_s[0] ** 2 + v_ref_m_s[1] ** 2 + v_ref_m_s[2] ** 2)
        if speed > lim.velocity_limit_m_s:
            return FaultKind.VELOCITY_LIMIT, (
                f"Velocity limit exceeded: the reference moved at {speed * 1e3:.0f} mm/s, above the "
                f"{lim.velocity_limit_m_s * 1e3:.0f} mm/s limit. The robot was stopped where it is.")
        return self.outside_workspace(x_ref_m)

    def pressing_too_hard(self, force_N: float, max_pressure_pa: float, indentation_m: float) -> str | None:
        """What of the probe's push passes a ceiling, as a clause ("the force 12.3 N is over the 12 N
        ceiling"), or None."""
        lim = self.limits
        if force_N > lim.force_ceiling_N:
            return f"The force {force_N:.2f} N is over the {lim.force_ceiling_N:.2f} N ceiling"
        if max_pressure_pa > lim.element_pressure_ceiling_pa:
            return (f"An element reads {max_pressure_pa / 1e3:.1f} kPa, over the "
                    f"{lim.element_pressure_ceiling_pa / 1e3:.1f} kPa ceiling")
        if indentation_m > lim.indentation_ceiling_m:
            return (f"The probe is {indentation_m * 1e3:.1f} mm into the tissue, over the "
                    f"{lim.indentation_ceiling_m * 1e3:.1f} mm ceiling")
        return None

    def outside_workspace(self, x_ref_m) -> tuple[FaultKind, str] | None:
        lim = self.limits
        for i, axis in enumerate("xyz"):
            if not (lim.workspace_min_m[i] <= x_ref_m[i] <= lim.workspace_max_m[i]):
                return FaultKind.WORKSPACE, (
                    f"Workspace limit: the reference {axis} = {x_ref_m[i] * 1e3:.1f} mm left the allowed "
                    f"{lim.workspace_min_m[i] * 1e3:.1f} to {lim.workspace_max_m[i] * 1e3:.1f} mm. "
                    f"The robot was stopped where it is.")
        return None

    def clear(self, still_violated: tuple[FaultKind, str] | None) -> str | None:
        """Clear the latched fault unless its cause persists; returns the refusal reason, if any."""
        if not self.faulted:
            return "there is no fault to clear"
        if still_violated is not None and still_violated[0] == self.fault:
            return f"the cause persists: {still_violated[1]}"
        self.fault, self.message = FaultKind.NONE, ""
        return None


def _stale(device: str, age_s: float, limit_s: float, action: str) -> str:
    seen = "has sent nothing since start-up" if math.isinf(age_s) else f"last reported {age_s * 1e3:.0f} ms ago"
    return f"Stale data: the {device} {seen} (limit {limit_s * 1e3:.0f} ms). {action}"
