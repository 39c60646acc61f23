"""The autopilot: palpates a phantom's areas one after another, as the paper's operator did (Section IV-A).

For each area, in order: raise the TSI to the travel height, move above the area, lower it to the approach
height (a clearance above the highest surface point under the TSI's face), switch S_z to force control so
the loop runs the Fig. 4 ramp, and wait for "region done" and the retract; then the next area. After the
last area the TSI is raised to the travel height again.

It is plain logic without Qt and without a clock of its own: :meth:`Autopilot.update` is called with each
display-rate snapshot (the latest tick row and the events since the previous one) and returns the typed
commands to send (``Jog``, ``SetRegion``, ``SetSz``). Every move is one ``Jog`` of the whole distance,
computed from the X_d the loop reports, so the loop's jog rate limit paces it; a move is over once X_d
is at the target and the robot has followed. Anything unexpected stops the autopilot with the reason: a
fault, a refused command, an area aborted or timed out, a phase it did not cause, a move that does not
arrive. It never retries on its own: the operator reads why and decides.

Plans are built from a map of the tissue's surface (:func:`plan_from_surface`): the composition root makes
one from a simulated rig's phantom file (:func:`app.rigs.plan_for_rig`); real hardware has no phantom file,
so the autopilot is unavailable there unless a plan is built by hand.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from control.messages import (
    CancelJog,
    Command,
    CommandRefused,
    FaultRaised,
    Jog,
    LevelTimedOut,
    RegionAborted,
    RegionDone,
    SetRegion,
    SetSz,
)
from hardware.interfaces import Phase, TactileConstraints

# A move has arrived when X_d is at the target (to rounding) and the robot is within this of it.
ARRIVAL_TOLERANCE_M = 0.3e-3
# A move is given its nominal time at the jog speed, times this, plus the fixed allowance, to arrive.
MOVE_TIME_FACTOR = 1.5
MOVE_ALLOWANCE_S = 3.0
COMMAND_TIMEOUT_S = 30.0  # a jog the controller neither refused nor started within this is lost
_OUR_COMMANDS = (Jog, SetRegion, SetSz)


class AutopilotError(ValueError):
    """An invalid plan or start request; the message says what is wrong."""


@dataclass(frozen=True)
class Area:
    """One palpation area: where the TSI centre goes (tissue frame) and how low it descends before S_z = 0."""

    index: int  # the region number the loop records it under
    x_m: float
    y_m: float
    approach_z_m: float


@dataclass(frozen=True)
class AutopilotPlan:
    areas: tuple[Area, ...]
    travel_z_m: float  # height for moves between areas, above every approach height
    jog_speed_m_s: float  # the loop's jog rate limit (ControlConfig.master.jog_speed_m_s), to time moves
    phantom_extent_m: tuple[float, float, float, float] | None = None  # (x0, x1, y0, y1) of the phantom, if known

    def __post_init__(self):
        if not self.areas:
            raise AutopilotError("the plan has no areas to palpate")
        values = [self.travel_z_m, self.jog_speed_m_s] + [v for a in self.areas for v in (a.x_m, a.y_m, a.approach_z_m)]
        if not all(math.isfinite(v) for v in values):
            raise AutopilotError("the plan contains a value that is not a finite number")
        if self.jog_speed_m_s <= 0:
            raise AutopilotError(f"jog speed must be > 0, got {self.jog_speed_m_s:g} m/s")
        highest = max(a.approach_z_m for a in self.areas)
        if self.travel_z_m <= highest:
            raise AutopilotError(f"travel height {self.travel_z_m * 1e3:.1f} mm does not clear the highest approach "
                                 f"height {highest * 1e3:.1f} mm")


class SurfaceMap(Protocol):
    """What a plan needs to know of the tissue (a simulated rig's phantom; on a real rig, a surface map from
    imaging): where the areas are, how high the surface is under the face, and the tissue's extent."""

    length_m: float
    width_m: float

    def palpation_regions(self, tsi_length_x_m: float) -> tuple[tuple[float, float], ...]: ...

    def highest_surface_m(self, x_m: float, y_m: float, face_size_m: tuple[float, float]) -> float: ...


def plan_from_surface(surface: SurfaceMap, sensor: TactileConstraints, *, clearance_m: float, travel_z_m: float,
                      jog_speed_m_s: float) -> AutopilotPlan:
    """The surface's palpation areas in order, numbered from 0, each approached ``clearance_m`` above the
    highest point under the TSI's face."""
    face = sensor.size_m
    areas = tuple(Area(i, float(x), float(y), surface.highest_surface_m(x, y, face) + clearance_m)
                  for i, (x, y) in enumerate(surface.palpation_regions(face[0])))
    return AutopilotPlan(areas, travel_z_m, jog_speed_m_s, (0.0, surface.length_m, 0.0, surface.width_m))


class AutopilotState(enum.Enum):
    IDLE = "idle"  # never started
    RUNNING = "running"
    FINISHED = "finished"  # every area of the run palpated, TSI back at the travel height
    STOPPED = "stopped"  # by the operator or by something unexpected; ``message`` says which


class _Kind(enum.Enum):
    RAISE = "raising the TSI"
    MOVE = "moving above"
    DESCEND = "lowering the TSI onto"
    PALPATE = "palpating"


@dataclass
class _Step:
    kind: _Kind
    area: Area | None  # None: the final raise
    target_m: tuple[float, float, float] | None = None  # moves: set when commanded
    deadline_s: float = math.inf  # moves: set once the controller is seen carrying the move out
    sent_s: float = math.inf  # moves: when the jog was sent
    start_m: tuple[float, float, float] | None = None  # moves: X_d when the jog was sent
    commanded: bool = False
    region_done: bool = False
    done_tick: int = -1  # palpation: the first tick seen in DONE after "region done"


class Autopilot:
    """Drive it with :meth:`update` on every snapshot; send what it returns. See the module docstring."""

    def __init__(self, plan: AutopilotPlan):
        if not isinstance(plan, AutopilotPlan):
            raise TypeError(f"plan must be an AutopilotPlan, got {type(plan).__name__}")
        self.plan = plan
        self.state = AutopilotState.IDLE
        self.message = "ready"
        self.done_areas: list[int] = []  # indices of the areas finished in this run
        self._steps: list[_Step] = []

    # ---- operator -----------------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self.state is AutopilotState.RUNNING

    def start(self, first_area: int = 0) -> list[Command]:
        """Palpate the plan's areas from position ``first_area`` (0-based) to the last."""
        n = len(self.plan.areas)
        if self.running:
            raise AutopilotError("the autopilot is already running")
        if isinstance(first_area, bool) or not isinstance(first_area, int) or not 0 <= first_area < n:
            raise AutopilotError(f"there is no area {first_area!r} to start at: the plan has areas 0 to {n - 1}")
        self._steps = []
        for area in self.plan.areas[first_area:]:
            self._steps += [_Step(_Kind.RAISE, area), _Step(_Kind.MOVE, area), _Step(_Kind.DESCEND, area),
                            _Step(_Kind.PALPATE, area)]
        self._steps.append(_Step(_Kind.RAISE, None))
        self.done_areas = []
        self.state = AutopilotState.RUNNING
        self.message = f"starting at area {first_area + 1} of {n}"
        return []

    def stop(self, reason: str = "stopped by the operator") -> list[Command]:
        """Stop here. A move under way is cancelled where X_d is when the controller takes the command; a
        ramp under way is left to the operator, who owns S_z again."""
        if not self.running:
            return []
        step = self._steps[0] if self._steps else None
        commands: list[Command] = [CancelJog()] if step is not None and step.commanded else []
        self._halt(reason)
        return commands

    # ---- driving ------------------------------------------------------------------------------------

    def update(self, tick: np.ndarray, events: Iterable = ()) -> list[Command]:
        """One display-rate update: ``tick`` is the latest TICK_DTYPE row, ``events`` those since the last call."""
        if not self.running:
            return []
        for event in events:
            self._on_event(event)
            if not self.running:
                return []
        if int(tick["fault"]) != 0:
            self._halt("a fault holds the robot")
            return []
        commands: list[Command] = []
        # several steps may end in one update (a move already at its target ends at once)
        while self.running and self._steps:
            step = self._steps[0]
            issued = self._advance(step, tick)
            if issued is None:
                break
            commands += issued
            if self._steps and self._steps[0] is step:
                break  # commanded and under way
        if self.running and not self._steps:
            self.state = AutopilotState.FINISHED
            self.message = f"done: {len(self.done_areas)} areas palpated"
        return commands

    def _on_event(self, event) -> None:
        step = self._steps[0] if self._steps else None
        if isinstance(event, FaultRaised):
            self._halt(f"fault: {event.message}")
        elif isinstance(event, CommandRefused) and isinstance(event.command, _OUR_COMMANDS):
            self._halt(f"the controller refused {event.command_name}: {event.reason}")
        elif step is None or step.kind is not _Kind.PALPATE or not step.commanded:
            return
        elif isinstance(event, RegionDone) and event.region == step.area.index:
            step.region_done = True
        elif isinstance(event, (RegionAborted, LevelTimedOut)):
            why = event.reason if isinstance(event, RegionAborted) else event.message
            self._halt(f"area {step.area.index + 1} was not finished: {why}")

    def _advance(self, step: _Step, tick: np.ndarray) -> list[Command] | None:
        """Commands to issue for ``step``; pops it when it is over. None: wait for the next update."""
        phase = int(tick["phase"])
        t_s = float(tick["t_s"])
        x_des = np.array(tick["x_des_m"], dtype=float)
        if step.kind is _Kind.PALPATE:
            return self._palpate(step, phase, int(tick["tick"]))
        if not step.commanded:
            if not Phase(phase).idle:
                if phase == Phase.RETRACT:
                    return None  # the loop is still lifting the TSI after the last area
                self._halt(f"the loop is in phase {Phase(phase).name}, not waiting for the operator; "
                           "someone else is driving")
                return None
            target = self._target(step, x_des)
            delta = np.asarray(target) - x_des
            distance = float(np.linalg.norm(delta))
            step.target_m, step.commanded = target, True
            if distance < 1e-6:
                self._steps.pop(0)
                return []
            step.sent_s, step.start_m = t_s, tuple(float(v) for v in x_des)
            self.message = self._describe(step)
            return [Jog(tuple(float(v) for v in delta))]
        if not Phase(phase).idle:
            self._halt(f"the loop left position control ({Phase(phase).name}) during a move")
            return None
        arrived = (np.abs(x_des - step.target_m).max() < 1e-6
                   and np.abs(np.asarray(tick["x_slave_m"]) - step.target_m).max() < ARRIVAL_TOLERANCE_M)
        if arrived:
            self._steps.pop(0)
            return []
        if step.deadline_s == math.inf:
            if np.abs(x_des - step.start_m).max() > 1e-9:
                # the clock starts when the controller takes the jog: commands reach it with a delay
                # that the display rate and the host's load set, not the move
                nominal = float(np.linalg.norm(np.subtract(step.target_m, step.start_m))) / self.plan.jog_speed_m_s
                step.deadline_s = t_s + MOVE_TIME_FACTOR * nominal + MOVE_ALLOWANCE_S
            elif t_s - step.sent_s > COMMAND_TIMEOUT_S:
                self._halt(f"the controller did not start the move to {_mm3(step.target_m)} "
                           f"within {COMMAND_TIMEOUT_S:g} s")
        elif t_s > step.deadline_s:
            self._halt(f"the TSI did not reach {_mm3(step.target_m)} in time (it is at {_mm3(tick['x_slave_m'])})")
        return None

    def _palpate(self, step: _Step, phase: int, tick_index: int) -> list[Command] | None:
        area = step.area
        if not step.commanded:
            if not Phase(phase).idle:
                self._halt(f"the loop is in phase {Phase(phase).name}; cannot start area {area.index + 1}")
                return None
            step.commanded = True
            self.message = self._describe(step)
            return [SetRegion(area.index), SetSz(position_control=False)]
        if step.region_done and phase == Phase.DONE:
            # The tick that finishes the retract still reports X_d from before the loop re-anchored it on
            # the robot; moves are computed from X_d, so wait for a later tick.
            if step.done_tick < 0:
                step.done_tick = tick_index
            elif tick_index > step.done_tick:
                self.done_areas.append(area.index)
                self._steps.pop(0)
                return []
        return None

    # ---- helpers ------------------------------------------------------------------------------------

    def _target(self, step: _Step, x_des: np.ndarray) -> tuple[float, float, float]:
        travel = self.plan.travel_z_m
        if step.kind is _Kind.RAISE:  # never lower: above the travel height is clear too
            return (float(x_des[0]), float(x_des[1]), max(travel, float(x_des[2])))
        area = step.area
        if step.kind is _Kind.MOVE:
            return (area.x_m, area.y_m, travel)
        return (area.x_m, area.y_m, area.approach_z_m)

    def _describe(self, step: _Step) -> str:
        n = len(self.plan.areas)
        if step.area is None:
            return "raising the TSI after the last area"
        where = f"area {step.area.index + 1} of {n}"
        if step.kind is _Kind.RAISE:
            return f"raising the TSI before {where}"
        return f"{step.kind.value} {where}"

    def _halt(self, reason: str) -> None:
        self.state = AutopilotState.STOPPED
        self.message = reason
        self._steps = []


def _mm3(v) -> str:
    return "(" + ", ".join(f"{float(c) * 1e3:.1f}" for c in v) + ") mm"
