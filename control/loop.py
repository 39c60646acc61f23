"""The steppable control loop: one call of :meth:`ControlLoop.step` is one 1 kHz tick.

The loop is pure: it does no I/O and reads no clock. A driver (the real-time controller process, the
fast-forward driver, or a test) polls the devices, passes their latest readings and the pending commands
with the tick's time, and applies the returned reference to the slave.

Order within a tick: readings -> commands -> new tactile frame (analysis, Fig. 4 state machine) -> safety
supervisor -> reference (Eq. 2) -> telemetry. The supervisor runs before the law so a violated limit
changes this tick's reference, not the next one's.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from control.analysis import (
    NOISE_MIN_FRAMES,
    ONSET_NOISE_SIGMAS,
    AirNoise,
    PoseHistory,
    StiffnessWindow,
    contact_thresholds,
    element_analysis,
)
from control.config import ControlConfig
from control.law import HybridImpedanceLaw
from control.messages import (
    AbortRegion,
    CancelJog,
    ClearFault,
    Command,
    CommandApplied,
    CommandRefused,
    EStop,
    Event,
    FaultCleared,
    FaultKind,
    FaultRaised,
    Jog,
    Notice,
    SetGains,
    SetRamp,
    SetRegion,
    SetSz,
    Source,
    SzChanged,
    Tare,
)
from control.palpation import FRAME_BUFFER, PalpationStateMachine
from control.safety import (
    FORCE_RESERVE_N,
    IMPLAUSIBLE_NEGATIVE_FRACTION,
    RETRACT_FAULTS,
    UNMEASURED_NEGATIVE_FRACTION,
    SafetySupervisor,
)
from control.telemetry import empty_frame, empty_tick
from hardware.interfaces import MasterFeedback, MasterState, Phase, SlaveState, TactileConstraints, TactileFrame, Vec3
from hardware.liveness import RepeatWatch, TravelWatch
from hardware.settings import ConfigError

Z = 2
OVERDUE_FRAME_PERIODS = 3.0  # a frame this many periods old is late: jitter stays well inside it, a stall does not
AT_REST_M_S = 1e-3  # a robot slower than this has come to rest (its stop distance is then reported)
STEP_TOLERANCE_M = 1e-6  # rounding in the law and the pose: far below any step that matters
# Onsets belong to the place they were found: moved sideways by a quarter of the element pitch, an element
# lies over other tissue
TRACKED_DRIFT_PITCHES = 0.25
NOISY_ELEMENT_FACTOR = 2.0  # an element this many times noisier than the face's median is named to the operator
# A reading stamped further ahead of the loop's clock than this comes from a clock or a device that lies: it is
# not fresh (one frame 5 s ahead, taken as "last seen", kept the stale watchdog quiet for 0.5-1 s)
FUTURE_TOLERANCE_S = 2e-3
# How far the probe may go deeper, under force control in contact, without the measured force rising: an array
# that streams zeros, repeats a frame or drifts down reads no more force however deep the probe goes, and the
# force loop pushes on. Tissue stiffens with depth; its creep under a held level moves the probe by a fraction
# of this at most. Less than 1 mm by the time the probe stops: the force loop descends at up to 20-30 mm/s,
# and the lift starts within a tick of the check.
UNEXPLAINED_TRAVEL_M = 0.6e-3
# Near the force ceiling the travel allowed is less: all of it may be force the array hides (a reading that
# drifts down reads the same however deep the probe goes), so it is held to what the stiffest accepted tissue
# turns into this much force over the ceiling at most, with the lift's own overshoot on top (the fault
# campaign: a 15-19 kPa drift at 4 kN/m hid 2.4 N in the 0.6 mm).
HIDDEN_FORCE_N = 0.2
# the force rise that counts as one (besides five standard deviations of the measured force's noise) ...
FORCE_RISE_N = 5e-3
# ... and the least it rises by per metre the probe went deeper: softer tissue than this cannot be palpated at
# all (at the 16 mm indentation ceiling it would push back 0.8 N, less than the 1 N first level; the paper's
# phantom is 0.65 N/mm, a 20 kPa layer under a spring-bed face 0.19 N/mm)
SOFTEST_TISSUE_N_M = 50.0
# ... once the face bears on the tissue with this much: a first touch on a ridge, one element at a time, rises by
# less (the paper's uneven phantom: 10 mN over 0.6 mm at a bump's edge)
ENGAGED_FORCE_N = 0.25
# A force that falls by more than this from one frame to the next while the probe goes no higher is no
# tissue's: it relaxes by millinewtons a frame, and lets go only when the probe lifts
FORCE_DROP_N = 0.25
# More total force than an array's creep and hysteresis leave after a press (3 % and 5 % of a 7 N press): the
# probe presses tissue
RESIDUAL_FORCE_N = 0.5
# the frames the force floor takes the most force of (50 ms at 100 frames/s)
RECENT_FRAMES = 5
# The stiffest tissue the full approach speed is for; on stiffer tissue the probe approaches as much slower
APPROACH_STIFFNESS_N_M = 5000.0
# An array that reads no contact at all while the probe is this far below where it confirmed contact is not
# reading the tissue
DEAD_DEPTH_M = 0.5e-3
# A first contact found less than this below the highest height the array read nothing at was not made from
# air: the array was already pressing (an onset's refinement is good to a tenth of a millimetre; an honest
# start this close to tissue only has to be lifted once)
PRELOAD_ONSET_M = 0.25e-3
# A robot's position reading may stray this far from where its last reading's position and velocity put it,
# plus what the robot can accelerate away in between: an encoder steps micrometres at 1 kHz, and a real
# robot arm accelerates at a few m/s^2
POSITION_JUMP_M = 0.5e-3
ROBOT_ACCEL_MAX_M_S2 = 20.0
# Tissue measured this much stiffer than SafetyLimits.tissue_stiffness_max_N_m stops the probe: beyond the
# force loop's margin (PHASE_MARGIN_DEG leaves it stable to about twice that) and the force floor's prediction
STIFFER_FACTOR = 1.25
# The unloaded reading between areas may wander by this share of full scale from the tare before force control
# is refused until the sensor is tared again: its offset would be taken for force
DRIFT_FRACTION = 0.01
ZERO3: Vec3 = (0.0, 0.0, 0.0)


@dataclass(slots=True)
class StepResult:
    position_ref_m: Vec3  # X_r for the slave's inner position loop
    velocity_ref_m_s: Vec3
    hold: bool  # True: call slave.hold() instead of command() (no valid reference)
    new_frame: bool  # True: loop.frame holds the analysis of a sensor frame first seen this tick
    events: list[Event] = field(default_factory=list)
    feedback: MasterFeedback | None = None
    tare: Tare | None = None  # the driver must tare the tactile sensor now, and say whether it did


class ControlLoop:
    """State: ``tick`` (TICK_DTYPE row, updated in place every step) and ``frame`` (FRAME_DTYPE row)."""

    def __init__(self, config: ControlConfig, sensor: TactileConstraints, has_master: bool = True):
        problem = config.gains_problem(config.gains, sensor.frame_rate_hz, sensor.latency_s)
        if problem is not None:  # the configuration was checked against the default array's timing, not this one's
            raise ConfigError("control.gains", problem)
        if config.ramp.settle_window_s * sensor.frame_rate_hz > FRAME_BUFFER:
            raise ConfigError("control.ramp.settle_window_s", f"{config.ramp.settle_window_s:g} s holds more than "
                                                              f"the {FRAME_BUFFER} frames kept of this array at "
                                                              f"{sensor.frame_rate_hz:g} frames/s")
        self.config = config
        self.sensor = sensor
        self.has_master = has_master
        self.law = HybridImpedanceLaw(config.gains)
        self.safety = SafetySupervisor(config.safety)
        self.sm = PalpationStateMachine(config.ramp, config.contact, sensor.shape, sensor.element_area_m2,
                                        config.safety.element_pressure_ceiling_pa, config.safety.indentation_ceiling_m)
        self.history = PoseHistory(config.contact.pose_history_s, config.rate_hz)
        self._told = PoseHistory(config.contact.pose_history_s, config.rate_hz)  # the references sent, per tick
        self.tick = empty_tick()
        self.frame = empty_frame()
        self._started = False
        self._t0 = 0.0
        self._last = 0.0
        self._ticks = 0
        self._x_s: Vec3 = ZERO3
        self._v_s: Vec3 = ZERO3
        self._slave_seq = -1
        # operator side: X_d = scale * master + offset, with a rate-limited jog folded into the offset
        self._offset = [0.0, 0.0, 0.0]
        self._jog_pending = [0.0, 0.0, 0.0]
        self._master_pos: Vec3 | None = None
        self._master_seq = -1
        self._master_t = 0.0
        self._master_switch: bool | None = None
        self._v_d = [0.0, 0.0, 0.0]
        self._a_d = [0.0, 0.0, 0.0]
        # sensor side
        self._sensor_seq = -1
        self._force_N = 0.0
        self._max_pressure_pa = 0.0
        self._lowest_pa = 0.0  # the element reading furthest below what a tared array can read, and how far it may
        self._lowest_allowance_pa = 0.0
        self._saturated = 0  # elements of the newest frame at their converter's limit
        self._indentation_m = math.nan  # the face's mean indentation over the elements in contact (shown, recorded)
        # What the indentation ceiling is held to: the depth below the first touch, the highest onset tracked, not
        # below the elements' mean onset (an element loaded less than the rest passes its threshold deeper)
        self._deepest_m = math.nan
        # The highest onset of a tracking started afresh because the probe slid sideways while it pressed lightly
        # and still below it: the new tracking's onsets come from where the slide had taken it (the fault campaign:
        # a jog down and sideways, and the ceiling counted from 0.5 mm below the surface)
        self._carried_top_m = math.nan
        self._noise = AirNoise(sensor.shape)
        # until the array's own noise is measured, what a noisy element may read below zero is not known either
        self._negative_allowance_pa = np.full(sensor.shape, UNMEASURED_NEGATIVE_FRACTION * sensor.full_scale_pa)
        self._repeats = RepeatWatch(sensor.shape)  # a frame that repeats the one before says nothing new
        # the rise is set again from the array's noise at each area
        self._travel = TravelWatch(FORCE_RISE_N, SOFTEST_TISSUE_N_M, ENGAGED_FORCE_N)
        # The least the whole face may read under force control: what its zero may have wandered since the tare
        # over every element, less the sum's noise (set at each area). A uniform drift down inside each element's
        # plausibility bound shows in the sum: 15 kPa hid 3.7 N and read -0.6 N in air (the fault campaign).
        self._drift_allowance_N = DRIFT_FRACTION * sensor.full_scale_pa * sensor.rows * sensor.cols \
            * sensor.element_area_m2
        self._sum_allowance_N = self._drift_allowance_N + FORCE_RISE_N
        self._contradiction: str | None = None  # what the array says that the probe's motion belies
        self._previous_contact: tuple[float, float] | None = None  # (force N, face height m) of the last frame
        self._recent_force_N: deque[float] = deque(maxlen=RECENT_FRAMES)  # the newest frames' total force
        self._stiffness = StiffnessWindow()
        self._too_stiff: str | None = None
        self._surface_top_m = math.nan  # the highest contact onset confirmed in this session
        # The first frame read the probe pressing (None before it), and no frame since has read it let go: a probe
        # that starts pressed into tissue is in by a depth no reading can tell, so it may not go deeper until it
        # has been lifted (the fault campaign: started 1.7 mm in, the ceiling counted from there and the probe went
        # 1.9 mm past it)
        self._started_pressed: bool | None = None
        # The array read its first contact as soon as the probe moved down from the highest it read nothing at: it
        # may have been tared pressed into tissue (an array takes its first frame as zero on connection), and the
        # force and depth of that press are hidden from every ceiling (the fault campaign: started 1.7 mm in,
        # the probe was taken 1.9 mm past the indentation ceiling). No deeper until it has been seen clear.
        # ``_clear_z``: before the first contact, the first frame's height or the highest the array read nothing
        # at; inf once it is made.
        self._clear_z = -math.inf
        self._zero_in_doubt = False
        contact = config.contact
        self._thresholds = (np.full(sensor.shape, contact.onset_threshold_pa),
                            np.full(sensor.shape, contact.confirm_threshold_pa))
        self._sent: Vec3 | None = None  # the last reference that left the loop (None: none yet, or held)
        # safe hold
        self._hold_xy: tuple[float, float] = (0.0, 0.0)
        self._lifting = False  # held by a stop-where-it-is fault, and lifting: it pressed over a ceiling
        # a frame older than this is overdue: normally one arrives every period, a latency after its sample
        self._overdue_s = min(config.safety.sensor_timeout_s, OVERDUE_FRAME_PERIODS / sensor.frame_rate_hz)
        self._frame_z = math.nan  # the TSI's height when the newest frame was sampled
        # ... and the force floor's: the higher of that and where the robot was told to be then. A robot pressing
        # into tissue, or descending, stays above its reference, so a reading below it is one that lies low; the
        # floor then went that much deeper (the independent campaign: a reading that carried on descending after
        # the robot had met the tissue, 0.6 mm low, and 0.6 N over the ceiling)
        self._floor_from_z = math.nan
        self._seek_base_N = 0.0  # the force the array read as the seek began (a residual, an offset)
        self._tracked_xy: tuple[float, float] | None = None  # where the contact tracking began (position control)
        self._stopping_from: Vec3 | None = None  # where the robot was when a stop-where-it-is fault latched
        self.stop_distance_m = math.nan  # how far the robot went after the last such fault, once at rest
        self._ages: tuple[float, float, float] = (math.inf, math.inf, math.inf)
        self._seen = [-math.inf, -math.inf, -math.inf]  # newest reading time of sensor, master, slave
        self._slave_t = -math.inf  # the newest robot reading's time
        self._position_problem: str | None = None  # why the robot's position reading cannot be trusted
        self._xd: Vec3 = ZERO3  # this tick's X_d

    # ---- helpers -------------------------------------------------------------------------------------

    def _master_term(self, i: int) -> float:
        return self.config.master.scale * self._master_pos[i] if self._master_pos is not None else 0.0

    def _desired(self) -> Vec3:
        """X_d = scale * master + offset (the offset alone without a master)."""
        off, master = self._offset, self._master_pos
        if master is None:
            return off[0], off[1], off[2]
        k = self.config.master.scale
        return k * master[0] + off[0], k * master[1] + off[1], k * master[2] + off[2]

    def _clutch(self, axes: Iterable[int]) -> None:
        """Re-anchor X_d on X_r for these axes so handing them to the operator moves nothing."""
        for i in axes:
            self._offset[i] = self.law.x_r[i] - self._master_term(i)
            self._jog_pending[i] = 0.0

    def _set_sz(self, now_s: float, position_control: bool, source: Source, events: list) -> None:
        self.law.set_selection(Z, position_control)
        events.append(SzChanged(now_s, int(position_control), source))

    # ---- commands ------------------------------------------------------------------------------------

    def _refuse(self, now_s: float, cmd: Command, reason: str, events: list) -> None:
        events.append(CommandRefused(now_s, cmd, reason))

    def _command(self, now_s: float, cmd: Command, events: list, result: StepResult) -> None:
        sm = self.sm
        if isinstance(cmd, SetSz):
            self._command_sz(now_s, cmd, events)
        elif isinstance(cmd, EStop):
            self._raise_fault(now_s, FaultKind.ESTOP, f"Emergency stop: {cmd.reason}. The robot was stopped "
                                                      f"where it is; clear the fault to continue.", events)
        elif isinstance(cmd, ClearFault):
            self._clear_fault(now_s, cmd, events)
        elif isinstance(cmd, AbortRegion):
            if sm.force_control:
                sm.abort(now_s, cmd.reason, self.law.x_r[Z])
                self._set_sz(now_s, True, Source.CONTROLLER, events)
            else:
                self._refuse(now_s, cmd, "no region is being palpated", events)
        elif isinstance(cmd, Tare):
            problem = self._tare_problem()
            if problem is not None:
                self._refuse(now_s, cmd, problem, events)
            else:
                result.tare = cmd  # the device has the last word: it refuses a reading no unloaded array gives
        elif isinstance(cmd, (SetRamp, SetGains, SetRegion)):
            if not (sm.phase.idle or sm.phase == Phase.HOLD):
                self._refuse(now_s, cmd, "settings can change only between regions", events)
            elif isinstance(cmd, SetRamp):
                sm.set_ramp(cmd.ramp)
                r = cmd.ramp
                events.append(CommandApplied(now_s, cmd, f"Ramp set: {r.force_min_N:g} to {r.force_max_N:g} N in "
                                                         f"{r.force_step_N:g} N steps ({r.n_levels} levels), eps = "
                                                         f"{r.rmse_threshold_N:g} N over {r.settle_window_s:g} s."))
            elif isinstance(cmd, SetGains):
                problem = self.config.gains_problem(cmd.gains, self.sensor.frame_rate_hz, self.sensor.latency_s)
                if problem is not None:
                    self._refuse(now_s, cmd, problem, events)
                else:
                    self.law.set_gains(cmd.gains)
                    events.append(CommandApplied(now_s, cmd, "Impedance gains changed."))
            else:
                sm.region = cmd.index - 1
                events.append(CommandApplied(now_s, cmd, f"Next region is number {cmd.index + 1}."))
        elif isinstance(cmd, CancelJog):
            self._jog_pending = [0.0, 0.0, 0.0]
        elif isinstance(cmd, Jog):
            if not sm.phase.idle:
                self._refuse(now_s, cmd, "jog only while the operator holds position control", events)
            else:
                for i in range(3):
                    self._jog_pending[i] += cmd.delta_m[i]
        else:
            self._refuse(now_s, cmd, "unknown command", events)

    def _tare_problem(self) -> str | None:
        """Why the sensor may not be tared now (None: it may). A zero taken while the probe presses would
        hide that force from every ceiling, so only with the operator in position control between areas,
        nothing faulted, and no element reading contact or saturated."""
        if not self.sm.phase.idle:
            return ("tare only between areas, with the probe lifted off the tissue (not during a ramp, a retract or "
                    "a fault)")
        if self._sensor_seq < 0:
            return "no tactile frame has arrived yet"
        confirm = self.config.contact.confirm_threshold_pa
        if self._saturated:
            return f"{self._saturated} element(s) saturated: the probe is pressing; lift it clear of the tissue"
        # lifted well above every surface this session has touched, a reading is the array's own drift
        clear = self._x_s[Z] - self._surface_top_m >= self.config.contact.retract_height_m / 2
        if not (self._max_pressure_pa < confirm or clear):
            return (f"an element reads {self._max_pressure_pa / 1e3:.2f} kPa, above the "
                    f"{confirm / 1e3:.2f} kPa contact threshold: the probe is touching something; lift it clear")
        return None

    def _command_sz(self, now_s: float, cmd: SetSz, events: list) -> None:
        sm = self.sm
        if not cmd.position_control:
            if sm.phase == Phase.HOLD:
                self._refuse(now_s, cmd, f"clear the fault first ({self.safety.message})", events)
            elif sm.force_control:
                self._refuse(now_s, cmd, "force control is already on", events)
            elif sm.phase == Phase.RETRACT:
                self._refuse(now_s, cmd, "the probe is still retracting", events)
            elif (problem := self._contact_problem() or self._start_problem()) is not None:
                self._refuse(now_s, cmd, problem, events)
            else:
                self._jog_pending = [0.0, 0.0, 0.0]  # no lateral motion under force control
                onset, _ = self._thresholds
                touching = bool((self.frame["pressure_pa"] >= onset).any())
                if not touching:
                    self._carried_top_m = math.nan  # the ramp tracks this area afresh
                sm.start(now_s, self._x_s[Z], self._thresholds, touching=touching,
                         seek_speed_m_s=sm.ramp.force_min_N / self.law.damping_N_s_m(Z))
                # the seek's force floor counts from here (_read_frame), or from higher if a frame or the reference
                # sent put the probe higher
                self._floor_from_z = max(self._floor_from_z, self._x_s[Z], self.law.x_r[Z])
                self._seek_base_N = max(self._recent_force_N, default=0.0)
                sigma = self._noise.sigma_pa()
                force_noise_N = float(np.sqrt(np.sum(sigma**2))) * self.sensor.element_area_m2
                self._travel.rise_N = max(5.0 * force_noise_N, FORCE_RISE_N)
                self._sum_allowance_N = self._drift_allowance_N + self._travel.rise_N
                self._set_sz(now_s, False, cmd.source, events)
                notice = self._noise_notice()
                if notice:
                    events.append(Notice(now_s, notice))
        elif sm.force_control:
            sm.abort(now_s, "switched to position control by the operator", self.law.x_r[Z], retract=False)
            self._clutch((Z,))
            self._set_sz(now_s, True, cmd.source, events)
        # during a retract z is already position controlled: the lift finishes, then z is handed back

    def _refresh_thresholds(self) -> None:
        sigma = self._noise.sigma_pa()
        if sigma is not None:
            contact_thresholds(self.config.contact, sigma, out=self._thresholds)
            np.multiply(sigma, ONSET_NOISE_SIGMAS, out=self._negative_allowance_pa)
            self._negative_allowance_pa += IMPLAUSIBLE_NEGATIVE_FRACTION * self.sensor.full_scale_pa

    def _contact_problem(self) -> str | None:
        """Why contact could not be told from the sensor's noise in this area (None: it can)."""
        sigma = self._noise.sigma_pa()  # what the thresholds were last made from: no frame was read since
        if sigma is None:
            return (f"the sensor's noise is not measured yet ({self._noise.count} of {NOISE_MIN_FRAMES} frames read "
                    f"with the probe held between areas); wait a moment")
        confirm = float(np.median(self._thresholds[1]))
        ramp = self.sm.ramp
        mean_pa = ramp.force_min_N / (self.sensor.rows * self.sensor.cols * self.sensor.element_area_m2)
        if confirm >= mean_pa:
            # Below this the seek at F_min could end with no element ever confirming contact, or on noise
            return (f"the sensor's noise (median {np.median(sigma):.0f} Pa per element) puts contact "
                    f"confirmation at {confirm / 1e3:.2f} kPa, above the face's mean pressure at the first level "
                    f"({mean_pa / 1e3:.2f} kPa at {ramp.force_min_N:g} N): check the sensor's cable and shielding")
        return None

    def _start_problem(self) -> str | None:
        """Why the array's reading cannot be trusted to start force control here (None: it can): its zero has
        drifted since the tare, or it already reads contact that it was not seen making, by an unknown depth
        that no ceiling would count (issue 49: started 8 mm into a soft layer, a ramp ended 24 mm in while the
        indentation ceiling read 16)."""
        tracker = self.sm.tracker
        pressed = tracker.blind & (self.frame["pressure_pa"] >= tracker.confirm_pa)
        if pressed.any():
            return (f"{int(pressed.sum())} element(s) already read contact, up to "
                    f"{float(self.frame['pressure_pa'][pressed].max()) / 1e3:.2f} kPa, that the probe was not seen "
                    f"making: it may press the tissue by a depth no ceiling would count; lift it clear of the "
                    f"tissue (a reading left by the last area fades within seconds in air)")
        if self._zero_in_doubt:
            return ("the array read its first contact as soon as the probe moved down from where it read nothing: "
                    "it may have been tared pressing the tissue, by a force and depth no ceiling would count; lift "
                    "the probe clear of the tissue and tare the sensor")
        zero = self._noise.zero_pa()
        bound = DRIFT_FRACTION * self.sensor.full_scale_pa
        if abs(zero) > bound:  # (not known before the array was seen unloaded)
            return (f"the array's unloaded reading has drifted to {zero / 1e3:+.2f} kPa since the tare (more than "
                    f"{bound / 1e3:.1f} kPa): tare the sensor with the probe clear of the tissue")
        return None

    def _noise_notice(self) -> str:
        """What the operator should know of the sensor's noise before this area ("": nothing): that the array is
        noisier than the configured thresholds allow for, or that some elements are far noisier than the rest.
        An element raised a few % above the configuration by its estimate's own scatter is not news."""
        onset, confirm = self._thresholds
        sigma = self._noise.sigma_pa()
        configured = self.config.contact.onset_threshold_pa
        said = []
        typical = float(np.median(sigma))
        if np.median(onset) > configured:
            said.append(f"Sensor noise between areas: {typical:.0f} Pa per element (median), more than the "
                        f"configured {configured:g} Pa onset allows for: contact is tracked from "
                        f"{np.median(onset) / 1e3:.2f} kPa (confirmed at {np.median(confirm) / 1e3:.2f} kPa).")
        for i, j in np.argwhere(sigma > NOISY_ELEMENT_FACTOR * typical) if typical > 0 else ():
            said.append(f"Element at row {i}, column {j} is {sigma[i, j] / typical:.0f}x noisier than the median "
                        f"({sigma[i, j]:.0f} Pa): its contact is tracked from {onset[i, j] / 1e3:.2f} kPa.")
        return " ".join(said)

    def _raise_fault(self, now_s: float, kind: FaultKind, message: str, events: list) -> None:
        if not self.safety.latch(kind, message):
            return
        events.append(FaultRaised(now_s, kind, message))
        # Every fault first stops the reference where the robot is: a retract that started from the law's
        # moving state would carry the probe on into the tissue for as long as M/B takes to stop it
        # (2.3 mm past the indentation ceiling with a light damping, in the fault campaign).
        here = self._lift_start()
        self.law.reset(here, ZERO3)
        self.sm.fault(now_s, message, here[Z], retract=self.safety.retract)
        self._hold_xy = (self._x_s[0], self._x_s[1])
        if not self.safety.retract:
            self._stopping_from = self._x_s
            self.stop_distance_m = math.nan

    def _lift_start(self) -> Vec3:
        """Where a lift starts: the robot's reading, or the last reference sent where that is higher. A robot
        pressing into tissue or descending stays above its reference, so a reading below it lies low, and a lift
        from it sent the probe down first (the independent campaign: a reading that carried on descending after
        the robot had stopped, 7 mm low, and 28 N over the ceiling)."""
        x, sent = self._x_s, self._sent
        return (x[0], x[1], sent[Z]) if sent is not None and sent[Z] > x[Z] else x

    def _watch_stop(self, now_s: float, events: list) -> None:
        """Once the robot has come to rest after a stop-where-it-is fault, say how far it went."""
        start = self._stopping_from
        if start is None or math.sqrt(sum(v * v for v in self._v_s)) > AT_REST_M_S:
            return
        self._stopping_from = None
        self.stop_distance_m = math.dist(start, self._x_s)
        events.append(Notice(now_s, f"The robot came to rest {self.stop_distance_m * 1e3:.2f} mm from where it "
                                    f"was when the stop was ordered."))

    def _clear_fault(self, now_s: float, cmd: ClearFault, events: list) -> None:
        kind = self.safety.fault
        if kind == FaultKind.SLAVE_IMPLAUSIBLE:
            self._position_problem = None  # the operator has checked the robot: its reading is taken again
        reason = self.safety.clear(self._violation(now_s))
        if reason is not None:
            self._refuse(now_s, cmd, reason, events)
            return
        if kind not in RETRACT_FAULTS:
            self.law.reset(self._x_s, ZERO3)  # Eq. 3 again: the reference restarts where the robot stopped
        self._lifting = False
        self._clutch((0, 1, 2))
        self.sm.clear_fault(now_s)
        events.append(FaultCleared(now_s, kind))

    # ---- the tick ------------------------------------------------------------------------------------

    def _violation(self, now_s: float):
        return self.safety.check(
            uptime_s=now_s - self._t0,
            x_ref_m=self.law.x_r,
            v_ref_m_s=self.law.v_r,
            force_N=self._force_N,
            max_pressure_pa=self._max_pressure_pa,
            lowest_pa=self._lowest_pa,
            negative_allowance_pa=self._lowest_allowance_pa,
            saturated_elements=self._saturated,
            indentation_m=self._indentation_now(),
            sensor_age_s=self._ages[0],
            sensor_repeats=self._repeats.repeats,
            contradiction=self._contradiction,
            position_problem=self._position_problem,
            too_stiff=self._too_stiff,
            master_age_s=self._ages[1] if self.has_master else None,
            slave_age_s=self._ages[2],
        )

    def _descent_limit_m(self, z_before: float, dt: float) -> float:
        """The lowest this tick's reference may go from ``z_before`` (never above it): near tissue (below the
        highest surface touched plus the retract height, or anywhere before any was touched) no faster than
        the approach speed, and never where the force would pass the ceiling (:meth:`_force_floor_m`)."""
        if self._started_pressed or self._zero_in_doubt:
            return z_before  # started pressed: up, or nowhere, until lifted
        near = not z_before > self._surface_top_m + self.config.contact.retract_height_m
        lowest = z_before - self._approach_speed_m_s() * dt if near else -math.inf
        floor = self._force_floor_m()
        if floor > lowest:  # (NaN before the first frame: the stale sensor stops everything then)
            lowest = min(floor, z_before)
        return lowest

    def _seek_reached_floor(self, now_s: float) -> None:
        """The seek went as deep as a blind seek may without touching anything: the stiffest tissue force
        control accepts, had it begun where the seek began, would now push back the ceiling, and an array that
        reads nothing cannot tell that tissue from air."""
        lim = self.safety.limits
        depth = self.sm.seek_depth_m(self.law.x_r[Z])
        self.sm.abort(now_s, (
            f"no tissue found within {depth * 1e3:.1f} mm below the start height: a seek that touches nothing goes "
            f"no deeper than where tissue of the stiffest kind force control accepts "
            f"({lim.tissue_stiffness_max_N_m / 1e3:g} N/mm) would reach the {lim.force_ceiling_N:g} N ceiling, as a "
            f"dead array reads air too; lower the probe to within that of the tissue and switch again"),
            self._x_s[Z])

    def _approach_speed_m_s(self) -> float:
        """The approach speed, slower for tissue stiffer than APPROACH_STIFFNESS_N_M: a robot stopping short of
        the force floor goes on by a distance that grows with its speed, and the stiffer the tissue the more
        force that distance is (the fault campaign: 0.07 mm past the floor at 20 mm/s, 1.2 N on 16 kN/m)."""
        lim = self.safety.limits
        return lim.approach_speed_m_s * min(1.0, APPROACH_STIFFNESS_N_M / lim.tissue_stiffness_max_N_m)

    def _force_floor_m(self) -> float:
        """The lowest the reference may go now: where the newest frame's force, plus what the stiffest tissue
        (SafetyLimits.tissue_stiffness_max_N_m) adds below the height that frame was taken at, reaches the
        ceiling less FORCE_RESERVE_N. Between frames the loop is blind for 10-20 ms; an operator pushing at
        250 mm/s reached 27.9 N against a 12 N ceiling before one arrived. So the ceiling holds at every
        velocity limit, and near it the probe slows by itself (0.2 N from it on 5 kN/m: 40 um a frame)."""
        lim = self.safety.limits
        # the most of the last few frames: a reading that falls to nothing (an array that died, a drift that
        # stepped) would otherwise open the whole headroom to the force loop at once, which then dives towards a
        # force it will never read (the fault campaign: 0.3 mm into 7 kN/m tissue in the 16 ms to the fault)
        force = max(self._recent_force_N, default=math.nan)
        if not force >= 0.0:  # tissue never pulls; an unknown force leaves no headroom
            force = 0.0 if force < 0.0 else math.inf
        headroom = lim.force_ceiling_N - FORCE_RESERVE_N - force
        return self._floor_from_z - max(headroom, 0.0) / lim.tissue_stiffness_max_N_m

    def _indentation_now(self) -> float:
        """The newest frame's depth below the first touch with the robot's own motion since added: a late frame
        must not hide travel into the tissue from the ceiling."""
        return self._deepest_m + max(self._frame_z - self._x_s[Z], 0.0)

    def _read_master(self, master: MasterState, now_s: float, events: list, result: StepResult) -> None:
        if master.seq == self._master_seq:
            return
        pos = master.position_m
        if self._master_pos is not None:
            dt = master.t_s - self._master_t
            if dt > 0:
                alpha = dt / (self.config.master.derivative_filter_s + dt)
                scale = self.config.master.scale
                for i in range(3):
                    v_raw = scale * (pos[i] - self._master_pos[i]) / dt
                    v_new = self._v_d[i] + alpha * (v_raw - self._v_d[i])
                    self._a_d[i] += alpha * ((v_new - self._v_d[i]) / dt - self._a_d[i])
                    self._v_d[i] = v_new
        else:
            # first sample: anchor X_d on the robot so start-up moves nothing
            self._master_pos = pos
            self._clutch((0, 1, 2))
        self._master_pos = pos
        self._master_seq = master.seq
        self._master_t = master.t_s
        switch = master.sz_switch
        if switch is not None and self._master_switch is not None and switch != self._master_switch:
            self._command(now_s, SetSz(position_control=switch, source=Source.MASTER), events, result)
        self._master_switch = switch

    def _read_frame(self, frame: TactileFrame) -> None:
        self._sensor_seq = frame.seq
        p = frame.pressure_pa
        if self._repeats.push(p, frame.t_s):  # else a frozen array, or a dead one streaming zeros: not fresh
            self._seen[0] = frame.t_s
        area = self.sensor.element_area_m2
        self._force_N = float(p.sum()) * area
        pressing = self._force_N > RESIDUAL_FORCE_N
        self._started_pressed = pressing if self._started_pressed is None else self._started_pressed and pressing
        self._recent_force_N.append(self._force_N if self._force_N == self._force_N else math.inf)
        self._max_pressure_pa = float(p.max())
        margin = p + self._negative_allowance_pa
        k = int(np.argmin(margin))  # a NaN element is the one: NaN is never plausible
        self._lowest_pa, self._lowest_allowance_pa = float(p.flat[k]), float(self._negative_allowance_pa.flat[k])
        self._saturated = int(frame.saturated.sum()) if frame.saturated is not None else 0
        pos = self.history.at(frame.t_s)
        self._frame_z = pos[Z]
        told = self._told.at(frame.t_s)[Z]
        sm = self.sm
        z_floor = told if told > pos[Z] else pos[Z]
        # In the seek the array has not yet shown that it reads force at all: a dead one (or one stuck on an
        # unloaded frame under fresh noise) reads air all the way down, and a floor that followed the probe would
        # never stop it (the independent campaign: seeks through the whole layer to 47 N). So the floor follows
        # only frames that read a rise over what the array read as the seek began (a residual, an offset): the
        # tissue may start just below where the array last showed it reads force, or where the seek began.
        if sm.phase != Phase.SEEK_CONTACT or self._force_N - self._seek_base_N > self._travel.rise_N:
            self._floor_from_z = z_floor
        elif not self._floor_from_z >= z_floor:
            self._floor_from_z = z_floor
        sm.on_frame(frame.t_s, p, self._force_N, pos)
        fr = self.frame
        fr["tick"] = self._ticks
        fr["sensor_seq"] = frame.seq
        fr["t_s"] = frame.t_s
        fr["tsi_position_m"] = pos
        fr["pressure_pa"] = p
        tracker = sm.tracker
        if sm.phase.idle:
            self._noise.push(p, unloaded=bool((p < self._thresholds[0]).all()))
            self._refresh_thresholds()  # the estimate moved on by a few elements (AirNoise)
        if not sm.force_control:
            # the ceiling holds under position control too: the operator can press the probe in by hand
            implausible = not self._lowest_pa >= -self._lowest_allowance_pa
            clear = (p < self._thresholds[0]).all() and not implausible
            # A sensor's residual reading after a hard press (creep) can hold an element above the threshold
            # in air for seconds: a probe moved to the next area would then carry the last area's onsets
            # over, and every thickness and indentation there would be another place's.
            # But a probe slid sideways while it presses firmly is still in the tissue it was pressed into: tracked
            # afresh, its onsets would start where it is, and the indentation ceiling would count from there (the
            # fault campaign: an operator jogging down and sideways went 8.4 mm in while the loop counted 3).
            moved = (self._tracked_xy is None or math.dist(self._tracked_xy, pos[:2])
                     > TRACKED_DRIFT_PITCHES * self.sensor.pitch_m) and not self._force_N > RESIDUAL_FORCE_N
            if clear:
                self._carried_top_m = math.nan
            elif moved and tracker.confirmed:
                top = float(np.nanmax(tracker.onset_height_m))
                if pos[Z] < top and not self._carried_top_m >= top:  # still in the tissue it touched
                    self._carried_top_m = top
            if clear or moved:
                tracker.reset(self._thresholds)  # the next contact is a new descent, tracked from here
                self._tracked_xy = (pos[0], pos[1])
            tracker.update(p, pos[Z])
        if self._clear_z < math.inf:  # no contact confirmed yet in this session
            # (told from noise only once the array's noise is measured: one noisy element crosses 900 Pa in air)
            if (p >= tracker.confirm_pa).any() and self._noise.sigma_pa() is not None:
                # where each element's reading began to rise: its onset, or if it read from the first frame on (a
                # residual, or a press), where it rose from that (nowhere yet: it read contact from the start)
                rose = np.fmax(tracker.onset_height_m, tracker.blind_onset_m)
                self._zero_in_doubt = not np.nanmax(rose, initial=-math.inf) < self._clear_z - PRELOAD_ONSET_M
                self._clear_z = math.inf
            elif self._clear_z == -math.inf or (pos[Z] > self._clear_z and (p < self._thresholds[0]).all()):
                self._clear_z = pos[Z]
        self._deepest_m = self._carried_top_m - pos[Z]
        top = tracker.top_m()  # by the summed reading where sooner than any element (a soft start)
        if top > -math.inf:
            if not self._deepest_m >= top - pos[Z]:
                self._deepest_m = top - pos[Z]
            if not self._surface_top_m >= top:
                self._surface_top_m = top
        if self._zero_in_doubt and not pos[Z] <= self._surface_top_m + PRELOAD_ONSET_M \
                and (p < self._thresholds[0]).all() and self._force_N >= -self._drift_allowance_N:
            self._zero_in_doubt = False  # seen clear of the tissue, reading nothing and nothing below zero
        _, dL, stiffness, _, self._indentation_m = element_analysis(
            p, tracker.onset_height_m, pos[Z], tracker.onset_pa, self.config.contact, area)
        # Elements already pressed when tracking began have no onset, so no indentation; without this the
        # ceiling sees NaN and the probe may be driven to the table. Each is in at least as far as the TSI
        # went down since its reading began to rise (at once if it was pressing tissue; not the descent
        # through air if its reading was a residual from the last area).
        blind_onset = tracker.blind_onset_m
        pressed_blind = tracker.blind & np.isfinite(blind_onset)
        if pressed_blind.any():
            travel = float(np.mean(blind_onset[pressed_blind])) - pos[Z]
            if not self._indentation_m >= travel:
                self._indentation_m = max(travel, 0.0)
            travel = float(np.max(blind_onset[pressed_blind])) - pos[Z]
            if not self._deepest_m >= travel:
                self._deepest_m = max(travel, 0.0)
        self._check_contact(p, pos[Z])
        self._check_stiffness(p, pos[Z])
        if sm.force_control:
            fr["dL_m"] = dL
            fr["stiffness_pa"] = stiffness
        else:
            fr["dL_m"] = np.nan
            fr["stiffness_pa"] = np.nan

    def _check_position(self, slave: SlaveState) -> None:
        """Whether the robot's new reading follows from its last one: where the last reading's position and
        velocity put it, within how far the robot can accelerate away in between. A reading that jumps
        (an encoder or a link that lies) would make every later reference jump with it: the stop-where-it-is
        and the lift start from the reading, and a robot whose reading lied 1-10 mm low was sent that far
        into the tissue (the fault campaign: up to 20 N over the ceiling)."""
        dt = slave.t_s - self._slave_t
        if not self._started or self._slave_seq < 0 or not 0.0 < dt <= 1.0 or self._position_problem:
            return
        predicted = (self._x_s[i] + self._v_s[i] * dt for i in range(3))
        off = math.dist(slave.position_m, tuple(predicted))
        allowed = POSITION_JUMP_M + 0.5 * ROBOT_ACCEL_MAX_M_S2 * dt * dt
        if not off <= allowed:  # NaN included
            self._position_problem = (
                f"Implausible robot position: its reading jumped {off * 1e3:.2f} mm from where its last one, "
                f"{dt * 1e3:.0f} ms before, put it (at most {allowed * 1e3:.2f} mm); no reference can be made "
                f"from it. The robot was told to hold.")

    def _check_contact(self, pressure_pa: np.ndarray, z_m: float) -> None:
        """Whether the array reads the contact the probe's motion says it has, under force control once contact
        is confirmed (``_contradiction`` says why not): no element reading contact while the probe is below
        where it confirmed contact, or the probe going deeper without the force rising. A dead array, one that
        repeats a frame, or one whose reading drifts down all read less than the tissue pushes, and the force
        loop pushes on into the tissue."""
        sm = self.sm
        previous, self._previous_contact = self._previous_contact, (self._force_N, z_m)
        if sm.force_control and not self._force_N >= -self._sum_allowance_N:
            self._contradiction = (
                f"Tactile force {self._force_N:.2f} N: the array's elements add up to less than the "
                f"{-self._sum_allowance_N:.2f} N a tared array can read (tissue never pulls, and its zero wanders by "
                f"{DRIFT_FRACTION:.0%} of full scale at most); its reading has drifted down and hides force. The "
                f"probe was lifted off the tissue.")
            return
        if sm.phase != Phase.SETTLING:
            self._travel.reset()
            self._contradiction = None
            self._previous_contact = None
            return
        if previous is not None and z_m <= previous[1] and previous[0] - self._force_N > max(
                FORCE_DROP_N, 2.0 * self._travel.rise_N):
            # (the fault campaign: an array that died while the ramp rose read 0 N for 16 ms before the depth
            # check saw it, and the probe pressed 0.7 N past the ceiling into 7 kN/m tissue)
            self._contradiction = (
                f"Tactile force fell from {previous[0]:.2f} to {self._force_N:.2f} N in one frame while the probe went "
                f"no higher: tissue does not let go so; the array is not reading it (dead, unplugged or drifting). "
                f"The probe was lifted off the tissue.")
            return
        tracker = sm.tracker
        onsets = tracker.onset_height_m
        top = float(np.nanmax(onsets)) if np.isfinite(onsets).any() else math.nan
        if z_m < top - DEAD_DEPTH_M and not (pressure_pa >= tracker.onset_pa).any():
            self._contradiction = (
                f"Dead tactile array: no element reads contact while the probe is {(top - z_m) * 1e3:.1f} mm below "
                f"where it confirmed contact; the array is not reading the tissue. The probe was lifted off the "
                f"tissue.")
            return
        self._travel.push(self._force_N, z_m)

    def _check_stiffness(self, pressure_pa: np.ndarray, z_m: float) -> None:
        """The tissue's stiffness over the newest frames in contact, against the stiffest the force loop and the
        force floor were made for (a 400 kPa layer 6 mm thick bounced 0-11.6 N at the 1 N level)."""
        sm = self.sm
        in_contact = bool((pressure_pa >= sm.tracker.onset_pa).any())
        if sm.phase in (Phase.RETRACT, Phase.HOLD) or (sm.phase.idle and not in_contact):
            self._stiffness.clear()  # lifting already, or lifted off: the next contact is measured afresh
            self._too_stiff = None
            return
        if not in_contact:
            return
        self._stiffness.push(z_m, self._force_N)
        k = self._stiffness.stiffness_N_m()
        stiffest = self.safety.limits.tissue_stiffness_max_N_m
        if k > STIFFER_FACTOR * stiffest and self._too_stiff is None:
            self._too_stiff = (
                f"Tissue too stiff: the force rose by {k / 1e3:.1f} N per mm of indentation, more than the "
                f"{stiffest / 1e3:.1f} N/mm force control is made stable for (safety.tissue_stiffness_max_N_m; raise "
                f"it with control.gains.damping_N_s_m[2]). The probe was lifted off the tissue.")

    def _check_hidden_force(self) -> None:
        """What the tissue, as stiff as this area's levels measured it, pushes back with now (it stiffens with
        depth, so this is the least), against the ceiling: a reading that drifted down while the force rose
        hides the rest."""
        settled = self.sm.settled
        if settled is None or self._contradiction is not None:
            return
        lim = self.safety.limits
        force_N, z_m, stiffness = settled
        predicted = force_N + stiffness * (z_m - self._x_s[Z])
        if predicted > lim.force_ceiling_N + HIDDEN_FORCE_N and predicted > self._force_N + HIDDEN_FORCE_N:
            self._contradiction = (
                f"Tactile force too low for the tissue: the probe went {(z_m - self._x_s[Z]) * 1e3:.2f} mm deeper "
                f"than at a level where the tissue pushed back {stiffness / 1e3:.1f} N per mm, so it now "
                f"presses about {predicted:.1f} N, over the {lim.force_ceiling_N:g} N ceiling, while the array "
                f"reads {self._force_N:.2f} N (drifting?). The probe was lifted off the tissue.")

    def _check_travel(self) -> None:
        """The robot, now, below where the array last read the force rise (between frames as well: a frame is
        10-20 ms late, and at 20 mm/s that is a third of a millimetre more)."""
        travel = self._travel.travel_m(self._x_s[Z])
        lim = self.safety.limits
        headroom = lim.force_ceiling_N + HIDDEN_FORCE_N - self._travel.peak_N
        allowed = min(UNEXPLAINED_TRAVEL_M, max(headroom, 0.0) / lim.tissue_stiffness_max_N_m)
        if travel > allowed and self._contradiction is None:
            self._contradiction = (
                f"Tactile force not rising: the probe went {travel * 1e3:.2f} mm deeper under force control while "
                f"the array read no more than {self._travel.peak_N:.2f} N; it is not reading the tissue (dead, "
                f"frozen or drifting). The probe was lifted off the tissue.")

    def step(
        self,
        now_s: float,
        sensor: TactileFrame | None,
        slave: SlaveState | None,
        master: MasterState | None,
        commands: Iterable[Command] = (),
    ) -> StepResult:
        events: list[Event] = []
        result = StepResult(ZERO3, ZERO3, hold=True, new_frame=False, events=events)
        if slave is not None:
            if slave.seq != self._slave_seq:
                self._check_position(slave)
                self._slave_seq = slave.seq
                self.history.push(slave.t_s, slave.position_m)
            self._x_s, self._v_s = slave.position_m, slave.velocity_m_s
            self._slave_t = slave.t_s
        if not self._started:
            if slave is None:
                self._fill_tick(now_s)  # nothing to anchor the reference on yet: hold
                return result
            self._started = True
            self._t0 = self._last = now_s
            self.law.reset(self._x_s, self._v_s)  # Eq. 3
            self._told.push(now_s, self._x_s)
            self._clutch((0, 1, 2))
            events.append(SzChanged(now_s, 1, Source.CONTROLLER))
        dt = min(max(now_s - self._last, 0.0), self.config.max_step_s)
        self._last = now_s
        ahead = now_s + FUTURE_TOLERANCE_S
        if sensor is not None and not sensor.t_s <= ahead:
            sensor = None  # stamped in the future (or not at all): not a reading of now
        if master is not None and master.t_s <= ahead:
            self._seen[1] = master.t_s
        if slave is not None and slave.t_s <= ahead:
            self._seen[2] = slave.t_s

        if master is not None and self.has_master:
            self._read_master(master, now_s, events, result)
        for cmd in commands:
            self._command(now_s, cmd, events, result)
        if sensor is not None and sensor.seq != self._sensor_seq:
            self._read_frame(sensor)
            result.new_frame = True
        # a device that stops answering keeps ageing from its last reading (the array: from its last new one)
        self._ages = (now_s - self._seen[0], now_s - self._seen[1], now_s - self._seen[2])

        sm = self.sm
        if sm.force_control:
            sm.on_tick(now_s, self._x_s[Z])
            self._check_hidden_force()
            self._check_travel()
        events.extend(sm.take_events())

        if not self.safety.faulted:
            violation = self._violation(now_s)
            if violation is not None:
                self._raise_fault(now_s, violation[0], violation[1], events)
                events.extend(sm.take_events())
        if self.law.sz == 0 and not sm.force_control:
            # the ramp ended (done, timeout, no tissue, fault): z goes back to position control
            self._set_sz(now_s, True, Source.CONTROLLER, events)

        self._reference(now_s, dt, result, events)
        self._guard(now_s, dt, result, events)
        self._told.push(now_s, self._x_s if result.hold else result.position_ref_m)
        self._watch_stop(now_s, events)
        events.extend(sm.take_events())
        result.feedback = MasterFeedback(now_s, int(sm.phase), sm.region_done, self._force_N, self.safety.faulted)
        self._fill_tick(now_s)
        return result

    def _reference(self, now_s: float, dt: float, result: StepResult, events: list) -> None:
        sm, law = self.sm, self.law
        z_before = law.x_r[Z]
        if sm.phase == Phase.HOLD and not (self.safety.retract or self._lifting):
            too_hard = self.safety.pressing_too_hard(self._force_N, self._max_pressure_pa, self._indentation_now())
            readable = (self._ages[2] <= self.safety.limits.slave_timeout_s
                        and self.safety.fault != FaultKind.SLAVE_IMPLAUSIBLE)  # a lift starts from the reading
            if too_hard is None or not readable:
                # stopped: keep the reference on the robot so clearing the fault restarts without a jump
                law.reset(self._x_s, ZERO3)
                result.position_ref_m = self._x_s
                result.hold = True
                return
            # held pressing harder than a ceiling allows (a robot that braked into the tissue): lift, and stay
            # faulted; a live robot moving up, away from the tissue, is safe
            self._lifting = True
            law.reset(self._x_s, ZERO3)
            sm.set_retract(self._x_s[Z])
            z_before = law.x_r[Z]
            events.append(Notice(now_s, f"{too_hard} while the robot was held: the probe is being lifted off the "
                                        f"tissue at the retract speed; the fault stays latched."))
        if sm.phase.idle:
            self._advance_jog(dt)
        x_d = self._xd = self._desired()
        f_d_z = -sm.force_desired_N if sm.force_control else 0.0
        # Tissue only pushes: a negative or non-finite reading (a damaged frame, found by the fault campaign)
        # must not pull the probe down through the law's compliance; the supervisor faults on it meanwhile.
        f_e = (0.0, 0.0, -self._force_N if self._force_N > 0.0 else 0.0)
        if sm.phase in (Phase.RETRACT, Phase.HOLD):
            z, vz, finished = sm.retract_step(law.x_r[Z], dt)
            if sm.phase == Phase.HOLD:
                x_d = (self._hold_xy[0], self._hold_xy[1], z)
                v_d = (0.0, 0.0, vz)
            else:
                x_d = (x_d[0], x_d[1], z)
                v_d = (self._v_d[0], self._v_d[1], vz)
            law.step(dt, x_d, v_d, ZERO3, ZERO3, ZERO3)
            # The lift is the retract ramp itself, not the law's answer to the tissue's push: with the push,
            # a probe carrying 9 N rose at F/B = 112 mm/s, the velocity guard refused it, and the probe was
            # stopped where it was, still pressing.
            law.x_r[Z], law.v_r[Z], law.a_r[Z] = z, vz, 0.0
            if sm.phase == Phase.RETRACT and finished:
                sm.retract_finished(now_s)
                self._clutch((Z,))
                self._xd = (self._xd[0], self._xd[1], self._desired()[Z])  # this tick's row shows the handed-back X_d
        else:
            law.step(dt, x_d, tuple(self._v_d), tuple(self._a_d), f_e, (0.0, 0.0, f_d_z))
        lowest = self._descent_limit_m(z_before, dt)
        if law.x_r[Z] < lowest:  # never lifted by it: it only stops a descent
            law.x_r[Z] = lowest
            law.v_r[Z] = max(law.v_r[Z], (lowest - z_before) / dt if dt > 0 else 0.0)
        if sm.phase == Phase.SEEK_CONTACT and not law.x_r[Z] > self._force_floor_m() + STEP_TOLERANCE_M:
            self._seek_reached_floor(now_s)
        if self._ages[0] > self._overdue_s and law.x_r[Z] < z_before:
            # the next frame is late: what the probe presses on is unknown, so it goes no deeper until it
            # comes (lateral and upward motion go on; the stale-sensor fault follows if it never does)
            law.x_r[Z] = z_before
            law.v_r[Z] = max(law.v_r[Z], 0.0)
        result.position_ref_m = (law.x_r[0], law.x_r[1], law.x_r[2])
        result.velocity_ref_m_s = (law.v_r[0], law.v_r[1], law.v_r[2])
        result.hold = False

    def _guard(self, now_s: float, dt: float, result: StepResult, events: list) -> None:
        """The last check before a reference leaves the loop, in every state (faulted included): finite, in
        the workspace, and no farther from the last one sent than the velocity limit allows in this tick.
        A reference that fails is not sent: the robot holds where it is, and the fault says why."""
        if result.hold:
            self._sent = None
            return
        x = result.position_ref_m
        lim = self.safety.limits
        last = self._sent if self._sent is not None else self._x_s
        if not all(math.isfinite(v) for v in x):
            problem = (FaultKind.WORKSPACE, f"Invalid reference: the controller computed a non-finite position "
                                            f"({x[0]:g}, {x[1]:g}, {x[2]:g}). The robot was stopped where it is.")
        else:
            problem = self.safety.outside_workspace(x)
            step = math.dist(x, last)
            allowed = lim.velocity_limit_m_s * max(dt, 1.0 / self.config.rate_hz) + STEP_TOLERANCE_M
            if problem is None and step > allowed:
                problem = (FaultKind.VELOCITY_LIMIT, (
                    f"Velocity limit: the next reference was {step * 1e3:.2f} mm from the last one sent, more "
                    f"than the {allowed * 1e3:.2f} mm the {lim.velocity_limit_m_s * 1e3:.0f} mm/s limit allows "
                    f"in one tick. It was not sent; the robot was stopped where it is."))
        if problem is None:
            self._sent = x
            return
        self._raise_fault(now_s, problem[0], problem[1], events)
        self.law.reset(self._x_s, ZERO3)
        result.position_ref_m, result.velocity_ref_m_s, result.hold = self._x_s, ZERO3, True
        self._sent = None

    def _advance_jog(self, dt: float) -> None:
        pending = self._jog_pending
        if pending[0] == pending[1] == pending[2] == 0.0:
            return
        norm = math.sqrt(pending[0] ** 2 + pending[1] ** 2 + pending[2] ** 2)
        step = min(1.0, self.config.master.jog_speed_m_s * dt / norm)
        for i in range(3):
            moved = pending[i] * step
            self._offset[i] += moved
            pending[i] -= moved
            if abs(pending[i]) < 1e-9:
                pending[i] = 0.0

    def _fill_tick(self, now_s: float) -> None:
        # one structured assignment costs a tenth of twenty field assignments; order = TICK_DTYPE's
        sm, law, ages, x_d = self.sm, self.law, self._ages, self._xd
        t = self.tick
        self.tick[()] = (
            self._ticks, now_s, t["late_s"], t["compute_s"], t["io_s"], t["missed_ticks"],
            sm.phase, law.sz, sm.region_done, self.safety.fault, sm.region, sm.level, sm.n_levels,
            sm.force_desired_N, self._force_N, sm.rmse_N,
            law.x_r, law.v_r, x_d, self._x_s,
            self._indentation_m, self._sensor_seq,
            ages[0], ages[1] if self.has_master else math.nan, ages[2],
        )
        self._ticks += 1
