"""Test plants for the loop alone: a robot over a flat elastic layer on the table (z = 0).

Each element's pressure is E * dL / L0 (a local linear layer, L0 = ``surface_m``, the layer's thickness), so
the face's stiffness is E * A * elements / L0. The array delivers frames every ``frame_period_s``,
``latency_s`` late, optionally clipped at a full scale (saturation flagged). The plant knows the truth the
loop cannot see (:meth:`LayerPlant.true_force_N`, :attr:`LayerPlant.x`), which is what the fault campaign
(:mod:`bench.safety_campaign`) and the control tests check the loop against. The simulated rig
(hardware/sim) is the physics-based plant; this one is exact and fast.

The robot either tracks X_r exactly (the default: what the loop alone is tested on) or is a
:class:`SecondOrderRobot`, which follows it as a real position-controlled arm does: late, limited in
acceleration and speed, and braking to a stop on a hold.

Faults of the devices, set by whoever drives the plant (the campaign): an array that reads zeros or repeats
one frame (``array_fault``) or is offset (``extra_force_pa``), frames stamped ahead of their sample
(``stamp_offset_s``), and a position reading that is frozen (:meth:`LayerPlant.freeze_position`) or offset
(``position_offset_m``). Each fault changes what the devices say, never the truth.
"""

from __future__ import annotations

import math

import numpy as np

from hardware.interfaces import SlaveState, TactileConstraints, TactileFrame

SHAPE = TactileConstraints().shape
ELEMENT_AREA_M2 = TactileConstraints().element_area_m2
ELEMENTS = SHAPE[0] * SHAPE[1]

# The simulated rig's robot, as its settings and world state it (hardware/sim/settings.py RobotSimSettings:
# a 20 Hz inner position loop, 5 m/s^2, 0.25 m/s; hardware/sim/world.py plans its stops at 0.6 of the
# acceleration limit). The numbers are taken, the model is not: the plant the loop is checked against is
# written independently of the rig, so the two do not share a mistake.
RIG_BANDWIDTH_HZ = 20.0
RIG_MAX_ACCEL_M_S2 = 5.0
RIG_MAX_SPEED_M_S = 0.25
BRAKE_FRACTION = 0.6
# Semi-implicit Euler follows the continuous second-order loop closely while omega * h stays small: at
# 40 Hz, the fastest bandwidth the campaign draws, 0.5 ms gives omega * h = 0.13, and a step response within
# 4 % of the step of the exact one (measured against 1 us sub-steps, which match the closed form).
SUBSTEP_S = 5e-4


class SecondOrderRobot:
    """A position-controlled robot following (X_r, X_r') as a critically damped second-order loop.

    Per axis, x'' = w^2 (x_r - x) + 2 w (x_r' - x') with w = 2 pi ``bandwidth_hz`` (the reference held over
    each tick, as an inner loop sees a 1 kHz reference), the acceleration limited to ``max_accel_m_s2`` and
    the speed to ``max_speed_m_s`` on the vector's norm. A hold brakes along the direction of travel at
    ``BRAKE_FRACTION`` of the acceleration limit to a stop and stays there until the next reference.
    """

    def __init__(self, position_m, bandwidth_hz: float = RIG_BANDWIDTH_HZ, max_accel_m_s2: float = RIG_MAX_ACCEL_M_S2,
                 max_speed_m_s: float = RIG_MAX_SPEED_M_S):
        self.omega = 2.0 * math.pi * bandwidth_hz
        self.max_accel_m_s2 = max_accel_m_s2
        self.max_speed_m_s = max_speed_m_s
        self.brake_m_s2 = BRAKE_FRACTION * max_accel_m_s2
        self.position = [float(v) for v in position_m]
        self.velocity = [0.0, 0.0, 0.0]
        self.reference = list(self.position)
        self.reference_velocity = [0.0, 0.0, 0.0]
        self.holding = True  # at rest where it stands until the first reference

    def braking_distance_m(self, speed_m_s: float) -> float:
        """How far a hold at ``speed_m_s`` carries the robot: its braking plan."""
        return speed_m_s * speed_m_s / (2.0 * self.brake_m_s2)

    def command(self, position_m, velocity_m_s) -> None:
        self.reference = [float(v) for v in position_m]
        self.reference_velocity = [float(v) for v in velocity_m_s]
        self.holding = False

    def hold(self) -> None:
        self.holding = True

    def advance(self, dt: float) -> None:
        if dt <= 0.0:
            return
        n = max(1, math.ceil(dt / SUBSTEP_S - 1e-9))
        h = dt / n
        x, v = self.position, self.velocity
        w = self.omega
        kp, kd = w * w, 2.0 * w
        (rx, ry, rz), (wx, wy, wz) = self.reference, self.reference_velocity
        vx, vy, vz = v
        # plain floats, unrolled: this runs every simulated millisecond of thousands of runs
        for _ in range(n):
            if self.holding:  # constant deceleration, integrated exactly: the stop lands on the plan
                speed = math.sqrt(vx * vx + vy * vy + vz * vz)
                if speed == 0.0:
                    break
                stops = speed <= self.brake_m_s2 * h  # within this sub-step
                t = speed / self.brake_m_s2 if stops else h
                travel = (speed - 0.5 * self.brake_m_s2 * t) * t / speed
                k = 0.0 if stops else 1.0 - self.brake_m_s2 * h / speed
                x[0] += vx * travel
                x[1] += vy * travel
                x[2] += vz * travel
                vx, vy, vz = vx * k, vy * k, vz * k
                continue
            ax = kp * (rx - x[0]) + kd * (wx - vx)
            ay = kp * (ry - x[1]) + kd * (wy - vy)
            az = kp * (rz - x[2]) + kd * (wz - vz)
            norm = math.sqrt(ax * ax + ay * ay + az * az)
            k = h * self.max_accel_m_s2 / norm if norm > self.max_accel_m_s2 else h
            vx, vy, vz = vx + ax * k, vy + ay * k, vz + az * k
            speed = math.sqrt(vx * vx + vy * vy + vz * vz)
            if speed > self.max_speed_m_s:
                k = self.max_speed_m_s / speed
                vx, vy, vz = vx * k, vy * k, vz * k
            x[0] += vx * h
            x[1] += vy * h
            x[2] += vz * h
        v[0], v[1], v[2] = vx, vy, vz


class LayerPlant:
    # the probe starts 1.5 mm above the surface, as an operator starts force control: a seek that touches nothing
    # goes no deeper than 2.4 mm at the default limits (control.safety.blind_seek_depth_m)
    def __init__(self, surface_m=0.025, modulus_pa=60e3, frame_period_s=0.01, latency_s=0.005,
                 start_m=(0.03, 0.015, 0.0265), stiff_mask=None, stiff_factor=1.0, noise_pa=50.0,
                 full_scale_pa=None, robot: SecondOrderRobot | None = None):
        self.surface_m = surface_m
        self.modulus = np.full(SHAPE, modulus_pa)
        if stiff_mask is not None:
            self.modulus[stiff_mask] *= stiff_factor
        self.frame_period_s = frame_period_s
        self.latency_s = latency_s
        self.robot = robot  # None: the robot is exactly where the last reference put it
        self.x = list(robot.position) if robot is not None else list(start_m)
        self.v = [0.0, 0.0, 0.0]
        self.history: list[tuple[float, float]] = []
        self.frame: TactileFrame | None = None
        self.seq = 0
        self.next_frame_t = 0.0
        self.sensor_alive = True
        self.slave_alive = True
        self.extra_force_pa = 0.0
        # white noise per element and frame, as the simulated array's default (hardware/sim/settings.py): an
        # array without noise repeats its frames exactly, which the loop takes for a frozen array
        self.noise_pa = noise_pa
        self.full_scale_pa = full_scale_pa  # None: an array that never saturates
        self.rng = np.random.default_rng(1)
        self.array_fault: str | None = None  # "zeros" | "frozen": what a dead or hung array streams
        self.stamp_offset_s = 0.0
        self.position_offset_m = (0.0, 0.0, 0.0)
        self._frozen_position: tuple[float, float, float] | None = None
        self._t = None

    @property
    def stiffness_N_m(self) -> float:
        """The face's stiffness on the layer: every element's E * A / L0."""
        return float(self.modulus.sum()) * ELEMENT_AREA_M2 / self.surface_m

    def pressure_at(self, z: float) -> np.ndarray:
        d = max(self.surface_m - z, 0.0)
        noise = self.rng.normal(0.0, self.noise_pa, SHAPE) if np.any(self.noise_pa) else 0.0
        return self.modulus * d / self.surface_m + self.extra_force_pa + noise

    def freeze_position(self) -> None:
        """The position reading sticks where the robot is now (an encoder or its link hung; the velocity
        read from it is then zero), while the robot itself goes on moving."""
        self._frozen_position = (self.x[0], self.x[1], self.x[2])

    def poll(self, now: float) -> None:
        robot = self.robot
        if robot is not None:
            robot.advance(now - self._t if self._t is not None else 0.0)
            self.x, self.v = list(robot.position), list(robot.velocity)
        self._t = now
        self.history.append((now, self.x[2]))
        if self.sensor_alive and now >= self.next_frame_t:
            t_sample = now - self.latency_s
            z = np.interp(t_sample, [h[0] for h in self.history[-50:]], [h[1] for h in self.history[-50:]])
            self.seq += 1
            p = self.pressure_at(float(z))
            saturated = None
            if self.full_scale_pa is not None:
                saturated = p >= self.full_scale_pa
                p = np.minimum(p, self.full_scale_pa)
            if self.array_fault == "zeros":
                p, saturated = np.zeros(SHAPE), np.zeros(SHAPE, bool)
            elif self.array_fault == "frozen" and self.frame is not None:
                p, saturated = self.frame.pressure_pa, self.frame.saturated
            self.frame = TactileFrame(self.seq, t_sample + self.stamp_offset_s, p, saturated)
            self.next_frame_t = now + self.frame_period_s
        if self._frozen_position is not None:
            x, v = self._frozen_position, (0.0, 0.0, 0.0)
        else:
            off = self.position_offset_m
            x, v = (self.x[0] + off[0], self.x[1] + off[1], self.x[2] + off[2]), tuple(self.v)
        self._slave = SlaveState(int(now * 1e6), now, x, v)

    def true_force_N(self) -> float:
        """The force the layer pushes back with where the probe is now (no noise, no sensor)."""
        d = max(self.surface_m - self.x[2], 0.0)
        return float((self.modulus * d / self.surface_m).sum()) * ELEMENT_AREA_M2

    def slave(self, now: float) -> SlaveState | None:
        return self._slave if self.slave_alive else None

    def apply(self, result) -> None:
        robot = self.robot
        if robot is not None:
            if result.hold:
                robot.hold()
            else:
                robot.command(result.position_ref_m, result.velocity_ref_m_s)
        elif not result.hold:
            self.x = list(result.position_ref_m)
            self.v = list(result.velocity_ref_m_s)
