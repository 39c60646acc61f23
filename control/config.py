"""Settings of the control core, validated on construction (the vocabulary is :mod:`hardware.settings`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

from hardware.settings import ConfigError, Settings, Vec3, bounded, positive, vec3

# The stiffest environment the law's own integration must stay stable against at one step: the whole 8 x 30 mm
# face on 1 mm of a 400 kPa silicone over the table (E A / h), beyond any tissue the console palpates.
ENVIRONMENT_STIFFNESS_MAX_N_M = 1e5
RATE_HZ_RANGE = (100.0, 5000.0)  # the paper's loop runs at 1 kHz; below 100 Hz it lags the 10 ms sensor frames

# The force loop closes through the tactile array, not through the 1 ms step: the tissue's push reaches the
# law with each frame, a latency after its sample, and the robot's own position loop lags the reference.
# :func:`force_loop_stiffness_limit_N_m` takes the array's frame rate and latency from the sensor (the
# defaults here are the simulated array's, hardware/sim/settings.py) and assumes the robot's inner loop is no
# slower than the simulated rig's (a second order of 20 Hz, damping ratio 0.7): a slower robot needs more
# damping than the rule asks.
DEFAULT_FRAME_RATE_HZ, DEFAULT_LATENCY_S = 100.0, 0.010
ROBOT_BANDWIDTH_HZ, ROBOT_DAMPING_RATIO = 20.0, 0.7
# At 45 degrees of phase margin a force step overshoots by about a quarter and the loop has no limit cycle;
# the default gains on the simulated rig limit-cycled from 10 kN/m (3.6 kN/m is where this rule's margin ends).
PHASE_MARGIN_DEG = 45.0


@dataclass(frozen=True)
class ImpedanceGains(Settings):
    """M_d, B_d, K_d of Eq. 2, diagonal, per tissue-frame axis (x, y, z)."""

    # z, the force-controlled axis, is damped for tissue up to SafetyLimits' 5 kN/m through the array's lag
    # (force_loop_stiffness_limit_N_m: 5.3 kN/m), and stiff enough in position control to stay critically
    # damped (B^2 = 4 M K) so it follows the operator as briskly as x and y do
    mass_kg: Vec3 = (1.0, 1.0, 0.5)
    damping_N_s_m: Vec3 = (80.0, 80.0, 200.0)
    stiffness_N_m: Vec3 = (1600.0, 1600.0, 20000.0)

    def __post_init__(self):
        object.__setattr__(self, "mass_kg", vec3("mass_kg", self.mass_kg, is_positive=True))
        object.__setattr__(self, "damping_N_s_m", vec3("damping_N_s_m", self.damping_N_s_m, is_positive=True))
        object.__setattr__(self, "stiffness_N_m", vec3("stiffness_N_m", self.stiffness_N_m, is_positive=True))


@dataclass(frozen=True)
class RampSettings(Settings):
    """The Fig. 4 force ramp: F_d from F_min to F_max in steps of dF, each level settled to RMSE < eps."""

    force_min_N: float = 1.0
    force_max_N: float = 7.0
    force_step_N: float = 1.0
    rmse_threshold_N: float = 0.05
    settle_window_s: float = 0.3
    min_settle_s: float = 0.5
    level_timeout_s: float = 8.0

    def __post_init__(self):
        for name in ("force_min_N", "force_max_N", "force_step_N", "rmse_threshold_N", "settle_window_s",
                     "min_settle_s", "level_timeout_s"):
            object.__setattr__(self, name, positive(name, getattr(self, name)))
        # each bounded so that a slip cannot make a ramp that never ends (1e300 s was accepted)
        for name, top, why in (("rmse_threshold_N", 2.0, "an eps that large settles on anything"),
                               ("settle_window_s", 2.0, "the paper's eps holds over a fraction of a second"),
                               ("min_settle_s", 60.0, "a level is recorded within seconds"),
                               ("level_timeout_s", 120.0, "a level that has not settled in two minutes will not")):
            bounded(name, getattr(self, name), 0.0, top, why)
        if self.force_max_N < self.force_min_N:
            raise ConfigError("force_max_N",
                              f"must be >= force_min_N ({self.force_min_N:g} N), got {self.force_max_N:g}")
        if self.force_step_N > self.force_max_N - self.force_min_N and self.force_max_N > self.force_min_N:
            raise ConfigError("force_step_N", f"{self.force_step_N:g} N is larger than the ramp span "
                              f"{self.force_max_N - self.force_min_N:g} N")
        if self.n_levels > 200:
            raise ConfigError("force_step_N", f"gives {self.n_levels} levels; at most 200 are allowed")
        if self.level_timeout_s <= self.min_settle_s:
            raise ConfigError("level_timeout_s", f"must exceed min_settle_s ({self.min_settle_s:g} s)")

    @cached_property  # read on every control tick; the settings are frozen
    def n_levels(self) -> int:
        span = self.force_max_N - self.force_min_N
        whole = int(math.floor(span / self.force_step_N + 1e-9)) + 1
        return whole + (0 if _is_multiple(span, self.force_step_N) else 1)

    def level_force_N(self, k: int) -> float:
        """Level k's desired force; the last level is always exactly F_max."""
        return min(self.force_min_N + k * self.force_step_N, self.force_max_N)


def _is_multiple(span: float, step: float) -> bool:
    q = span / step
    return abs(q - round(q)) < 1e-9


@dataclass(frozen=True)
class ContactSettings(Settings):
    """How contact, L0 and dL are found from the data (see control/analysis.py)."""

    onset_threshold_pa: float = 300.0
    confirm_threshold_pa: float = 900.0
    min_indentation_m: float = 0.2e-3
    table_height_m: float = 0.0
    retract_height_m: float = 8e-3
    retract_speed_m_s: float = 0.02
    max_seek_depth_m: float = 0.04
    pose_history_s: float = 0.5

    def __post_init__(self):
        for name in ("onset_threshold_pa", "confirm_threshold_pa", "min_indentation_m", "retract_height_m",
                     "retract_speed_m_s", "max_seek_depth_m", "pose_history_s"):
            object.__setattr__(self, name, positive(name, getattr(self, name)))
        for name, top, why in (("onset_threshold_pa", 50e3, "half the array's full scale"),
                               ("confirm_threshold_pa", 95e3, "the element pressure ceiling"),
                               ("min_indentation_m", 5e-3, "Eq. 1 would be blank for most of a ramp"),
                               ("retract_height_m", 0.05, "deeper than any palpated tissue is thick"),
                               ("max_seek_depth_m", 0.1, "the bench robot's height over the table"),
                               # the loop keeps this much of the robot's path at 1 kHz (1e6 s was 7.45 GiB)
                               ("pose_history_s", 5.0, "frames come within a few tens of ms")):
            bounded(name, getattr(self, name), 0.0, top, why)
        if self.pose_history_s < 0.05:
            raise ConfigError("pose_history_s", f"must be at least 0.05 s to hold a late frame's pose, got "
                                                f"{self.pose_history_s:g}")
        object.__setattr__(self, "table_height_m", bounded("table_height_m", self.table_height_m, -1.0, 1.0,
                                                           "a bench robot's reach, in m"))
        if self.confirm_threshold_pa <= self.onset_threshold_pa:
            raise ConfigError("confirm_threshold_pa",
                              f"must exceed onset_threshold_pa ({self.onset_threshold_pa:g} Pa)")


@dataclass(frozen=True)
class SafetyLimits(Settings):
    """The supervisor's limits; each bounded so a typing slip cannot switch a limit off (the bounds say why)."""

    force_ceiling_N: float = 12.0
    element_pressure_ceiling_pa: float = 95e3
    indentation_ceiling_m: float = 0.016
    velocity_limit_m_s: float = 0.1
    workspace_min_m: Vec3 = (-0.02, -0.02, 0.0)
    workspace_max_m: Vec3 = (0.10, 0.06, 0.10)
    sensor_timeout_s: float = 0.06
    master_timeout_s: float = 0.05
    slave_timeout_s: float = 0.01
    # The stiffest tissue under the whole face (N per m of indentation) the console palpates: the force loop
    # must be stable against it, the force is predicted with it between frames, and tissue found stiffer
    # stops the ramp. The paper's 20 kPa phantoms give 0.4-1 kN/m at 1-7 N; silicone of 200 kPa, 2-5 kN/m.
    tissue_stiffness_max_N_m: float = 5000.0
    # The fastest the probe may descend near tissue (below the highest surface touched in this session plus the
    # retract height, or anywhere before it has touched any): a frame tells of contact 10-20 ms late and a robot
    # brakes at a few m/s^2, so at 250 mm/s a probe meeting tissue went 6-10 mm further before it could stop.
    approach_speed_m_s: float = 0.02

    def __post_init__(self):
        object.__setattr__(self, "approach_speed_m_s", bounded(
            "approach_speed_m_s", self.approach_speed_m_s, 1e-3, 0.05,
            "faster, a probe meeting the stiffest tissue passes the ceilings before a frame tells"))
        object.__setattr__(self, "tissue_stiffness_max_N_m", bounded(
            "tissue_stiffness_max_N_m", self.tissue_stiffness_max_N_m, 100.0, ENVIRONMENT_STIFFNESS_MAX_N_M,
            "from the softest tissue to the face on 1 mm of stiff silicone"))
        for name, top, why in (
                ("force_ceiling_N", 30.0, "the TSI's full scale is 95 kPa over 240 mm^2, 23 N"),
                ("element_pressure_ceiling_pa", 1e6, "a capacitive element saturates far below 1 MPa"),
                ("indentation_ceiling_m", 0.05, "deeper than any palpated tissue is thick"),
                ("velocity_limit_m_s", 0.5, "a palpation robot near tissue"),
                ("sensor_timeout_s", 1.0, "a second without data is a lost device"),
                ("master_timeout_s", 1.0, "a second without data is a lost device"),
                ("slave_timeout_s", 1.0, "a second without data is a lost device")):
            value = positive(name, getattr(self, name))
            object.__setattr__(self, name, bounded(name, value, 0.0, top, why))
        lo = vec3("workspace_min_m", self.workspace_min_m)
        hi = vec3("workspace_max_m", self.workspace_max_m)
        for i, axis in enumerate("xyz"):
            for key, v in (("workspace_min_m", lo[i]), ("workspace_max_m", hi[i])):
                bounded(f"{key}[{i}]", v, -1.0, 1.0, "a bench robot's reach, in m")
            if hi[i] <= lo[i]:
                raise ConfigError("workspace_max_m",
                                  f"{axis} upper bound {hi[i]:g} m must exceed lower bound {lo[i]:g} m")
        object.__setattr__(self, "workspace_min_m", lo)
        object.__setattr__(self, "workspace_max_m", hi)


@dataclass(frozen=True)
class MasterMapping(Settings):
    """X_d = scale * master position + offset; the offset is re-clutched whenever an axis is handed back to
    the operator (start-up, end of a ramp, cleared fault) so the robot never jumps to the master."""

    scale: float = 1.0
    jog_speed_m_s: float = 0.01
    derivative_filter_s: float = 0.005

    def __post_init__(self):
        object.__setattr__(self, "scale", positive("scale", self.scale))
        object.__setattr__(self, "jog_speed_m_s", positive("jog_speed_m_s", self.jog_speed_m_s))
        object.__setattr__(self, "derivative_filter_s", positive("derivative_filter_s", self.derivative_filter_s))
        bounded("scale", self.scale, 0.0, 100.0, "a master moved a millimetre moves the probe at most 10 cm")
        bounded("derivative_filter_s", self.derivative_filter_s, 0.0, 1.0, "a slower filter is no velocity")


def force_loop_stiffness_limit_N_m(mass_kg: float, damping_N_s_m: float, frame_rate_hz: float, latency_s: float,
                                   dt_s: float) -> float:
    """The stiffest tissue the force loop on z (S_z = 0: M x'' + B x' = F_d - F_e) stays stable against with
    PHASE_MARGIN_DEG of margin, the tissue's force read by an array at ``frame_rate_hz`` (held half a frame
    on average), ``latency_s`` after its sample, through a robot as ROBOT_BANDWIDTH_HZ assumes, at step dt_s.
    Its open loop is k R(s) e^(-s tau) / (s (M s + B)); the phase falls monotonically with frequency, so the
    frequency where the margin is left is found by bisection and the stiffness that puts the crossover there
    follows from the gain."""
    wn = 2.0 * math.pi * ROBOT_BANDWIDTH_HZ
    delay = latency_s + 0.5 / frame_rate_hz + dt_s

    def robot(w: float) -> tuple[float, float]:  # (gain, phase lag) of the inner loop
        re, im = 1.0 - (w / wn) ** 2, 2.0 * ROBOT_DAMPING_RATIO * w / wn
        return 1.0 / math.hypot(re, im), math.atan2(im, re)

    def lag(w: float) -> float:
        return 0.5 * math.pi + math.atan(mass_kg * w / damping_N_s_m) + w * delay + robot(w)[1]

    target = math.pi - math.radians(PHASE_MARGIN_DEG)
    lo, hi = 1e-3, 1e5  # rad/s: the lag passes the target between them for any positive M, B and delay
    for _ in range(80):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if lag(mid) < target else (lo, mid)
    return lo * math.hypot(mass_kg * lo, damping_N_s_m) / robot(lo)[0]


def stable_for_environment(gains: ImpedanceGains, dt_s: float, stiffness_N_m: float) -> bool:
    """Whether the impedance law (control/law.py: backward Euler in its own B and K) stays stable against an
    environment of ``stiffness_N_m`` fed back explicitly through F_e at step ``dt_s``, on every axis:
    dt^2 k < 2 (2 M + dt B), Jury's test on the force-control axis (the least damped)."""
    return all(dt_s * dt_s * stiffness_N_m < 2.0 * (2.0 * m + dt_s * b)
               for m, b in zip(gains.mass_kg, gains.damping_N_s_m))


@dataclass(frozen=True)
class ControlConfig(Settings):
    rate_hz: float = 1000.0
    max_step_s: float = 0.002
    gains: ImpedanceGains = field(default_factory=ImpedanceGains)
    ramp: RampSettings = field(default_factory=RampSettings)
    contact: ContactSettings = field(default_factory=ContactSettings)
    safety: SafetyLimits = field(default_factory=SafetyLimits)
    master: MasterMapping = field(default_factory=MasterMapping)

    def __post_init__(self):
        object.__setattr__(self, "rate_hz", bounded("rate_hz", self.rate_hz, *RATE_HZ_RANGE,
                                                     "the paper's loop runs at 1 kHz"))
        object.__setattr__(self, "max_step_s", positive("max_step_s", self.max_step_s))
        if self.max_step_s < 1.0 / self.rate_hz:
            raise ConfigError("max_step_s", f"must be at least one period ({1.0 / self.rate_hz:g} s)")
        if self.max_step_s > 10.0 / self.rate_hz:
            raise ConfigError("max_step_s", f"must be at most ten periods ({10.0 / self.rate_hz:g} s): a longer step "
                                            "moves the reference too far at once")
        if self.safety.workspace_min_m[2] < self.contact.table_height_m:
            raise ConfigError("safety.workspace_min_m",
                              f"its z {self.safety.workspace_min_m[2]:g} m lies below the table "
                              f"(contact.table_height_m {self.contact.table_height_m:g} m): the probe could be driven "
                              f"into it")
        if self.ramp.force_max_N > self.safety.force_ceiling_N:
            raise ConfigError("ramp.force_max_N", f"{self.ramp.force_max_N:g} N is above the force ceiling "
                                                  f"({self.safety.force_ceiling_N:g} N): the last level would trip it")
        if self.safety.approach_speed_m_s > self.safety.velocity_limit_m_s:
            raise ConfigError("safety.approach_speed_m_s", f"{self.safety.approach_speed_m_s:g} m/s is above the "
                                                           f"velocity limit ({self.safety.velocity_limit_m_s:g} m/s)")
        for key, speed in (("contact.retract_speed_m_s", self.contact.retract_speed_m_s),
                           ("master.jog_speed_m_s", self.master.jog_speed_m_s)):
            if speed > self.safety.velocity_limit_m_s:
                raise ConfigError(key, f"{speed:g} m/s is above the velocity limit "
                                       f"({self.safety.velocity_limit_m_s:g} m/s)")
        problem = self.gains_problem(self.gains, DEFAULT_FRAME_RATE_HZ, DEFAULT_LATENCY_S)
        if problem is not None:
            raise ConfigError("gains", problem)

    def gains_problem(self, gains: ImpedanceGains, frame_rate_hz: float, latency_s: float) -> str | None:
        """Why ``gains`` would not be stable here (None: they are): the same rule for the configuration file,
        the loop's own sensor and every change of gains at run time."""
        if not stable_for_environment(gains, self.max_step_s, ENVIRONMENT_STIFFNESS_MAX_N_M):
            return ("the impedance law would go unstable against stiff tissue: need dt^2 k < 2 (2 M + dt B) on "
                    f"every axis with dt = max_step_s and k = {ENVIRONMENT_STIFFNESS_MAX_N_M:g} N/m; raise mass_kg "
                    "or damping_N_s_m")
        limit = force_loop_stiffness_limit_N_m(gains.mass_kg[2], gains.damping_N_s_m[2], frame_rate_hz, latency_s,
                                               self.period_s)
        stiffest = self.safety.tissue_stiffness_max_N_m
        if limit < stiffest:
            return (f"force control on z would be stable only on tissue up to {limit:.0f} N/m, through an array "
                    f"at {frame_rate_hz:g} frames/s and {latency_s * 1e3:g} ms latency, not the "
                    f"safety.tissue_stiffness_max_N_m of {stiffest:.0f} N/m: raise damping_N_s_m[2] (about "
                    f"{gains.damping_N_s_m[2] * stiffest / limit:.0f}) or lower that limit")
        return None

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz


ControlConfig._nested = {"gains": ImpedanceGains, "ramp": RampSettings, "contact": ContactSettings,
                         "safety": SafetyLimits, "master": MasterMapping}
