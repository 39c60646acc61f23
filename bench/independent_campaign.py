"""Issue 49's independent campaign: the real loop, driven as the console drives it, on a plant of its own.

``bench/safety_campaign.py`` checks the loop against ``hardware/sim/plant.py``; a mistake shared by that plant
and the loop (how a robot brakes, when a frame is sampled, how tissue stiffens) would pass both. This campaign
shares none of that physics. It imports from the project only what the console itself is made of (the loop, its
configuration, the device interfaces, the fast-forward driver and the settings panel's gain fields), never
``hardware.sim`` or the other campaign, and builds from first principles:

* a robot: a second-order position servo on an effective mass the tissue pushes back on (bandwidth, damping and
  mass drawn per run), acceleration and speed limits, a brake that decelerates it at a drawn rate on a hold and
  then clamps it, and a position reading that may arrive a few milliseconds late;
* a tissue: a layer on a very stiff table, its force exponential or a power law in the indentation, with some
  viscosity; its tangent stiffness at the force ceiling drawn from 2 kN/m to the configuration's
  ``tissue_stiffness_max_N_m`` (the stiffest tissue the loop accepts), stiffer still beyond the ceiling;
* a tactile array: 60 elements whose loads add up to the true force, shared by a pattern that moves from the
  centre to the edges as the force grows, each with its own gain scatter, offset and noise, clipped at full
  scale; sampled at a frame rate and read a latency later, both drawn around the configuration's and declared
  to the loop as the array's constraints, each frame's timing jittered.

Each run draws, from its seed, a configuration the validation accepts for that array, the plant, and one kind
of trouble of :data:`KINDS` (the kinds of issue 49), then steps the loop with :class:`app.fastforward.FastForward`
(the console's own tick) and checks on every tick, against the TRUE state of the plant:

* the true force stays within the force ceiling + 0.5 N, the true indentation (from the true surface) within
  the indentation ceiling (or the depth the run began at) + 0.5 mm;
* after a stop-where-it-is fault those bounds are widened by what the robot's braking from its true speed adds:
  no loop can take that back. Once the robot is at rest, a probe still pressing over the bounds must have been
  lifted within :data:`HELD_GRACE_S` (issue 49: a force over the ceiling while held starts a retract);
* no reference leaves the loop farther than the velocity limit allows in one period, and none is non-finite.

``python -m bench.independent_campaign --runs N --seed S --json OUT`` runs a campaign; ``--replay SEED`` runs
one run again and prints its trace.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import math
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from app.fastforward import FastForward
from control.config import ControlConfig, ImpedanceGains
from control.messages import (
    CommandApplied,
    CommandRefused,
    EStop,
    FaultKind,
    FaultRaised,
    PhaseChanged,
    RegionAborted,
    RegionDone,
    SetGains,
    SetSz,
)
from control.safety import RETRACT_FAULTS, blind_seek_depth_m
from hardware.interfaces import (
    ConnectionState,
    DeviceError,
    MasterConstraints,
    MasterDevice,
    MasterState,
    Phase,
    SlaveConstraints,
    SlaveManipulator,
    SlaveState,
    TactileConstraints,
    TactileFrame,
    TactileSensor,
    tare_problem,
)
from hardware.rig import Rig
from hardware.settings import ConfigError
from widgets.settings_panel import GAIN_FIELDS

# What issue 49 judges a run by (the same margins as our own campaign's checker, with no allowance for the
# array's lag: how fast the probe moves where it cannot yet see is the loop's choice)
FORCE_MARGIN_N = 0.5
INDENTATION_MARGIN_M = 0.5e-3
STEP_TOLERANCE_M = 1e-6
# A robot at rest after a stop, still pressing over a bound, must have been lifted back within them by then: at
# the default 20 mm/s retract speed a second lifts 20 mm, more than any braking overshoot
HELD_GRACE_S = 1.0
AT_REST_M_S = 1e-4
KINDS = (
    "plain",  # the ramp alone: what the other kinds' violations are measured against
    "dead-array",  # zeros (or bare noise) under fresh sequence numbers and stamps
    "frozen-array",  # one frame repeated (exactly, or its load under fresh noise)
    "drifting-array",  # a uniform negative drift within the plausibility bound, at various rates and starts
    "stuck-position",  # the robot's position reading stops following it
    "lying-position",  # the reading offset by a step, or creeping away from the truth
    "future-stamp",  # frames stamped seconds ahead (one, or all of them), sometimes the array then silent
    "estop-pressing",  # an e-stop at a level, or while the operator drives the probe down
    "operator-push",  # the operator pushes the master down at up to the velocity limit, position control
    "in-contact-start",  # force control asked with the probe pressed into the tissue
    "panel-gains",  # gains as the settings panel takes them, sent with the loop's run-time command
    "high-fmax",  # a ramp to F_max >= 9 N
)
# the physics
SUBSTEPS = 4  # per 1 ms tick: keeps omega * h below 0.6 on the table's stiffness
TABLE_STIFFNESS_N_M = 2e6  # a steel table under the face, through what is left of the layer
STIFFNESS_CAP_N_M = 1e6  # the layer's own stiffening stops here (it is then as stiff as the table it lies on)
FULL_SCALE_PA = 100e3
RUN_SECONDS = 6.0
HIGH_FMAX_RUN_SECONDS = 9.0
QUIET_TICKS = 250
RETRY_TICKS = 200  # a refused force control is asked again this often, as an operator presses the switch again


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(math.log(lo), math.log(hi))))


# ---- the physics -------------------------------------------------------------------------------------------


class Layer:
    """A wide layer of thickness ``surface_m`` on a table at z = 0, under a level face. Its elastic force in
    the indentation d is ``k0/beta (exp(beta d) - 1)`` (exponential) or ``c d^p`` (power law), its tangent
    stiffness capped at STIFFNESS_CAP_N_M; a viscous part ``eta`` times the indentation rate adds to it (taking
    off at most half of it while the face withdraws: the layer never pulls)."""

    def __init__(self, surface_m: float, law: str, stiffness_at_ceiling_N_m: float, ceiling_N: float,
                 shape: float, eta_N_s_m: float):
        self.surface_m, self.law, self.eta = surface_m, law, eta_N_s_m
        k, f = stiffness_at_ceiling_N_m, ceiling_N
        if law == "exp":
            # tangent k0 + beta F: ``shape`` is k0's share of the stiffness at the ceiling
            self.k0 = shape * k
            self.beta = k * (1.0 - shape) / f
        else:
            # tangent p F / d: ``shape`` is the exponent p
            self.p = shape
            self.c = (k / self.p) ** self.p / f ** (self.p - 1.0)
        self.d_cap, self.f_cap = self._cap()

    def _elastic(self, d: float) -> float:
        if self.law == "exp":
            return self.k0 * d if self.beta * d < 1e-9 else self.k0 / self.beta * math.expm1(self.beta * d)
        return self.c * d ** self.p

    def _tangent(self, d: float) -> float:
        if self.law == "exp":
            return self.k0 * math.exp(self.beta * d)
        return self.p * self.c * d ** (self.p - 1.0)

    def _cap(self) -> tuple[float, float]:
        """The depth at which the tangent reaches STIFFNESS_CAP_N_M, and the force there."""
        if self.law == "exp":
            d = math.log(STIFFNESS_CAP_N_M / self.k0) / self.beta if self.beta > 0 else math.inf
        else:
            d = (STIFFNESS_CAP_N_M / (self.p * self.c)) ** (1.0 / (self.p - 1.0))
        return d, (self._elastic(d) if math.isfinite(d) else math.inf)

    def elastic_N(self, d: float) -> float:
        if d <= 0.0:
            return 0.0
        if d > self.d_cap:
            return self.f_cap + STIFFNESS_CAP_N_M * (d - self.d_cap)
        return self._elastic(d)

    def tangent_N_m(self, d: float) -> float:
        return STIFFNESS_CAP_N_M if d > self.d_cap else self._tangent(max(d, 0.0))

    def force_N(self, z: float, vz: float) -> float:
        """What pushes the face up at height ``z`` moving at ``vz``: the layer, and the table below it."""
        d = self.surface_m - z
        if d <= 0.0:
            return 0.0
        force = self.elastic_N(d) + max(-self.eta * vz, -0.5 * self.elastic_N(d))
        if z < 0.0:
            force += TABLE_STIFFNESS_N_M * -z
        return max(force, 0.0)

    def depth_of_force_m(self, force_N: float) -> float:
        """The indentation at which the layer (elastic part) pushes ``force_N``."""
        lo, hi = 0.0, self.surface_m + 1.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if self.elastic_N(mid) < force_N else (lo, mid)
        return hi


@dataclass
class ServoParams:
    bandwidth_hz: float
    damping: float
    mass_kg: float  # what the tissue pushes back on: the servo's stiffness is mass * omega^2
    max_accel_m_s2: float
    max_speed_m_s: float
    brake_m_s2: float  # the deceleration its brake stops it at on a hold
    reading_delay_ticks: int  # the position reading's transport delay, in 1 ms readings


class Plant:
    """The robot over the layer, one clock for both; the array's samples are taken as the clock passes them."""

    def __init__(self, layer: Layer, servo: ServoParams, start_m, sample_times, period_s: float):
        self.layer, self.servo = layer, servo
        self.t = 0.0
        self.x = list(start_m)
        self.v = [0.0, 0.0, 0.0]
        self.x_ref, self.v_ref = list(start_m), [0.0, 0.0, 0.0]
        self.braking = False  # a hold: decelerating on the brake, then clamped where it stopped
        self.clamp: list[float] | None = None
        self.omega = 2.0 * math.pi * servo.bandwidth_hz
        self.h = period_s / SUBSTEPS
        self._samples = sample_times  # iterator of the array's sampling instants
        self.next_sample = next(self._samples)
        self.sampled: collections.deque = collections.deque()  # (t_sample, true force) not yet framed
        self.force = 0.0

    def command(self, x, v) -> None:
        self.x_ref, self.v_ref = list(x), list(v)
        self.braking, self.clamp = False, None

    def hold(self) -> None:
        if not self.braking:
            self.braking, self.clamp = True, None

    def advance(self, t_end: float) -> None:
        h, s = self.h, self.servo
        w2, cw = self.omega * self.omega, 2.0 * s.damping * self.omega
        x, v = self.x, self.v
        while self.t < t_end - 1e-12:
            push = self.layer.force_N(x[2], v[2])  # the tissue on the face, up
            if self.braking and self.clamp is None:
                speed = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
                if speed <= s.brake_m_s2 * h:
                    self.clamp = list(x)
                    v[0] = v[1] = v[2] = 0.0
                    a = [0.0, 0.0, 0.0]
                else:
                    a = [-s.brake_m_s2 * v[i] / speed for i in range(3)]
            else:
                target, vt = (self.clamp, (0.0, 0.0, 0.0)) if self.clamp is not None else (self.x_ref, self.v_ref)
                a = [w2 * (target[i] - x[i]) + cw * (vt[i] - v[i]) for i in range(3)]
                norm = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
                if norm > s.max_accel_m_s2:
                    a = [ai * s.max_accel_m_s2 / norm for ai in a]
            a[2] += push / s.mass_kg  # the motors' acceleration is limited, the tissue's push is not
            for i in range(3):
                v[i] += a[i] * h
            speed = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
            if speed > s.max_speed_m_s and not self.braking:
                for i in range(3):
                    v[i] *= s.max_speed_m_s / speed
            for i in range(3):
                x[i] += v[i] * h
            self.t += h
            self.force = self.layer.force_N(x[2], v[2])
            while self.t >= self.next_sample:
                self.sampled.append((self.next_sample, self.force))
                self.next_sample = next(self._samples)

    @property
    def depth_m(self) -> float:
        return self.layer.surface_m - self.x[2]

    @property
    def speed_m_s(self) -> float:
        return math.sqrt(sum(c * c for c in self.v))


# ---- the devices over the plant ------------------------------------------------------------------------------


class _Device:
    name = "independent"

    def __init__(self):
        self._state = ConnectionState.DISCONNECTED

    @property
    def connection(self) -> ConnectionState:
        return self._state

    def open(self) -> None:
        self._state = ConnectionState.CONNECTED

    def close(self) -> None:
        self._state = ConnectionState.DISCONNECTED


class PlantArray(_Device, TactileSensor):
    """The array: each sample of the true force becomes a frame ``latency`` later. ``fault`` changes what it
    says, never the plant: None, "zeros", "noise" (dead with live electronics), "frozen" (one frame repeated),
    "stuck" (one frame's load under fresh noise), "drift" (``drift_pa`` off every element, negative), "gain"
    (reads ``gain`` times the load: a miscalibration no loop can tell, for the negative control)."""

    name = "independent array"

    def __init__(self, plant: Plant, constraints: TactileConstraints, rng: np.random.Generator,
                 latency_jitter_s: float, noise_pa: float):
        super().__init__()
        self.plant, self.constraints, self.rng = plant, constraints, rng
        rows, cols = constraints.shape
        self.area = constraints.element_area_m2
        # how the face shares the load: a rigid face on a layer loads its rim most, more so as it sinks in
        ii, jj = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
        rim = np.maximum(np.abs(ii - (rows - 1) / 2) / ((rows - 1) / 2), np.abs(jj - (cols - 1) / 2) / ((cols - 1) / 2))
        self.centre_w = _normalised(1.3 - 0.6 * rim**2)
        self.rim_w = _normalised(1.0 + float(rng.uniform(0.3, 1.2)) * rim**4)
        self.spread_N = float(rng.uniform(1.0, 6.0))  # the force at which the pattern is halfway to the rim's
        self.gain_scatter = 1.0 + float(rng.uniform(0.0, 0.08)) * rng.standard_normal(constraints.shape)
        self.sigma = noise_pa * rng.uniform(0.7, 1.3, constraints.shape)
        self.offset = 0.3 * noise_pa * rng.standard_normal(constraints.shape)
        self.zero = np.zeros(constraints.shape)
        self.latency_jitter_s = latency_jitter_s
        self.queue: collections.deque = collections.deque()  # (ready time, TactileFrame)
        self.frame: TactileFrame | None = None
        self.raw: np.ndarray | None = None  # the newest frame before the fault, untared
        self.seq = 0
        self.fault: str | None = None
        self.held_pa: np.ndarray | None = None  # what a frozen or stuck array keeps reading
        self.drift_pa = 0.0
        self.gain = 1.0
        self.stamp_ahead_s = 0.0
        self.silent = False

    def load_pa(self, force_N: float) -> np.ndarray:
        """The elements' pressures under ``force_N``: they add up to it (to their gains' scatter)."""
        s = max(force_N, 0.0) / (max(force_N, 0.0) + self.spread_N)
        w = (1.0 - s) * self.centre_w + s * self.rim_w
        return force_N * w * self.gain_scatter / self.area

    def poll(self, now_s: float) -> None:
        plant = self.plant
        plant.advance(now_s)
        while plant.sampled:
            t_sample, force = plant.sampled.popleft()
            latency = self.constraints.latency_s + float(self.rng.uniform(-1.0, 1.0)) * self.latency_jitter_s
            noise = self.sigma * self.rng.standard_normal(self.sigma.shape)
            self.queue.append((t_sample + max(latency, 1e-3), t_sample, force, noise))
        while self.queue and self.queue[0][0] <= now_s:
            _, t_sample, force, noise = self.queue.popleft()
            if not self.silent:
                self._publish(t_sample, force, noise)

    def _publish(self, t_sample: float, force: float, noise: np.ndarray) -> None:
        fault = self.fault
        if fault in ("frozen", "stuck") and self.held_pa is None and self.raw is not None:
            self.held_pa = self.raw
        if fault == "zeros":
            raw = np.zeros(self.sigma.shape)
        elif fault == "frozen" and self.held_pa is not None:
            raw = self.held_pa
        elif fault == "stuck" and self.held_pa is not None:
            raw = self.held_pa + noise
        elif fault == "noise":
            raw = self.offset + noise
        else:
            raw = self.gain * self.load_pa(force) + self.offset + noise - self.drift_pa
        self.raw = raw
        pressure = raw - self.zero if fault not in ("zeros", "frozen") else raw
        saturated = pressure >= FULL_SCALE_PA
        pressure = np.minimum(pressure, FULL_SCALE_PA)
        self.seq += 1
        self.frame = TactileFrame(self.seq, t_sample + self.stamp_ahead_s, pressure, saturated)

    def latest(self) -> TactileFrame | None:
        return self.frame

    def tare(self) -> None:
        if self.raw is None:
            raise DeviceError("no frame to tare on yet")
        problem = tare_problem(self.raw, None, FULL_SCALE_PA)
        if problem is not None:
            raise DeviceError(problem)
        self.zero = self.raw.copy()


def _normalised(w: np.ndarray) -> np.ndarray:
    return w / w.sum()


class PlantRobot(_Device, SlaveManipulator):
    """The robot's side: its reading (late by ``reading_delay_ticks`` readings) and the references it takes.
    ``fault``: None, "stuck" (the reading stops where it was, at rest or still moving as it last was),
    "step" (the reading jumps by ``offset_m`` in z) or "creep" (it wanders off at ``creep_m_s`` to at most
    ``offset_m``)."""

    name = "independent robot"

    def __init__(self, plant: Plant, constraints: SlaveConstraints):
        super().__init__()
        self.plant, self.constraints = plant, constraints
        self.readings: collections.deque = collections.deque(maxlen=plant.servo.reading_delay_ticks + 1)
        self.seq = 0
        self.fault: str | None = None
        self.fault_t = 0.0
        self.offset_m = 0.0
        self.creep_m_s = 0.0
        self.stuck: tuple | None = None
        self.stuck_moving = False
        self.state: SlaveState | None = None

    def poll(self, now_s: float) -> None:
        plant = self.plant
        plant.advance(now_s)
        self.readings.append((now_s, tuple(plant.x), tuple(plant.v)))
        t, x, v = self.readings[0]
        if self.fault == "stuck":
            if self.stuck is None:
                self.stuck = (t, x, v)
            t0, x0, v0 = self.stuck
            if self.stuck_moving:  # the reading carries on as it last moved, whatever the robot does
                x = tuple(x0[i] + v0[i] * (t - t0) for i in range(3))
                v = v0
            else:
                x, v = x0, (0.0, 0.0, 0.0)
        elif self.fault == "step":
            x = (x[0], x[1], x[2] + self.offset_m)
        elif self.fault == "creep":
            off = math.copysign(min(abs(self.creep_m_s) * (t - self.fault_t), abs(self.offset_m)), self.offset_m)
            x = (x[0], x[1], x[2] + off)
        self.seq += 1
        self.state = SlaveState(self.seq, t, x, v)

    def latest(self) -> SlaveState | None:
        return self.state

    def command(self, position_m, velocity_m_s, now_s: float) -> None:
        self.plant.command(position_m, velocity_m_s)

    def hold(self, now_s: float) -> None:
        self.plant.hold()


class Hand(_Device, MasterDevice):
    """The operator's master: where the campaign's hand puts it (no S_z switch: S_z goes by command)."""

    name = "independent hand"
    constraints = MasterConstraints(has_sz_switch=False)

    def __init__(self, start_m):
        super().__init__()
        self.position = list(start_m)
        self.seq = 0
        self.state: MasterState | None = None

    def poll(self, now_s: float) -> None:
        self.seq += 1
        self.state = MasterState(self.seq, now_s, (self.position[0], self.position[1], self.position[2]), None)

    def latest(self) -> MasterState | None:
        return self.state


def _sample_times(rng: np.random.Generator, rate_hz: float, first_s: float):
    """The array's sampling instants: its nominal period with a few % of jitter, for ever."""
    period, k = 1.0 / rate_hz, 0
    while True:
        yield first_s + k * period + float(rng.uniform(-0.03, 0.03)) * period
        k += 1


# ---- the checker ---------------------------------------------------------------------------------------------


@dataclass
class RunResult:
    seed: int
    kind: str
    drawn: dict = field(default_factory=dict)
    ticks: int = 0
    injected: bool = False
    trouble_t_s: float = math.nan
    max_force_over_ceiling_N: float = -math.inf  # TRUE force less the ceiling
    max_indentation_over_ceiling_mm: float = -math.inf  # TRUE indentation less the ceiling
    violations: list = field(default_factory=list)  # {"type", "t_s", "values"}
    faults: list = field(default_factory=list)  # (t_s, FaultKind name) in order
    first_fault_after_trouble_ms: float = math.nan  # the loop's reaction time to the trouble
    over_to_fault_ms: float = math.nan  # from the true force or depth first passing its ceiling to a fault
    gains_applied: bool | None = None
    levels_recorded: int = 0
    region_done: bool = False
    aborted: list = field(default_factory=list)  # (t_s, why) of each area the loop ended without region done


class Checker:
    """The invariants, every tick, on the plant's truth."""

    def __init__(self, result: RunResult, config: ControlConfig, layer: Layer, start_depth_m: float):
        self.r, self.config, self.layer = result, config, layer
        lim = config.safety
        self.force_allowed = lim.force_ceiling_N + FORCE_MARGIN_N
        self.depth_allowed = max(lim.indentation_ceiling_m, start_depth_m) + INDENTATION_MARGIN_M
        self.base = (self.force_allowed, self.depth_allowed)
        self.sent = None
        self.rest_since: float | None = None  # when the robot came to rest after a stop
        self.over_since: float | None = None

    def stop(self, plant: Plant) -> None:
        """A stop where it is: what the brake from the robot's true speed adds can be allowed, not taken back."""
        down = max(-plant.v[2], 0.0)
        depth = plant.depth_m + down * down / (2.0 * plant.servo.brake_m_s2)
        self.depth_allowed = max(self.depth_allowed, depth + INDENTATION_MARGIN_M)
        # the layer's viscosity pushes hardest as the brake takes hold, its elasticity once the robot has stopped
        braking_N = max(self.layer.elastic_N(plant.depth_m) + self.layer.eta * down, self.layer.elastic_N(depth))
        self.force_allowed = max(self.force_allowed, braking_N + FORCE_MARGIN_N)
        self.rest_since = None

    def reference(self, step, period_s: float) -> None:
        if step.hold:
            self.sent = None
            return
        x = step.position_ref_m
        if not all(math.isfinite(c) for c in x):
            self.violate("reference", {"reference_m": list(x)})
        elif self.sent is not None:
            allowed = self.config.safety.velocity_limit_m_s * period_s + STEP_TOLERANCE_M
            jump = math.dist(x, self.sent)
            if jump > allowed:
                self.violate("reference", {"step_mm": jump * 1e3, "allowed_mm": allowed * 1e3})
        self.sent = x

    def truth(self, now_s: float, plant: Plant, held: bool) -> None:
        lim, r = self.config.safety, self.r
        force, depth = plant.force, plant.depth_m
        r.max_force_over_ceiling_N = max(r.max_force_over_ceiling_N, force - lim.force_ceiling_N)
        r.max_indentation_over_ceiling_mm = max(r.max_indentation_over_ceiling_mm,
                                                (depth - lim.indentation_ceiling_m) * 1e3)
        over = force > lim.force_ceiling_N or depth > lim.indentation_ceiling_m
        if over and self.over_since is None:
            self.over_since = now_s
        if not force <= self.force_allowed:
            self.violate("force", {"true_force_N": force, "ceiling_N": lim.force_ceiling_N,
                                   "allowed_N": self.force_allowed})
        if not depth <= self.depth_allowed:
            self.violate("indentation", {"true_indentation_mm": depth * 1e3,
                                         "ceiling_mm": lim.indentation_ceiling_m * 1e3,
                                         "allowed_mm": self.depth_allowed * 1e3})
        if self.base == (self.force_allowed, self.depth_allowed):
            return
        # after a stop: once at rest, the probe has HELD_GRACE_S to be lifted back within the plain bounds
        if plant.speed_m_s > AT_REST_M_S and self.rest_since is None:
            return
        self.rest_since = now_s if self.rest_since is None else self.rest_since
        within = force <= self.base[0] and depth <= self.base[1]
        if within:
            self.force_allowed, self.depth_allowed = self.base
        elif now_s - self.rest_since > HELD_GRACE_S:
            self.violate("held-over-ceiling", {"true_force_N": force, "true_indentation_mm": depth * 1e3,
                                               "ceiling_N": lim.force_ceiling_N, "held": held})
            self.force_allowed, self.depth_allowed = self.base  # from now on the plain bounds

    def violate(self, what: str, values: dict) -> None:
        r = self.r
        if len(r.violations) < 3 and not any(v["type"] == what for v in r.violations):
            r.violations.append({"type": what, "t_s": round(r.ticks * self.config.period_s, 4),
                                 **{k: (round(v, 4) if isinstance(v, float) else v) for k, v in values.items()}})


# ---- drawing a run -------------------------------------------------------------------------------------------


def draw_config(rng: np.random.Generator, kind: str, constraints: TactileConstraints) -> tuple[ControlConfig, int]:
    """A configuration the validation accepts, and that the loop accepts for this array; the refusals met."""
    refused = 0
    default = ControlConfig()
    while True:
        high = kind == "high-fmax"
        if high:
            f_max = float(rng.uniform(9.0, 22.0))
            ceiling = min(f_max + float(rng.uniform(0.5, 5.0)), 30.0)
            step = float(rng.uniform(f_max / 8.0, f_max / 3.0))
        else:
            ceiling = float(rng.uniform(5.0, 20.0))
            f_max = float(rng.uniform(2.0, min(ceiling, 12.0)))
            step = float(rng.uniform(0.5, max(0.5, min(3.0, f_max - 1.0))))
        v_lim = _log_uniform(rng, 0.03, 0.5)
        safety = {"force_ceiling_N": ceiling, "indentation_ceiling_m": float(rng.uniform(0.004, 0.02)),
                  "velocity_limit_m_s": v_lim,
                  "approach_speed_m_s": min(float(rng.uniform(0.002, 0.05)), v_lim)}
        if rng.uniform() < 0.5:
            gains = {name: list(getattr(default.gains, name)) for name in ("mass_kg", "damping_N_s_m",
                                                                             "stiffness_N_m")}
            safety["tissue_stiffness_max_N_m"] = default.safety.tissue_stiffness_max_N_m
        else:
            gains = {"mass_kg": [1.0, 1.0, _log_uniform(rng, 0.05, 3.0)],
                     "damping_N_s_m": [80.0, 80.0, _log_uniform(rng, 150.0, 800.0)],
                     "stiffness_N_m": [1600.0, 1600.0, _log_uniform(rng, 2e3, 5e4)]}
            safety["tissue_stiffness_max_N_m"] = _log_uniform(rng, 2e3, 2e4)
        table = {"gains": gains, "safety": safety,
                 "ramp": {"force_min_N": 1.0, "force_max_N": f_max, "force_step_N": min(step, f_max - 1.0),
                          "min_settle_s": float(rng.uniform(0.15, 0.4)), "settle_window_s": 0.1,
                          "level_timeout_s": float(rng.uniform(1.5, 4.0)), "rmse_threshold_N": 0.08}}
        try:
            config = ControlConfig.from_mapping(table)
        except ConfigError:
            refused += 1
            continue
        if config.gains_problem(config.gains, constraints.frame_rate_hz, constraints.latency_s) is None:
            return config, refused
        refused += 1


def panel_gains(rng: np.random.Generator) -> ImpedanceGains:
    """Gains as an operator types them into the settings panel: anything its spin boxes take."""
    values = {}
    for name, _, _, decimals, maximum in GAIN_FIELDS:
        least = 10.0 ** -decimals
        values[name] = tuple(max(round(_log_uniform(rng, least, maximum), decimals), least) for _ in range(3))
    return ImpedanceGains(**values)


class Run:
    """One run: its draws, the rig over the plant, the FastForward driver, the operator and the trouble."""

    def __init__(self, seed: int, kind: str | None = None, array_fault: tuple[str, float] | None = None,
                 trace: bool = False):
        rng = self.rng = np.random.default_rng(seed)
        kind = kind or KINDS[seed % len(KINDS)]
        self.r = RunResult(seed, kind)
        # the array first: the loop takes its timing from what it declares
        rate = float(rng.uniform(80.0, 125.0))
        latency = float(rng.uniform(0.004, 0.014))
        constraints = TactileConstraints(full_scale_pa=FULL_SCALE_PA, frame_rate_hz=rate, latency_s=latency)
        self.config, refused = draw_config(rng, kind, constraints)
        lim = self.config.safety
        k_ceiling = _log_uniform(rng, 2e3, lim.tissue_stiffness_max_N_m)
        law = "exp" if rng.uniform() < 0.5 else "power"
        shape = float(rng.uniform(0.2, 0.9)) if law == "exp" else float(rng.uniform(1.2, 2.2))
        probe = Layer(1.0, law, k_ceiling, lim.force_ceiling_N, shape, 0.0)
        # thick enough that the ceiling's force is reached in the layer, not on the table
        at_ceiling = probe.depth_of_force_m(lim.force_ceiling_N)
        thickness = max(float(rng.uniform(0.004, 0.045)), 1.3 * at_ceiling)
        layer = self.layer = Layer(thickness, law, k_ceiling, lim.force_ceiling_N, shape,
                                   float(rng.uniform(0.0, 30.0)))
        servo = ServoParams(bandwidth_hz=_log_uniform(rng, 8.0, 40.0), damping=float(rng.uniform(0.5, 1.2)),
                            mass_kg=_log_uniform(rng, 0.5, 5.0), max_accel_m_s2=_log_uniform(rng, 2.0, 20.0),
                            max_speed_m_s=float(rng.uniform(0.1, 0.6)), brake_m_s2=0.0,
                            reading_delay_ticks=int(rng.integers(0, 4)) if rng.uniform() < 0.5 else 0)
        servo.brake_m_s2 = float(rng.uniform(0.3, 1.0)) * servo.max_accel_m_s2
        # The operator begins the seek within the depth a blind seek may go (docs/console.md); one run in ten
        # begins beyond it, where the seek must give up before it presses too hard
        # (drawn apart, so that a seed draws everything else as it did before)
        reach, u = blind_seek_depth_m(lim), float(rng.uniform())
        beyond = np.random.default_rng([seed, 2]).uniform() < 0.1
        self.start_above = reach * (1.0 + 1.5 * u) if beyond else 0.0003 + u * max(0.8 * reach - 0.0003, 0.0)
        start = (0.03, 0.015, thickness + self.start_above)
        self.plant = Plant(layer, servo, start, _sample_times(rng, rate, float(rng.uniform(0.0, 1.0 / rate))),
                           self.config.period_s)
        self.array = PlantArray(self.plant, constraints, np.random.default_rng([seed, 1]),
                                latency_jitter_s=float(rng.uniform(0.0, 0.001)), noise_pa=_log_uniform(rng, 15, 150))
        self.robot = PlantRobot(self.plant, SlaveConstraints())
        self.hand = Hand(start)
        if array_fault is not None:
            self.array.fault, self.array.gain = array_fault
        self.trace = [] if trace else None
        self.r.drawn = {
            "frame_rate_hz": rate, "latency_ms": latency * 1e3, "config_refusals": refused,
            "force_ceiling_N": lim.force_ceiling_N, "indentation_ceiling_mm": lim.indentation_ceiling_m * 1e3,
            "velocity_limit_m_s": lim.velocity_limit_m_s, "approach_speed_m_s": lim.approach_speed_m_s,
            "tissue_stiffness_max_N_m": lim.tissue_stiffness_max_N_m, "force_max_N": self.config.ramp.force_max_N,
            "gains_z": [self.config.gains.mass_kg[2], self.config.gains.damping_N_s_m[2],
                        self.config.gains.stiffness_N_m[2]],
            "tissue": {"law": law, "shape": shape, "stiffness_at_ceiling_N_m": k_ceiling,
                       "thickness_mm": thickness * 1e3, "eta_N_s_m": layer.eta,
                       "depth_at_ceiling_mm": at_ceiling * 1e3},
            "robot": asdict(servo), "start_above_mm": self.start_above * 1e3}
        self._draw_trouble(kind)

    # ---- the trouble, drawn up front so a run is its seed

    def _draw_trouble(self, kind: str) -> None:
        rng, cfg = self.rng, self.config
        self.fc_at = int(rng.integers(400, 700))  # the tick force control is first asked for (-1: never)
        # when the trouble starts: ("ramp", k) at level k of the ramp (-1: its start), ("push", d) once the
        # operator's push has the probe d deep (None: at once), ("pressed", d) once the hand has it d deep
        self.trigger: tuple = ("ramp", int(rng.integers(-1, min(cfg.ramp.n_levels, 4))))
        self.push_from, self.push_until, self.push_m_s = -1, -1, 0.0
        t = self.trouble = {}
        if kind == "dead-array":
            t["fault"] = "zeros" if rng.uniform() < 0.5 else "noise"
        elif kind == "frozen-array":
            t["fault"] = "frozen" if rng.uniform() < 0.5 else "stuck"
        elif kind == "drifting-array":
            t["drift_pa"] = float(rng.uniform(1e3, 19e3))
            t["drift_s"] = 0.0 if rng.uniform() < 0.3 else _log_uniform(rng, 0.02, 3.0)
            t["delay_ticks"] = int(rng.integers(0, 400))
        elif kind in ("stuck-position", "lying-position"):
            if kind == "stuck-position":
                t["moving"] = bool(rng.integers(2))
            else:
                t["how"] = "step" if rng.uniform() < 0.5 else "creep"
                t["offset_m"] = float(rng.choice((-1.0, 1.0))) * float(rng.uniform(0.001, 0.010))
                t["creep_m_s"] = _log_uniform(rng, 0.001, 0.03)
            if rng.uniform() < 0.5:  # while the operator drives the probe down
                self._draw_push(fast=False)
                self.trigger = ("push", float(rng.uniform(-0.002, 0.002)))
        elif kind == "future-stamp":
            t["ahead_s"] = float(rng.uniform(0.5, 10.0))
            t["every_frame"] = bool(rng.integers(2))
            t["silent_after_ticks"] = int(rng.integers(0, 300)) if rng.uniform() < 0.6 else None
        elif kind == "estop-pressing":
            t["delay_ticks"] = int(rng.integers(0, 300))
            if rng.uniform() < 0.5:
                self.trigger = ("ramp", max(self.trigger[1], 0))
            else:
                self._draw_push(fast=True)
                self.trigger = ("push", float(rng.uniform(-0.001, 0.004)))
        elif kind == "operator-push":
            self._draw_push(fast=bool(rng.integers(2)))
            self.trigger = ("push", None)
        elif kind == "in-contact-start":
            # pressed in by hand, slowly, to a depth short of both ceilings, then force control
            lim = self.config.safety
            deepest = min(0.8 * self.layer.depth_of_force_m(lim.force_ceiling_N), 0.8 * lim.indentation_ceiling_m)
            self.push_from, self.push_m_s = 20, float(rng.uniform(0.002, 0.01))
            self.push_until = math.inf  # until the press is in
            self.trigger = ("pressed", float(rng.uniform(0.0005, max(deepest, 0.001))))
            self.fc_at = -1  # asked once the press is in
        elif kind == "panel-gains":
            t["gains"] = panel_gains(rng)
            t["at_tick"] = int(rng.integers(50, self.fc_at - 20))
            self.trigger = ("ramp", -1)
        if self.trigger[0] == "push":
            self.fc_at = -1  # position control throughout
        if kind in ("plain", "high-fmax"):
            self.trigger = ("ramp", -1)

    def _draw_push(self, fast: bool) -> None:
        rng, v_lim = self.rng, self.config.safety.velocity_limit_m_s
        self.push_from = int(rng.integers(100, 500))
        self.push_m_s = float(rng.uniform(0.3, 1.0) * v_lim if fast else rng.uniform(0.003, v_lim))
        self.push_until = self.push_from + int(0.06 / self.push_m_s / self.config.period_s)  # 60 mm down at most

    # ---- the run

    def _triggered(self, k: int, ff: FastForward) -> bool:
        if self.r.injected:
            return False
        how, at = self.trigger
        if how == "pressed":
            return self.plant.depth_m >= at
        if how == "push":
            return k >= self.push_from and (at is None or self.plant.depth_m >= at)
        sm = ff.loop.sm
        return sm.force_control and (at < 0 or (sm.phase == Phase.SETTLING and sm.level >= at))

    def _inject(self, k: int, ff: FastForward) -> None:
        r, t, array, robot = self.r, self.trouble, self.array, self.robot
        r.injected, r.trouble_t_s, self.k0 = True, ff.now_s, k
        kind = r.kind
        if kind in ("dead-array", "frozen-array"):
            array.fault = t["fault"]
        elif kind == "stuck-position":
            robot.fault, robot.stuck_moving = "stuck", t["moving"]
        elif kind == "lying-position":
            robot.fault, robot.offset_m, robot.creep_m_s, robot.fault_t = t["how"], t["offset_m"], t["creep_m_s"], \
                ff.now_s
        elif kind == "future-stamp":
            array.stamp_ahead_s = t["ahead_s"]
            self.stamped_seq = array.seq
        elif kind == "estop-pressing" and self.trigger[0] == "push":
            ff.send(EStop("independent campaign: while the probe is driven down"))
        elif kind == "in-contact-start":
            self.push_until = k  # the hand stops: the probe is in
            self.fc_at = k + 100

    def _evolve(self, k: int, ff: FastForward) -> None:
        r, t, array = self.r, self.trouble, self.array
        since = k - self.k0
        if r.kind == "drifting-array" and since >= t["delay_ticks"]:
            ramp = (since - t["delay_ticks"]) * self.config.period_s
            array.drift_pa = t["drift_pa"] * (1.0 if t["drift_s"] == 0.0 else min(1.0, ramp / t["drift_s"]))
        elif r.kind == "future-stamp":
            if not t["every_frame"] and array.seq > self.stamped_seq:
                array.stamp_ahead_s = 0.0
            if t["silent_after_ticks"] is not None and since >= t["silent_after_ticks"]:
                array.silent = True
        elif r.kind == "estop-pressing" and self.trigger[0] == "ramp" and since == t["delay_ticks"]:
            ff.send(EStop("independent campaign: pressing at a level"))

    def run(self) -> RunResult:
        r, plant, cfg = self.r, self.plant, self.config
        rig = Rig(self.array, self.robot, self.hand)
        seconds = HIGH_FMAX_RUN_SECONDS if r.kind == "high-fmax" else RUN_SECONDS
        n = int(seconds * cfg.rate_hz)
        check = Checker(r, cfg, self.layer, 0.0)
        fc_started = False
        quiet = 0
        with FastForward(cfg, rig, block_rows=1024) as ff:
            for k in range(n):
                if k == self.trouble.get("at_tick"):
                    ff.send(SetGains(self.trouble["gains"]))
                if not fc_started and self.fc_at >= 0 and k >= self.fc_at and (k - self.fc_at) % RETRY_TICKS == 0:
                    ff.send(SetSz(position_control=False))
                if 0 <= self.push_from <= k < self.push_until:
                    self.hand.position[2] -= self.push_m_s * cfg.period_s
                if self._triggered(k, ff):
                    self._inject(k, ff)
                if r.injected:
                    self._evolve(k, ff)
                ff.step()
                step = ff.last_result
                fc_started = fc_started or ff.loop.sm.force_control
                self._events(step.events, check, ff)
                check.reference(step, cfg.period_s)
                check.truth(plant.t, plant, step.hold)
                r.ticks += 1
                if self.trace is not None:
                    tick = ff.loop.tick
                    self.trace.append((ff.now_s, Phase(int(tick["phase"])).name, int(tick["fault"]),
                                       float(tick["force_measured_N"]), plant.force, plant.depth_m * 1e3,
                                       plant.x[2] * 1e3, float(tick["x_slave_m"][2]) * 1e3, plant.v[2] * 1e3,
                                       step.hold))
                quiet = quiet + 1 if self._quiet(k, ff, fc_started) else 0
                if quiet >= QUIET_TICKS:
                    break
                ff.clear()  # the checker reads the truth as it goes; the rows are not needed
        return r

    def _events(self, events, check: Checker, ff: FastForward) -> None:
        r = self.r
        for e in events:
            if isinstance(e, FaultRaised):
                r.faults.append((round(e.t_s, 4), e.kind.name))
                if r.injected and math.isnan(r.first_fault_after_trouble_ms):
                    r.first_fault_after_trouble_ms = (e.t_s - r.trouble_t_s) * 1e3
                if check.over_since is not None and math.isnan(r.over_to_fault_ms):
                    r.over_to_fault_ms = (e.t_s - check.over_since) * 1e3
                if e.kind not in RETRACT_FAULTS:
                    check.stop(self.plant)
            elif isinstance(e, CommandApplied) and isinstance(e.command, SetGains):
                r.gains_applied = True
            elif isinstance(e, CommandRefused) and isinstance(e.command, SetGains):
                r.gains_applied = False
            elif isinstance(e, PhaseChanged) and e.phase == Phase.SETTLING and e.level > 0:
                r.levels_recorded = max(r.levels_recorded, e.level)
            elif isinstance(e, RegionDone):
                r.region_done = True
                r.levels_recorded = e.n_levels
            elif isinstance(e, RegionAborted):
                r.aborted.append((round(e.t_s, 4), e.reason))

    def _quiet(self, k: int, ff: FastForward, fc_started: bool) -> bool:
        """Nothing more can happen: no ramp under way or to come, no push, the trouble played out, at rest."""
        loop = ff.loop
        if loop.sm.force_control or loop.sm.phase == Phase.RETRACT or (self.fc_at >= 0 and not fc_started):
            return False
        if self.plant.speed_m_s > AT_REST_M_S:
            return False
        if loop.safety.faulted:
            return True
        if 0 <= self.push_from and k < self.push_until and not self.r.injected:
            return False
        return self.r.injected or self.fc_at >= 0


def run(seed: int, kind: str | None = None, **options) -> RunResult:
    """One run; everything it draws comes from ``seed`` (its kind too, unless given)."""
    return Run(seed, kind, **options).run()


# ---- the campaign --------------------------------------------------------------------------------------------


CHUNK_RUNS = 50  # runs a worker takes at a time: progress is told after each


def _chunk(seeds: list[int]) -> list[dict]:
    return [asdict(run(seed)) for seed in seeds]


def campaign(runs: int, seed: int = 0, workers: int = 1,
             progress: Callable[[list[dict]], None] | None = None) -> dict:
    """``runs`` seeded runs; ``progress`` hears the results so far after every ``CHUNK_RUNS`` of them (2,000
    runs took 16 minutes and said nothing until the end)."""
    started, cpu = time.monotonic(), time.process_time()
    seeds = [seed * 1_000_003 + i for i in range(runs)]
    chunks = [seeds[i:i + CHUNK_RUNS] for i in range(0, runs, CHUNK_RUNS)]
    workers = max(1, min(workers, 2))  # the machine is shared: two processes at most
    results: list[dict] = []
    with ProcessPoolExecutor(workers) if workers > 1 else contextlib.nullcontext() as pool:
        for part in (pool.map(_chunk, chunks) if pool is not None else map(_chunk, chunks)):
            results += part
            if progress is not None:
                progress(results)
    return summarise(results, time.monotonic() - started, time.process_time() - cpu)


def summarise(results: list[dict], seconds: float = math.nan, cpu_seconds: float = math.nan) -> dict:
    def top(values):
        values = list(values)
        return max(values) if values else None

    violations = []
    by_kind: dict = {}
    for r in sorted(results, key=lambda r: r["seed"]):
        mine = by_kind.setdefault(r["kind"], {"runs": 0, "injected": 0, "violating_runs": 0, "violations": {},
                                              "max_force_over_ceiling_N": -math.inf,
                                              "max_indentation_over_ceiling_mm": -math.inf,
                                              "faults": {}, "reaction_ms": []})
        mine["runs"] += 1
        mine["injected"] += r["injected"]
        mine["violating_runs"] += bool(r["violations"])
        for key in ("max_force_over_ceiling_N", "max_indentation_over_ceiling_mm"):
            mine[key] = max(mine[key], r[key])
        for _, name in r["faults"][:1]:
            mine["faults"][name] = mine["faults"].get(name, 0) + 1
        if not math.isnan(r["first_fault_after_trouble_ms"]):
            mine["reaction_ms"].append(r["first_fault_after_trouble_ms"])
        for v in r["violations"]:
            mine["violations"][v["type"]] = mine["violations"].get(v["type"], 0) + 1
            violations.append({"seed": r["seed"], "kind": r["kind"], **v,
                               "max_force_over_ceiling_N": round(r["max_force_over_ceiling_N"], 3),
                               "max_indentation_over_ceiling_mm": round(r["max_indentation_over_ceiling_mm"], 3),
                               "faults": r["faults"][:3]})
    for mine in by_kind.values():
        reaction = mine.pop("reaction_ms")
        mine["reaction_ms_median"] = float(np.median(reaction)) if reaction else None
        mine["reaction_ms_max"] = top(reaction)
    return {
        "runs": len(results),
        "violating_runs": len({v["seed"] for v in violations}),
        "violations": violations,
        "max_force_over_ceiling_N": top(r["max_force_over_ceiling_N"] for r in results),
        "max_indentation_over_ceiling_mm": top(r["max_indentation_over_ceiling_mm"] for r in results),
        "by_kind": {kind: by_kind[kind] for kind in KINDS if kind in by_kind},
        "ticks": sum(r["ticks"] for r in results),
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
    }


def replay(seed: int, every_ms: int = 50) -> RunResult:
    """Run ``seed`` again and print what it drew, what the loop did and its trace, every ``every_ms``."""
    one = Run(seed, trace=True)
    result = one.run()
    print(json.dumps({k: v for k, v in asdict(result).items()}, indent=1, default=str))
    print(f"{'t s':>7} {'phase':>12} {'fault':>18} {'F read':>7} {'F true':>7} {'depth':>7} {'z true':>7} "
          f"{'z read':>7} {'vz mm/s':>8} hold")
    last = None
    for i, row in enumerate(one.trace):
        t, phase, fault, f_read, f_true, depth, z, z_read, vz, hold = row
        changed = (phase, fault, hold) != last
        last = (phase, fault, hold)
        if i % every_ms == 0 or changed or i == len(one.trace) - 1:
            print(f"{t:7.3f} {phase:>12} {FaultKind(fault).name:>18} {f_read:7.2f} {f_true:7.2f} {depth:7.2f} "
                  f"{z:7.2f} {z_read:7.2f} {vz:8.1f} {int(hold)}")
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.independent_campaign", description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=240)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=1, help="processes (at most 2)")
    parser.add_argument("--json", type=Path, help="write the summary here")
    parser.add_argument("--replay", type=int, metavar="SEED", help="run this one run again and print its trace")
    args = parser.parse_args(argv)
    if args.replay is not None:
        return 1 if replay(args.replay).violations else 0
    if args.runs < 1:
        parser.error(f"--runs must be at least 1, got {args.runs}")
    def progress(results: list[dict]) -> None:
        bad = sum(bool(r["violations"]) for r in results)
        print(f"  {len(results)}/{args.runs} runs, {bad} violating", file=sys.stderr, flush=True)

    summary = campaign(args.runs, args.seed, args.workers, progress)
    text = json.dumps(summary, indent=1)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    brief = {k: summary[k] for k in ("runs", "violating_runs", "max_force_over_ceiling_N",
                                     "max_indentation_over_ceiling_mm", "seconds")}
    print(json.dumps(brief, indent=1))
    return 1 if summary["violations"] else 0


if __name__ == "__main__":
    sys.exit(main())
