"""The simulated capacitive tactile array (15 x 4 elements of 2 mm, the paper's TSI).

Every ``1 / frame_rate_hz`` the array samples the tissue under the TSI where the robot had it at that
instant; the frame becomes readable ``latency_s`` later and carries the sampling instant as ``t_s`` and
the sample index as ``seq`` (a jump in ``seq`` is a frame the host never saw). Per element, in order:

1. true pressure ``p`` = the tissue model's element force / element area, seen through the sensor's
   compliant cover, which spreads load sideways by about its thickness (``cover_spread_m``, a Gaussian
   integrated over the 2 mm elements: it softens the rigid face's edge peaks; total force is kept);
2. creep ``c``: the dielectric relaxes under load, a first-order rise towards ``creep_fraction * p``
   with time constant ``creep_time_constant_s`` (and back when unloaded);
3. hysteresis ``p h (1 + s)``, ``h = 2 * hysteresis_fraction``: the dielectric reads higher on unloading
   than on loading. Each element keeps a memory ``s`` in [-1, 1] that its load's relative change moves,
   whatever the rate: rising from ``p0`` to ``p1`` gives ``s = -1 + (s + 1) p0 / p1``, falling gives
   ``s = 1 + (s - 1) p1 / p0``. The array is calibrated on loading (``s = -1`` reads ``p``); unloading
   from full scale reads ``p (1 + 2 h (1 - p / FS))``, a gap widest at half scale, where it is ``h FS / 2``
   = ``hysteresis_fraction * FS``, the datasheet's figure;
4. the raw reading ``offset + gain * (p + hysteresis + c) + noise``: a per-element zero offset and
   sensitivity fixed by the sensor's own seed, white noise from the run's seed;
5. quantisation to the converter step and saturation of the converter at ``[0, full_scale +
   zero_offset]``, so a tared element saturates at about full scale;
6. minus the tare (the raw reading taken as zero), giving the calibrated, tared pressure.

On connection the array takes its first frame as zero, as acquisition software does on start-up, unless
an unloaded array could not give it (:func:`~hardware.interfaces.tare_problem`: the probe starts pressed
into the tissue): then nothing is taken as zero and ``tare_refused`` says why. :meth:`tare` takes the
latest frame's reading instead, under the same rule. An element whose converter is at its limit is
flagged saturated in the frame.

A frame is computed half-way through its latency (at the first poll after ``t_s + latency_s / 2``), not
at its sampling instant: what it describes is fixed by ``t_s`` alone (the world keeps its recent
trajectory), and at the default 100 frames/s with 10 ms latency the sampling instant of one frame is the
delivery instant of the one before, so computing it then would put the simulator's heaviest work on the
same control tick as the loop's frame analysis.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from hardware.interfaces import DeviceError, TactileConstraints, TactileFrame, TactileSensor, tare_problem
from hardware.sim.world import SimDevice, SimWorld
from tissue.face import cover_operators, cover_weight

LOADED_PA = 10.0  # an element under less than this carries no press (a fraction of the array's noise)
PRESS_STEP_M = 0.1e-3  # how much deeper the tissue is asked, to read its stiffness under each element
# A press's offset was measured from 2 mm deep on (docs/phantoms.md, section 2, item 12), and at rest the real
# array reads within 0.02 % of full scale: an element touched 0.05 mm deep cannot read as if 0.7 mm deeper (on
# a stiff cushion that was 1 N out of nothing, and the loop rightly took the collapse that followed for a dead
# array). The offset grows in over this much of the element's own depth.
PRESS_ONSET_M = 1e-3


class SimTactileSensor(SimDevice, TactileSensor):
    name = "sim-tsi"

    def __init__(self, world: SimWorld, seed: int = 0):
        super().__init__(world)
        s = world.settings.sensor
        self.settings = s
        self.constraints = TactileConstraints(full_scale_pa=s.full_scale_pa, frame_rate_hz=s.frame_rate_hz,
                                              latency_s=s.latency_s, cover_spread_m=s.stated_cover_spread_m)
        shape = self.constraints.shape
        self._cover_rows, self._cover_cols = cover_operators(
            cover_weight(s.cover_spread_m, self.constraints.pitch_m), shape)
        made = np.random.default_rng(s.seed)
        # log-normal: a relative spread that can never make an element's sensitivity negative
        self._gain = np.exp(s.gain_spread * made.standard_normal(shape))
        self._offset_pa = np.clip(s.zero_offset_pa + s.zero_offset_spread_pa * made.standard_normal(shape), 0.0, None)
        # this session's move of the rest offsets since the array was made (the tare takes it out)
        self._offset_pa += s.session_offset_fraction * s.full_scale_pa * np.random.default_rng(
            [seed, 2]).uniform(-1.0, 1.0, shape)
        self._noise = np.random.default_rng(seed)
        # presses (see _pressed): their own draws, so that white noise alone is the same with or without them
        self._presses = np.random.default_rng([seed, 1])
        self._press_m = np.zeros(shape)  # each element's offset for the press it is in
        self._pressed = np.zeros(shape, dtype=bool)
        self._released_s = np.full(shape, -np.inf)  # when each element was last unloaded
        self._face_press_m = 0.0
        self._area_m2 = self.constraints.element_area_m2
        self._raw_max_pa = s.full_scale_pa + s.zero_offset_pa
        # frames in flight: [readable at, seq, sampling instant, raw reading (None until computed)]
        self._in_flight: deque[list] = deque()
        self._backlog = int(math.ceil(s.latency_s * s.frame_rate_hz)) + 1
        self._next_index: int | None = None
        self._creep_pa = np.zeros(shape)
        self._creep_t: float | None = None
        self._memory = np.ones(shape)  # hysteresis: unloaded last
        self._memory_load_pa = np.zeros(shape)
        self._zero_pa: np.ndarray | None = None
        self._latest: TactileFrame | None = None
        self._latest_raw: np.ndarray | None = None
        self.tare_refused = ""  # why the first frame was not taken as zero on connection

    @property
    def gain_pattern(self) -> np.ndarray:
        """Each element's sensitivity as the array was made (what a calibration should find)."""
        return self._gain.copy()

    def _on_open(self) -> None:
        self._in_flight.clear()
        self._next_index = None
        self._zero_pa = None
        self.tare_refused = ""

    def close(self) -> None:
        super().close()
        self._in_flight.clear()

    def latest(self) -> TactileFrame | None:
        return self._latest

    def tare(self) -> None:
        """Zero every element at its latest reading; DeviceError (nothing changed) if there is none or an
        unloaded array could not give it."""
        raw, frame = self._latest_raw, self._latest
        if raw is None or frame is None:
            raise DeviceError("sim tactile sensor: no frame has arrived yet to take as zero")
        problem = tare_problem(raw, frame.saturated, self.constraints.full_scale_pa)
        if problem is not None:
            raise DeviceError(f"sim tactile sensor: not tared: {problem}")
        self._zero_pa = raw.copy()

    def true_pressure_pa(self, t_s: float) -> np.ndarray:
        """What an ideal array would read at ``t_s``: the tissue model's forces over the element area,
        through the cover, before creep, gain, noise and the converter (the first stage of every frame)."""
        x, y, z = self.world.state_at(t_s)[0]
        forces = np.asarray(self.world.tissue.element_forces_N(x, y, z), dtype=float)
        if forces.shape != self.constraints.shape or not math.isfinite(forces.sum()):
            problem = "non-finite forces" if forces.shape == self.constraints.shape else f"shape {forces.shape}"
            raise DeviceError(f"sim tactile sensor: the tissue model {type(self.world.tissue).__name__} returned "
                              f"{problem} at ({x:.4f}, {y:.4f}, {z:.4f}) m; it must return finite "
                              f"{self.constraints.shape} forces")
        return self._through_cover(forces / self._area_m2)

    def poll(self, now_s: float) -> None:
        world = self.world
        world.advance(now_s)
        if not self.connected:
            return
        rate = self.constraints.frame_rate_hz
        newest = world.instant_index(rate)
        if self._next_index is None:
            self._next_index = newest
        latency = self.settings.latency_s
        in_flight = self._in_flight
        # frames sampled long before now are superseded by newer ones before the host could read them
        for k in range(max(self._next_index, newest - self._backlog), newest + 1):
            t = world.instant_s(k, rate)
            in_flight.append([t + latency, k, t, None])
        self._next_index = max(self._next_index, newest + 1)
        # in sampling order: the creep state carries from one frame to the next
        for frame in in_flight:
            if frame[3] is None:
                if frame[2] + 0.5 * latency > now_s and frame[0] > now_s:
                    break
                frame[3] = self._sample(frame[2])
        while in_flight and in_flight[0][0] <= now_s:
            _, seq, t, raw = in_flight.popleft()
            saturated = raw >= self._raw_max_pa
            if self._zero_pa is None:
                problem = tare_problem(raw, saturated, self.constraints.full_scale_pa)
                self._zero_pa = raw.copy() if problem is None else np.zeros_like(raw)
                self.tare_refused = "" if problem is None else f"not tared on connection: {problem}"
            self._latest_raw = raw
            self._latest = TactileFrame(seq=seq, t_s=t, pressure_pa=raw - self._zero_pa, saturated=saturated)

    def _sample(self, t_s: float) -> np.ndarray:
        # in place where it can be: this runs on a control tick, and every temporary costs a microsecond
        s = self.settings
        p = self.true_pressure_pa(t_s)
        if s.press_offset_m or s.press_offset_element_m or s.first_press_m:
            p = self._pressed_pa(p, t_s)
        creep = self._creep_pa
        if self._creep_t is not None:
            # exact first-order update, taking the load over the interval to be the one sampled at its end
            decay = math.exp(-max(t_s - self._creep_t, 0.0) / s.creep_time_constant_s)
            creep *= decay
            creep += (s.creep_fraction * (1.0 - decay)) * p
        self._creep_t = t_s
        self._hysteresis(p)
        p *= 1.0 + 2.0 * s.hysteresis_fraction * (1.0 + self._memory)
        raw = np.add(p, creep, out=p)
        raw *= self._gain
        raw += self._offset_pa
        if s.noise_std_pa > 0:
            raw += s.noise_std_pa * self._noise.standard_normal(raw.shape)
        if s.quantisation_pa > 0:
            raw /= s.quantisation_pa
            np.round(raw, out=raw)
            raw *= s.quantisation_pa
        return np.clip(raw, 0.0, self._raw_max_pa, out=raw)

    def _pressed_pa(self, p: np.ndarray, t_s: float) -> np.ndarray:
        """``p`` as each loaded element reads it in its current press: as if the face stood deeper by the
        press's offset. A press begins when an unloaded element is loaded; its offset is drawn then: the
        face's (when it was unloaded throughout), the element's own, and the first-press excess, which grows
        back while the element rests unloaded. The reading moves by the element's own stiffness times the
        offset (the tissue's response to a little more depth), in full from ``PRESS_ONSET_M`` deep, never below
        zero."""
        s = self.settings
        loaded = p > LOADED_PA
        if loaded.any() and not self._pressed.any():
            self._face_press_m = s.press_offset_m * float(self._presses.standard_normal())
        begun = loaded & ~self._pressed
        if begun.any():
            rest = t_s - self._released_s[begun]
            self._press_m[begun] = (self._face_press_m
                                    + s.press_offset_element_m * self._presses.standard_normal(int(begun.sum()))
                                    + s.first_press_m * -np.expm1(-rest / s.first_press_recovery_s))
        self._released_s[self._pressed & ~loaded] = t_s
        self._pressed = loaded
        if not loaded.any():
            return p
        x, y, z = self.world.state_at(t_s)[0]
        deeper = self._through_cover(np.asarray(self.world.tissue.element_forces_N(x, y, z - PRESS_STEP_M),
                                                dtype=float) / self._area_m2)
        stiffness = (deeper - p) / PRESS_STEP_M  # Pa per m of depth
        # the offset fades in over the element's first PRESS_ONSET_M of depth (p / stiffness, its secant depth)
        gained = self._press_m * np.minimum(stiffness, p / PRESS_ONSET_M)
        return np.where(loaded, np.maximum(p + gained, 0.0), p)

    def _hysteresis(self, p: np.ndarray) -> None:
        """Move each element's hysteresis memory by its load's relative change since the last frame."""
        before = self._memory_load_pa
        # the share of the memory a change keeps, p0 / p1 rising and p1 / p0 falling: the smaller load over
        # the larger (an element unloaded throughout keeps it all)
        larger = np.maximum(p, before)
        kept = np.divide(np.minimum(p, before), larger, out=np.ones_like(p), where=larger > 0)
        target = np.where(p > before, -1.0, 1.0)
        memory = self._memory
        memory -= target
        memory *= kept
        memory += target
        before[...] = p

    def _through_cover(self, p: np.ndarray) -> np.ndarray:
        """Spread each element's load to its neighbours along both axes; edge elements keep what would
        leave the array, so the total force is unchanged."""
        return self._cover_rows @ p @ self._cover_cols
