"""A scripted operator at the master device, following the paper's protocol (Section IV-A).

For each palpation area of the phantom, in order: with the switch ON (S_z = 1, position control) move at
travel height to above the area, descend to ``clearance_m`` above the highest surface point under the
TSI's footprint (the operator sees the tissue through the camera), steady there, switch OFF (S_z = 0: the
loop approaches and ramps the force under force control), wait for the loop to report the area done
(or a fault, or the phase falling back to APPROACH after an abort), switch ON, rise to travel height and
go on to the next area. After the last area it returns home and reports :attr:`finished`.

An area whose seek ended without touching anything (the loop aborted it from SEEK_CONTACT: no tissue within
the blind seek's depth) is tried once more, from lower down: the face brought level with the highest point
the camera shows under it where it now is. The camera samples the surface every 0.5 mm and the tissue
touches the face at its mesh's nodes, so the end of a ridge under the face's last few tenths of a
millimetre set an approach height the seek could not reach down from (a held-out study phantom,
s48002-0000; there the second seek touched that end with the face's edge and was stopped by the loop's
"tactile force not rising" guard, so the area stays lost). Once only: a second seek that touches nothing
means the camera and the array disagree, which going lower does not settle. A seek that starts there is
as safe as one that starts on the tissue, which the blind seek's depth allows for
(control.safety.blind_seek_depth_m).

Positions are the hand's, in the master's frame, which the loop's default mapping (scale 1) carries into
the tissue frame up to its clutch offset; they are sampled at ``rate_hz`` on the world's clock, each
reading with its sequence number and instant. Every move is a
minimum-jerk profile, the smooth bell-shaped speed of a human reach, timed so its peak speed is the
configured lateral or vertical speed.

The operator's targets are where it wants the TSI, which it sees on the camera. When the loop hands z
back after an area it re-clutches the z offset (wherever the TSI is then, possibly still on its way up),
and clearing a fault re-clutches every axis, so after each area the operator lines its hand up with the
TSI it sees and aims its moves accordingly, as a person at a clutched master does. After a fault it waits
until the fault is cleared before it looks: lined up before the clear, it aimed with an offset the clear then
changed, and took the probe 10 mm into the tissue under position control on its way to the next area.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hardware.interfaces import (
    MasterConstraints,
    MasterDevice,
    MasterFeedback,
    MasterState,
    Phase,
    TactileConstraints,
    Vec3,
)
from hardware.settings import ConfigError
from hardware.sim.world import SimDevice, SimWorld

_MIN_JERK_PEAK = 1.875  # peak speed of a minimum-jerk move = 1.875 * distance / duration
_ENGAGED = frozenset({Phase.SEEK_CONTACT, Phase.SETTLING, Phase.RETRACT, Phase.HOLD})


@dataclass(frozen=True, slots=True)
class RegionOutcome:
    index: int
    centre_xy_m: tuple[float, float]
    result: str  # "done" | "aborted" | "fault" | "timeout"
    switched_off_s: float
    ended_s: float


@dataclass(frozen=True, slots=True)
class _Step:
    kind: str  # "move" | "dwell" | "await"
    target_m: Vec3  # moves: where the operator wants the TSI, in the tissue frame
    duration_s: float  # dwells: their length; "await": the give-up time-out; moves: timed when they start
    sz: bool
    region: int  # the area this step belongs to, -1 on the way home
    look: bool = False  # moves: first line the hand up with where the camera shows the TSI
    look_z: bool = False  # moves: first line the hand's height up with the TSI's (its side to side is kept)


def _min_jerk(tau: float) -> float:
    return tau * tau * tau * (10.0 + tau * (-15.0 + 6.0 * tau))


class ScriptedOperator(SimDevice, MasterDevice):
    name = "sim-operator"

    def __init__(self, world: SimWorld, sensor: TactileConstraints | None = None):
        super().__init__(world)
        self.settings = world.settings.operator
        self.constraints = MasterConstraints(rate_hz=self.settings.rate_hz, has_sz_switch=True)
        self._sensor = sensor if sensor is not None else TactileConstraints()
        self.regions = world.phantom.palpation_regions(self._sensor.size_m[0])
        self.home_m: Vec3 = world.settings.robot.home_m
        face = self._sensor.size_m
        self.approach_heights_m = tuple(world.phantom.highest_surface_m(x, y, face) + self.settings.clearance_m
                                        for x, y in self.regions)
        self._check_heights()
        self._steps = self._plan()
        self._index = 0
        self._step_t0: float | None = None  # start of the current step; None until the first reading
        self._hand_m: Vec3 = self.home_m  # where the current step starts
        self._hand_to_m: Vec3 = self.home_m  # where the current move ends
        self._move_s = 0.0
        self._camera_offset_m: Vec3 = (0.0, 0.0, 0.0)  # TSI seen minus hand, at the last look
        self._resolved_s: float | None = None
        self._engaged = False
        self._touched = False  # the area being awaited got past SEEK_CONTACT
        self._retried: set[int] = set()  # areas tried again after a seek that touched nothing
        self._faulted = False  # the loop's newest feedback says a fault is latched
        self._cleared_s = -math.inf  # when the latest fault was seen cleared
        self._last_t = -math.inf
        self._last_seq = -1
        self._latest: MasterState | None = None
        self.region_index = -1  # the area being worked on (or last worked on)
        self.outcomes: list[RegionOutcome] = []

    # ---- planning ------------------------------------------------------------------------------------

    def _check_heights(self) -> None:
        travel = self.settings.travel_height_m
        highest = max(self.approach_heights_m)
        if travel <= highest:
            raise ConfigError("operator.travel_height_m",
                              f"{travel * 1e3:g} mm does not clear phantom {self.world.phantom.name!r}: the approach "
                              f"height above its highest area is {highest * 1e3:.1f} mm (surface + clearance)")
        ceiling = self.world.settings.robot.workspace_max_m[2]
        if travel > ceiling:
            raise ConfigError("operator.travel_height_m",
                              f"{travel * 1e3:g} mm is above the robot's workspace (z <= {ceiling * 1e3:g} mm)")

    def _plan(self) -> list[_Step]:
        s = self.settings
        travel = s.travel_height_m
        steps: list[_Step] = []
        x, y = self.home_m[0], self.home_m[1]
        for i, ((rx, ry), z_approach) in enumerate(zip(self.regions, self.approach_heights_m)):
            # after an area the loop has re-clutched z (and a cleared fault every axis): look first
            steps.append(_Step("move", (x, y, travel), 0.0, True, i, look=i > 0))
            x, y = rx, ry
            steps.append(_Step("move", (x, y, travel), 0.0, True, i))
            # and again before the descent: the loop hands z back once its lift is over, which may be after the
            # first look, and a hand aimed with the offset from before it stopped millimetres short of the approach
            # height, beyond where a seek may go (control.safety.blind_seek_depth_m)
            steps.append(_Step("move", (x, y, z_approach), 0.0, True, i, look_z=True))
            steps.append(_Step("dwell", (x, y, z_approach), s.dwell_above_s, True, i))
            steps.append(_Step("await", (x, y, z_approach), s.region_timeout_s, False, i))
            steps.append(_Step("dwell", (x, y, z_approach), s.dwell_after_s, False, i))
        steps.append(_Step("move", (x, y, travel), 0.0, True, -1, look=True))
        steps.append(_Step("move", (self.home_m[0], self.home_m[1], travel), 0.0, True, -1))
        steps.append(_Step("move", self.home_m, 0.0, True, -1))
        return steps

    # ---- running the script --------------------------------------------------------------------------

    @property
    def finished(self) -> bool:
        """True once the operator is back home after the last area."""
        return self._index >= len(self._steps)

    def _step_end_s(self, step: _Step) -> float:
        if step.kind == "move":
            return self._step_t0 + self._move_s
        if step.kind == "await" and self._resolved_s is not None:
            return self._resolved_s
        if step.kind == "dwell" and self._faulted:
            return math.inf  # the operator clears the fault first (whoever does, the script waits for it)
        return max(self._step_t0 + step.duration_s, self._cleared_s)

    def _enter(self, index: int, t0: float) -> None:
        if self._step_t0 is not None:
            self._hand_m = self._position_at(t0)[0]
        self._index, self._step_t0 = index, t0
        if self.finished:
            return
        step = self._steps[index]
        if step.region >= 0:
            self.region_index = step.region
        if step.kind == "await":
            self._resolved_s = None
            self._engaged = False
            self._touched = False
        elif step.kind == "move":
            self._start_move(step, t0)

    def _start_move(self, step: _Step, t0: float) -> None:
        """Aim the hand so the TSI ends at the target, as the operator would by watching the camera."""
        hand = self._hand_m
        if step.look or step.look_z:
            tsi = self.world.state_at(t0)[0]
            c = self._camera_offset_m
            self._camera_offset_m = ((tsi[0] - hand[0], tsi[1] - hand[1]) if step.look else c[:2]) + (tsi[2] - hand[2],)
        c = self._camera_offset_m
        to = (step.target_m[0] - c[0], step.target_m[1] - c[1], step.target_m[2] - c[2])
        s = self.settings
        lateral = math.hypot(to[0] - hand[0], to[1] - hand[1])
        vertical = abs(to[2] - hand[2])
        self._hand_to_m = to
        self._move_s = _MIN_JERK_PEAK * max(lateral / s.lateral_speed_m_s, vertical / s.vertical_speed_m_s)

    def _run_to(self, t: float) -> None:
        if self._step_t0 is None:
            self._enter(0, t)
        while not self.finished:
            step = self._steps[self._index]
            end = self._step_end_s(step)
            if end > t:
                break
            if step.kind == "await" and self._resolved_s is None:
                self._conclude("timeout", end)
            self._enter(self._index + 1, end)

    def _position_at(self, t: float) -> tuple[Vec3, bool]:
        if self.finished:
            return self._hand_m, True
        step = self._steps[self._index]
        if step.kind != "move" or self._move_s <= 0.0:
            return self._hand_m, step.sz
        f = _min_jerk(min(max((t - self._step_t0) / self._move_s, 0.0), 1.0))
        a, b = self._hand_m, self._hand_to_m
        return (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2])), step.sz

    def _conclude(self, result: str, t: float) -> None:
        self._resolved_s = t
        i = self.region_index
        self.outcomes.append(RegionOutcome(i, self.regions[i], result, self._step_t0, t))

    # ---- the device ----------------------------------------------------------------------------------

    def latest(self) -> MasterState | None:
        return self._latest

    def poll(self, now_s: float) -> None:
        sample = self._next_sample(now_s, self.constraints.rate_hz, self._last_seq)
        if sample is None:
            return
        m, t = sample
        self._run_to(t)
        position, sz = self._position_at(t)
        self._latest = MasterState(seq=m, t_s=t, position_m=position, sz_switch=sz)
        self._last_seq, self._last_t = m, t

    def feedback(self, fb: MasterFeedback) -> None:
        """Watches for the end of the area being palpated; everything else the operator only looks at."""
        if self.finished or self._step_t0 is None or fb.t_s < self._step_t0:
            return
        if self._faulted and not fb.faulted:
            self._cleared_s = max(fb.t_s, self._last_t)
        self._faulted = fb.faulted
        if self._steps[self._index].kind != "await" or self._resolved_s is not None:
            return
        if fb.phase in _ENGAGED:
            self._engaged = True
        if fb.phase == Phase.SETTLING:
            self._touched = True  # the seek found the tissue
        if fb.faulted:
            result = "fault"
        elif self._engaged and fb.region_done:
            result = "done"
        elif self._engaged and fb.phase == Phase.APPROACH:
            result = "aborted"
        else:
            return
        # never before a reading already given out, so the script's clock only moves forwards
        t = max(fb.t_s, self._last_t)
        self._conclude(result, t)
        if result == "aborted" and not self._touched and self.region_index not in self._retried:
            self._try_again_lower(t)

    def _try_again_lower(self, t: float) -> None:
        """After the area's closing dwell, the area once more from the highest surface point the camera
        shows under the TSI where it now is (the module docstring)."""
        self._retried.add(self.region_index)
        await_step = self._steps[self._index]
        tsi = self.world.state_at(t)[0]
        x, y = await_step.target_m[0], await_step.target_m[1]
        z = self.world.phantom.highest_surface_m(tsi[0], tsi[1], self._sensor.size_m)
        if not z < await_step.target_m[2]:
            return
        s, i = self.settings, self.region_index
        again = [_Step("move", (x, y, z), 0.0, True, i, look=True),
                 _Step("dwell", (x, y, z), s.dwell_above_s, True, i),
                 _Step("await", (x, y, z), s.region_timeout_s, False, i),
                 _Step("dwell", (x, y, z), s.dwell_after_s, False, i)]
        after = self._index + 2  # the await, then its closing dwell
        self._steps[after:after] = again
