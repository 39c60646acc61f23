"""Contact onset, initial thickness L0, indentation dL and stiffness (Eq. 1), per tactile element.

How they are found from the data — written down once, here:

* The probe descends under force control with its face level. For each element we watch its pressure
  against the TSI face height z (robot kinematics, interpolated at the frame's own timestamp, since the
  sensor lags the robot and runs 10-100x slower than the loop).
* **Thresholds from the sensor's own noise.** p_on and p_c are set per element, never below the
  configured values: p_on = max(configured p_on, 5 sigma), with sigma the element's white noise measured
  from the frames read between areas (:class:`AirNoise`), and p_c = p_on times the configured ratio. At
  5 sigma a single element-frame of noise crosses p_on with probability 3e-7 (a face of 60 elements read
  100 times a second: about once in 10 minutes), and such a crossing is forgotten once it falls back;
  p_c at 3 p_on (15 sigma) is never reached by noise. A fixed threshold on a noisier sensor (4x the
  default's 50 Pa: 300 Pa is 1.5 sigma) took noise in air for contact and aborted 76 of 77 areas.
* **Contact onset.** The first frame pair in which the element's pressure crosses the onset threshold
  p_on gives the crossing height z1 (linear interpolation between the two frames). Pressure near onset
  rises roughly linearly with indentation, so once the pressure also crosses the confirm threshold
  p_c (height z2), the onset height is refined by extrapolating that line back to zero pressure:
  z0 = z1 + p_on * (z1 - z2) / (p_c - p_on). A crossing that falls back below p_on before reaching
  p_c is taken for noise and forgotten. The extrapolated onset lies at or above z1 and is kept only
  when the descent between the crossings was real (z2 < z1); otherwise z0 = z1. An element that
  already reads above p_on when tracking starts has an unknown onset (the region must start above
  the tissue) and stays NaN for the region, unless its reading then falls below p_on or to half of
  what it was: that was the sensor's creep after the last area, decaying to nothing in air (tissue
  under a face that descends or stands still relaxes by far less in the seconds of a descent), and
  the element is tracked like the others on its reading above the lowest it fell to.
* **L0**, the initial thickness under the element, is the onset height above the table:
  L0 = z0 - z_table (the table height comes from the rig's calibration, ContactSettings.table_height_m).
* **dL**, the element's indentation, is how far the face has travelled below that element's onset:
  dL = z0 - z (an element on a bump starts earlier and is indented more than one over a gap).
* An element is **in contact** while its pressure is at least p_on and its onset is known.
* **Stiffness** (Eq. 1): E = F L0 / (A dL) with F = p A the element's force and A its area (4e-6 m^2).
  It is NaN for elements not in contact and for dL below min_indentation_m, where the ratio is
  dominated by noise; never inf, never a division error.
* The **TSI indentation depth** is the mean dL over the elements in contact (NaN if none).
"""

from __future__ import annotations

import math

import numpy as np

from control.config import ContactSettings
from tissue.face import stiffness_pa

# An element's contact onset threshold stands this many of its own noise standard deviations above zero.
ONSET_NOISE_SIGMAS = 5.0
NOISE_WINDOW_FRAMES = 256  # the newest frames read between areas: 2.6 s at 100 frames/s
# Frames needed before the noise is known: 31 differences give an element's sigma to about 25 %, and the
# face's median of them (the floor under every element's) to a few %
NOISE_MIN_FRAMES = 32
ELEMENTS_PER_FRAME = 2  # elements whose noise each frame between areas brings up to date: all 60 in 30 frames
_MAD_TO_SIGMA = 1.4826  # a normal distribution's standard deviation over its median absolute deviation
_OUTLIER_SIGMAS = 5.0  # a frame-to-frame difference beyond this many standard deviations is not the noise


# The summed reading's rise is followed through these multiples of its own onset threshold: the heights it
# passes them at place the tissue's first push (see ContactTracker.first_touch_m), as an element's onset and
# confirmation place its own
SUM_STEPS = (1.0, 3.0)


class ContactTracker:
    """Per-element contact onset during one region's descent."""

    def __init__(self, contact: ContactSettings, shape: tuple[int, int]):
        self.shape = shape
        # per element: the thresholds this descent is tracked with (see contact_thresholds)
        self.onset_pa = np.full(shape, contact.onset_threshold_pa)
        self.confirm_pa = np.full(shape, contact.confirm_threshold_pa)
        self.onset_height_m = np.empty(shape)
        self._z1 = np.empty(shape)
        self._confirmed = np.empty(shape, dtype=bool)
        self._blind = np.empty(shape, dtype=bool)  # in contact before tracking began
        # a blind element: its reading when tracking began, and where it then rose by the onset threshold
        # (at once if it was pressing tissue; later if that reading was a residual in air)
        self._blind_base_pa = np.empty(shape)
        self.blind_onset_m = np.empty(shape)
        self._settled = np.empty(shape, dtype=bool)  # confirmed or blind: nothing more to find
        # a creep residual's floor: the lowest reading of a blind element; once it is known to have been in
        # air (aired), the floor follows the residual down until contact and is taken off its reading
        self._floor_pa = np.empty(shape)
        self._aired = np.empty(shape, dtype=bool)
        self._prev_p = np.empty(shape)
        # the summed reading: its lowest in this descent, its last, and where its rise over that lowest passed
        # each of SUM_STEPS times its onset threshold (NaN: not yet)
        self._sum_on_pa = 0.0
        self._sum_floor_pa = math.inf
        self._sum_prev = (math.nan, math.nan)
        self._sum_heights_m = np.full(len(SUM_STEPS), np.nan)
        self.reset()

    def reset(self, thresholds: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Forget the descent, in place: under position control this runs on every frame clear of the tissue.
        ``thresholds`` (onset, confirm per element): track the next descent with these."""
        if thresholds is not None:
            self.onset_pa[...], self.confirm_pa[...] = thresholds
        self.onset_height_m.fill(np.nan)
        self._z1.fill(np.nan)
        self._confirmed.fill(False)
        self._blind.fill(False)
        self._blind_base_pa.fill(0.0)
        self.blind_onset_m.fill(np.nan)
        self._settled.fill(False)
        self._floor_pa.fill(np.inf)
        self._aired.fill(False)
        self._started = False  # no frame since the reset: the next one is the baseline
        self._prev_z = np.nan
        # the summed reading's noise is the elements' added in quadrature, so is its onset threshold (each
        # element's stands ONSET_NOISE_SIGMAS of its own noise up, or higher if configured so)
        self._sum_on_pa = math.sqrt(float(np.vdot(self.onset_pa, self.onset_pa)))  # (no array made: per frame in air)
        self._sum_floor_pa = math.inf
        self._sum_prev = (math.nan, math.nan)
        self._sum_heights_m.fill(np.nan)

    def update(self, pressure_pa: np.ndarray, tsi_z_m: float) -> None:
        p_on, p_c = self.onset_pa, self.confirm_pa
        if not self._started:
            np.greater_equal(pressure_pa, p_on, out=self._blind)
            np.copyto(self._blind_base_pa, pressure_pa, where=self._blind)
            np.copyto(self._floor_pa, pressure_pa, where=self._blind)
            self._settled[...] = self._blind
            self._prev_p[...] = pressure_pa
            self._prev_z = tsi_z_m
            self._started = True
            return
        if self._blind.any():
            self._air_out(pressure_pa, p_on)
        reading = pressure_pa
        if self._aired.any():
            # the creep residual of an element found in air keeps decaying until the face reaches tissue
            np.minimum(self._floor_pa, pressure_pa, out=self._floor_pa, where=self._aired & np.isnan(self._z1))
            reading = pressure_pa - self._residual_pa()
        if not self._settled.all():
            self._track(reading, tsi_z_m, p_on, p_c)
        rising = self._blind & np.isnan(self.blind_onset_m) & (pressure_pa >= self._blind_base_pa + p_on)
        if rising.any():
            self.blind_onset_m[rising] = self._prev_z
        self._track_sum(float(pressure_pa.sum()), tsi_z_m)
        self._prev_p[...] = reading
        self._prev_z = tsi_z_m

    def _track_sum(self, total_pa: float, tsi_z_m: float) -> None:
        """Where the summed reading's rise over its lowest in this descent passed each step of SUM_STEPS (the
        height interpolated between frames); a rise that falls back below the first step was noise."""
        heights = self._sum_heights_m
        if np.isnan(heights[0]) and total_pa < self._sum_floor_pa:
            self._sum_floor_pa = total_pa  # (a residual decaying in air, before any rise)
        before, z0 = self._sum_prev
        self._sum_prev = (total_pa, tsi_z_m)
        rise, rose = total_pa - self._sum_floor_pa, before - self._sum_floor_pa
        if not math.isfinite(rise):
            return
        if rise < self._sum_on_pa:
            heights.fill(np.nan)
            return
        for k, step in enumerate(SUM_STEPS):
            level = step * self._sum_on_pa
            if np.isnan(heights[k]) and rise >= level:
                # where between the frames it passed the level (at this frame if the last one was not known)
                heights[k] = (z0 + (level - rose) / (rise - rose) * (tsi_z_m - z0)
                              if math.isfinite(rose) and rose < level and math.isfinite(z0) else tsi_z_m)

    def first_touch_m(self) -> float:
        """Where the tissue began to push, by the summed reading (NaN: it has not risen through both steps yet).

        The summed reading's noise is the elements' in quadrature, so it rises out of it several times sooner
        than any one element's: on tissue whose push starts softly (force as the indentation to the power 2.2,
        the independent campaign's softest) an element's onset came 0.8 mm below the surface, and the probe
        went that much past the indentation ceiling. The rise's first two steps are extrapolated back to none,
        as linear tissue's would be: exact there, and on a softer start still short of the surface (a fit of the
        start's power to a third step was thrown far above it by the tissue's viscous push at first touch).
        """
        z1, z3 = self._sum_heights_m
        if not z1 > z3:
            return math.nan
        return float(z1 + (z1 - z3) * SUM_STEPS[0] / (SUM_STEPS[1] - SUM_STEPS[0]))

    def top_m(self) -> float:
        """Where this contact was first touched: the highest onset tracked, or the summed reading's first rise
        (:meth:`first_touch_m`) where higher; -inf before either. What the indentation ceiling counts from."""
        onsets = self.onset_height_m
        top = float(np.nanmax(onsets)) if np.isfinite(onsets).any() else -math.inf
        touched = self.first_touch_m()
        return touched if touched > top else top

    def _air_out(self, pressure_pa: np.ndarray, p_on: np.ndarray) -> None:
        """Blind elements whose reading fell below p_on, or to half of what it was, were reading creep in
        air: from here they are tracked as elements that had not yet touched, on their reading above its
        floor."""
        waiting = self._blind & np.isnan(self.blind_onset_m)
        np.minimum(self._floor_pa, pressure_pa, out=self._floor_pa, where=waiting)
        aired = waiting & ((self._floor_pa < p_on) | (self._floor_pa <= 0.5 * self._blind_base_pa))
        if aired.any():
            self._blind[aired] = False
            self._settled[aired] = False
            self._aired |= aired
            self._prev_p[aired] = (pressure_pa - self._residual_pa())[aired]

    def _residual_pa(self) -> np.ndarray:
        """What is taken off each element's reading: an aired element's floor (never below zero)."""
        return np.where(self._aired, np.clip(self._floor_pa, 0.0, None), 0.0)

    def _track(self, pressure_pa: np.ndarray, tsi_z_m: float, p_on: np.ndarray, p_c: np.ndarray) -> None:
        # Divisions below only run where p0 < threshold <= p, so their denominators are positive.
        p0, z0 = self._prev_p, self._prev_z
        dz = tsi_z_m - z0
        unknown = np.isnan(self._z1)
        first = unknown & ~self._blind & (p0 < p_on) & (pressure_pa >= p_on)
        if first.any():
            z1 = z0 + (p_on[first] - p0[first]) / (pressure_pa[first] - p0[first]) * dz
            self._z1[first] = z1
            self.onset_height_m[first] = z1
            unknown &= ~first
        conf = ~unknown & ~self._confirmed & (p0 < p_c) & (pressure_pa >= p_c)
        if conf.any():
            z2 = z0 + (p_c[conf] - p0[conf]) / (pressure_pa[conf] - p0[conf]) * dz
            z1 = self._z1[conf]
            refined = z1 + p_on[conf] * (z1 - z2) / (p_c[conf] - p_on[conf])
            self.onset_height_m[conf] = np.where(z2 < z1, refined, z1)
            self._confirmed[conf] = True
            self._settled |= conf
        # an unconfirmed crossing that falls back below p_on was noise, not contact
        blip = ~unknown & ~self._confirmed & (pressure_pa < p_on)
        if blip.any():
            self._z1[blip] = np.nan
            self.onset_height_m[blip] = np.nan

    @property
    def blind(self) -> np.ndarray:
        return self._blind

    @property
    def confirmed(self) -> bool:
        """Whether an element has confirmed contact in this descent."""
        return bool(self._confirmed.any())


class AirNoise:
    """Each element's white noise, from the frames read while the operator holds the probe between areas.

    Estimated from frame-to-frame differences (whose spread is sqrt(2) sigma for white noise): a slow change
    of load (the probe lowered, a creep residual decaying) hardly moves a difference, and the differences
    further from their median than 5 sigma (by their median absolute deviation), the frames pressing or
    lifting off tissue, are set aside. The whole face's medians at once take half a millisecond, too long
    for one tick of the 1 kHz loop: once the first NOISE_MIN_FRAMES frames have given every element an
    estimate, each frame brings ELEMENTS_PER_FRAME of them up to date in turn."""

    def __init__(self, shape: tuple[int, int], window_frames: int = NOISE_WINDOW_FRAMES):
        self.shape = shape
        n = shape[0] * shape[1]
        self._diffs = np.zeros((n, window_frames - 1))  # each element's differences, oldest overwritten first
        self._last = np.zeros(n)
        self._next = 0
        self._own = np.full(n, np.nan)
        self._turn = 0  # the next element brought up to date
        self.count = 0  # frames held, up to the window
        self._levels = np.zeros(window_frames)  # each held frame's median reading: where the array's zero lies
        self._level_next = 0
        self._levels_held = 0

    def push(self, pressure_pa: np.ndarray, unloaded: bool = True) -> None:
        """A frame read between areas; ``unloaded``: no element reads contact, so it shows where the array's
        zero lies (:meth:`zero_pa`)."""
        reading = pressure_pa.ravel()
        if unloaded:
            self._levels[self._level_next] = _row_medians(reading[None])[0]
            self._level_next = (self._level_next + 1) % len(self._levels)
            self._levels_held = min(self._levels_held + 1, len(self._levels))
        if self.count:
            self._diffs[:, self._next] = reading - self._last
            self._next = (self._next + 1) % self._diffs.shape[1]
        self._last[:] = reading
        self.count = min(self.count + 1, self._diffs.shape[1] + 1)
        if self.count < NOISE_MIN_FRAMES:
            return
        if np.isnan(self._own).any():  # the first estimate, of every element, from the few frames held
            self._estimate(np.arange(len(self._own)))
            return
        turn = np.arange(self._turn, self._turn + ELEMENTS_PER_FRAME) % len(self._own)
        self._estimate(turn)
        self._turn = int(turn[-1] + 1) % len(self._own)

    def _estimate(self, elements: np.ndarray) -> None:
        diffs = self._diffs[elements, : self.count - 1]
        centred = diffs - _row_medians(diffs)[:, None]
        distance = np.abs(centred)
        # The median absolute deviation of a converter's readings moves in whole steps (at 50 Pa of noise on
        # 24 Pa steps it gave 51 Pa or 77 Pa): it only sets aside the frames that pressed or lifted off, and
        # the standard deviation of the rest is the estimate.
        kept = distance <= _OUTLIER_SIGMAS * _MAD_TO_SIGMA * _row_medians(distance)[:, None]
        spread = np.sqrt(np.sum(np.where(kept, centred, 0.0) ** 2, axis=1) / np.maximum(kept.sum(axis=1) - 1, 1))
        self._own[elements] = spread / np.sqrt(2.0)

    def zero_pa(self) -> float:
        """Where the unloaded array reads now: the median over the unloaded frames held of each frame's median
        element (a face in air reads its tare's zero plus noise; a drifting array reads its drift). NaN
        before any such frame."""
        if not self._levels_held:
            return float("nan")
        return float(np.median(self._levels[: self._levels_held]))

    def sigma_pa(self) -> np.ndarray | None:
        """Per-element noise standard deviation, never below the face's median (an element's own estimate
        from a few dozen frames can fall well short of its noise; one noisier than the rest keeps its own);
        None until NOISE_MIN_FRAMES frames are held."""
        if np.isnan(self._own).any():
            return None
        return np.maximum(self._own, _row_medians(self._own[None])[0]).reshape(self.shape)


def _row_medians(values: np.ndarray) -> np.ndarray:
    """Each row's median, by partition: np.median costs several times as much, on the 1 kHz loop's tick."""
    n = values.shape[1]
    half = n // 2
    if n % 2:
        return np.partition(values, half, axis=1)[:, half]
    parted = np.partition(values, (half - 1, half), axis=1)
    return 0.5 * (parted[:, half - 1] + parted[:, half])


def contact_thresholds(contact: ContactSettings, sigma_pa: np.ndarray,
                       out: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(onset, confirm) per element: the configured ones, raised to stand ONSET_NOISE_SIGMAS above each
    element's noise; confirm keeps its configured ratio to onset (the onset extrapolation uses both). ``out``:
    written in place (the loop does this on every frame between areas)."""
    onset, confirm = out if out is not None else (np.empty(sigma_pa.shape), np.empty(sigma_pa.shape))
    np.multiply(sigma_pa, ONSET_NOISE_SIGMAS, out=onset)
    np.maximum(onset, contact.onset_threshold_pa, out=onset)
    np.multiply(onset, contact.confirm_threshold_pa / contact.onset_threshold_pa, out=confirm)
    return onset, confirm


def element_analysis(
    pressure_pa: np.ndarray,
    onset_height_m: np.ndarray,
    tsi_z_m: float,
    onset_threshold_pa: np.ndarray | float,
    contact: ContactSettings,
    element_area_m2: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """(L0_m, dL_m, stiffness_pa, in_contact, tsi_indentation_m) for one pressure map at one height, with
    the onset threshold the contact was tracked with (per element, or one for all)."""
    L0 = onset_height_m - contact.table_height_m  # NaN where the onset is unknown
    in_contact = (pressure_pa >= onset_threshold_pa) & (L0 == L0)
    dL = np.where(in_contact, onset_height_m - tsi_z_m, np.nan)
    stiffness = stiffness_pa(pressure_pa * element_area_m2, L0, dL, element_area_m2, contact.min_indentation_m)
    n = np.count_nonzero(in_contact)
    # An element still reading after the face has risen above its onset (the array's creep and hysteresis
    # while the probe is lifted) is in no deeper than zero: the operator saw -8.2 mm while retracting.
    indentation = float(np.maximum(dL[in_contact], 0.0).sum() / n) if n else float("nan")
    return L0, dL, stiffness, in_contact, indentation


class StiffnessWindow:
    """How stiff the tissue under the face is: the least-squares slope of the total force against the face's
    height over the newest frames in contact, N per m of indentation (NaN until their forces span
    MIN_SPAN_N, far above the force's noise of a few mN: over less, the noise is the slope). The frames need
    not follow each other: a probe bouncing on stiff tissue is in contact for a few frames at a time."""

    MIN_SPAN_N = 0.25

    def __init__(self, frames: int = 8):
        self._z = np.full(frames, np.nan)
        self._f = np.full(frames, np.nan)
        self._i = 0

    def clear(self) -> None:
        self._z.fill(np.nan)
        self._f.fill(np.nan)

    def push(self, z_m: float, force_N: float) -> None:
        self._z[self._i], self._f[self._i] = z_m, force_N
        self._i = (self._i + 1) % len(self._z)

    def stiffness_N_m(self) -> float:
        z, f = self._z, self._f
        if np.isnan(z).any() or not np.isfinite(f).all() or np.ptp(f) < self.MIN_SPAN_N or np.ptp(z) <= 0.0:
            return float("nan")
        dz = z - z.mean()
        return float(-np.dot(dz, f - f.mean()) / np.dot(dz, dz))


class PoseHistory:
    """The slave's recent positions, to look up where the TSI was when a (late) frame was sampled."""

    def __init__(self, duration_s: float, rate_hz: float):
        n = max(4, int(np.ceil(duration_s * rate_hz)) + 2)
        self._t = np.full(n, -np.inf)
        self._p = np.zeros((n, 3))
        self._i = 0
        self._count = 0

    def push(self, t_s: float, position_m) -> None:
        i = self._i
        self._t[i] = t_s
        self._p[i] = position_m
        self._i = (i + 1) % len(self._t)
        self._count = min(self._count + 1, len(self._t))

    def at(self, t_s: float) -> tuple[float, float, float]:
        """Linear interpolation at t_s, clamped to the oldest / newest sample held."""
        count = self._count
        if count == 0:
            raise LookupError("no pose recorded yet")
        n = len(self._t)
        t, p = self._t, self._p
        newer = (self._i - 1) % n
        if t_s >= t[newer]:
            return tuple(p[newer].tolist())  # type: ignore[return-value]
        # frames lag the robot by tens of ms: walk back from the newest sample, a few steps at most
        for _ in range(count - 1):
            older = (newer - 1) % n
            t_old = t[older]
            if t_s >= t_old:
                w = (t_s - t_old) / (t[newer] - t_old)
                a, b = p[older].tolist(), p[newer].tolist()
                return (a[0] + w * (b[0] - a[0]), a[1] + w * (b[1] - a[1]), a[2] + w * (b[2] - a[2]))
            newer = older
        return tuple(p[newer].tolist())  # type: ignore[return-value]
