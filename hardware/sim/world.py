"""The simulated world one rig's devices share: its clock, the robot's body and the tissue.

Time is the host's clock (``now_s`` as the devices are polled with it). The world keeps its state on a
fixed grid ``epoch + k * substep_s`` (the epoch is the first ``advance``), so what it computes does not
depend on how often or how irregularly the devices are polled: ``advance(now_s)`` integrates every grid
step up to ``now_s`` and nothing else, and repeating it (or going back in time) changes nothing.

After a host stall longer than ``max_catchup_s`` only its first ``max_catchup_s`` are integrated; for the
rest the robot is taken to have settled at rest on its last reference position (its inner loop settles
within a few tens of ms, and a reference that has not been refreshed for that long is one to hold). A
100 ms stall is integrated in full; integrating a debugger pause would cost time just when the loop is
late, for no difference.

The robot is position controlled and far stiffer than tissue, so the tissue does not push it back: the
world integrates the robot alone, and the tissue's forces are what the tactile sensor reads (sampled from
the recent trajectory the world keeps, so a frame describes the TSI where it was at its own instant).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import expm

from hardware.interfaces import ConnectionState, Vec3
from hardware.sim.settings import RobotSimSettings, SimSettings
from hardware.sim.tissue import TissueModel
from tissue.phantom import Phantom

HISTORY_S = 0.5  # trajectory kept for readings that describe a past instant (sensor latency, slow polls)
_GRID_EPS = 1e-6  # fraction of a step: absorbs rounding when a time lies on the grid
# The robot plans its braking at this fraction of its acceleration limit: the velocity loop lags the
# planned profile, and the headroom lets it follow without overshooting the target (0.08 mm on a 50 mm
# move, against 1.1 mm when braking is planned at the full limit).
BRAKE_FRACTION = 0.6
# Semi-implicit Euler follows the continuous inner loop within ~1 % of its step response while the
# velocity-loop gain times the step stays below this (measured: 0.044 gives 1.2 %, 0.088 gives 2.3 %).
EULER_GAIN_STEP = 0.05


def _norm(x: float, y: float, z: float) -> float:
    return math.sqrt(x * x + y * y + z * z)


class RobotBody:
    """The slave robot's TSI as its Cartesian inner position loop moves it.

    A cascade, as industrial controllers are built: a position P loop commands a velocity on top of the
    reference's feed-forward velocity, a velocity loop turns the error into an acceleration. For small
    errors the closed loop is second order with natural frequency ``bandwidth_hz`` and damping
    ``damping_ratio`` (gains ``kv = 2 zeta wn``, ``kp = wn / (2 zeta)``); the commanded velocity is
    limited to the maximum speed and to what still lets the robot brake onto the reference within the
    acceleration limit (planned at ``BRAKE_FRACTION`` of it), and the acceleration to its limit. The
    limits act on the vector norm (a Cartesian controller's limits do not depend on the direction of
    travel).

    A step with no limit active is integrated exactly (the closed loop is then linear: the zero-order-hold
    transition matrix, computed once per step length); one where a limit acts is integrated with
    semi-implicit Euler sub-steps short enough to follow the continuous loop (``EULER_GAIN_STEP``). Near
    the reference, where the loop spends most of its time, a 1 ms step then costs one update instead of
    four.
    """

    def __init__(self, settings: RobotSimSettings):
        wn = 2.0 * math.pi * settings.bandwidth_hz
        self._kv = 2.0 * settings.damping_ratio * wn
        self._kp = wn / (2.0 * settings.damping_ratio)
        self._vmax = settings.max_speed_m_s
        self._amax = settings.max_accel_m_s2
        self._brake = BRAKE_FRACTION * settings.max_accel_m_s2
        self._lo = settings.workspace_min_m
        self._hi = settings.workspace_max_m
        self.position: list[float] = list(settings.home_m)
        self.velocity: list[float] = [0.0, 0.0, 0.0]
        self.reference: list[float] = list(settings.home_m)
        self.reference_velocity: list[float] = [0.0, 0.0, 0.0]
        self.holding = False  # a hold's stop point is planned once, not re-planned ahead of the robot
        self._exact: dict[float, tuple[float, float, float, float]] = {}

    def _transition(self, dt: float) -> tuple[float, float, float, float]:
        """Exact transition over ``dt`` of one axis' (error - equilibrium error, velocity) when no limit
        acts: d(e)/dt = -v, dv/dt = kv * (kp * e - v), with e measured from its equilibrium -vr / kp."""
        phi = self._exact.get(dt)
        if phi is None:
            a = np.array([[0.0, -1.0], [self._kv * self._kp, -self._kv]])
            m = expm(a * dt)
            phi = self._exact[dt] = (float(m[0, 0]), float(m[0, 1]), float(m[1, 0]), float(m[1, 1]))
        return phi

    def set_reference(self, position_m: Vec3, velocity_m_s: Vec3) -> None:
        """Track a new reference; it is clamped into the workspace with its velocity zeroed there."""
        for i in range(3):
            p, v = float(position_m[i]), float(velocity_m_s[i])
            if p <= self._lo[i]:
                p, v = self._lo[i], max(v, 0.0)
            elif p >= self._hi[i]:
                p, v = self._hi[i], min(v, 0.0)
            self.reference[i] = p
            self.reference_velocity[i] = v
        self.holding = False

    def hold(self) -> None:
        """Brake to a stop (at the planned deceleration, within the acceleration limit) and stay there.

        The stop point is planned at the first call and kept by the ones after it until the next
        reference: re-planning it from the moving robot each tick would put it ahead again every time,
        and the robot would coast instead of braking. It is clamped into the workspace (the soft limits
        bind a hold as they bind a reference), where the brake may then use the full acceleration.
        """
        if self.holding:
            return
        v = self.velocity
        speed = _norm(*v)
        brake = speed / (2.0 * self._brake)  # stopping distance / speed
        self.reference = [min(max(self.position[i] + v[i] * brake, self._lo[i]), self._hi[i]) for i in range(3)]
        self.reference_velocity = [0.0, 0.0, 0.0]
        self.holding = True

    def settle(self) -> None:
        """At rest on the reference position (the end of a stall longer than the catch-up)."""
        self.position = list(self.reference)
        self.velocity = [0.0, 0.0, 0.0]
        self.reference_velocity = [0.0, 0.0, 0.0]

    def step(self, dt: float) -> None:
        if self._step_exact(dt):
            return
        n = max(1, math.ceil(dt * self._kv / EULER_GAIN_STEP))
        for _ in range(n):
            self._euler(dt / n)

    def _acceleration(self, x, v) -> tuple[float, float, float, bool]:
        """The cascade's commanded acceleration at position ``x``, velocity ``v``, and whether a speed,
        braking or acceleration limit shaped it (False: the loop is linear there)."""
        # plain floats, no helpers: this runs at least twice per simulated millisecond
        r, vr = self.reference, self.reference_velocity
        vmax, amax = self._vmax, self._amax
        ex, ey, ez = r[0] - x[0], r[1] - x[1], r[2] - x[2]
        err = math.sqrt(ex * ex + ey * ey + ez * ez)
        gain = self._kp
        limited = False
        if gain * err > vmax or gain * gain * err > 2.0 * self._brake:
            limit = min(vmax, math.sqrt(2.0 * self._brake * err))
            gain = min(gain, limit / err)
            limited = True
        cx, cy, cz = vr[0] + gain * ex, vr[1] + gain * ey, vr[2] + gain * ez
        speed = math.sqrt(cx * cx + cy * cy + cz * cz)
        if speed > vmax:
            k = vmax / speed
            cx, cy, cz = cx * k, cy * k, cz * k
            limited = True
        kv = self._kv
        ax, ay, az = kv * (cx - v[0]), kv * (cy - v[1]), kv * (cz - v[2])
        acc = math.sqrt(ax * ax + ay * ay + az * az)
        if acc > amax:
            k = amax / acc
            ax, ay, az = ax * k, ay * k, az * k
            limited = True
        return ax, ay, az, limited

    def _step_exact(self, dt: float) -> bool:
        """One exact step if no limit acts at its start or its end; False (nothing changed) otherwise."""
        x, v = self.position, self.velocity
        if self._acceleration(x, v)[3]:
            return False
        p00, p01, p10, p11 = self._transition(dt)
        r, vr, kp = self.reference, self.reference_velocity, self._kp
        new_x, new_v = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        for i in range(3):
            e_eq = -vr[i] / kp
            e = r[i] - x[i] - e_eq
            new_x[i] = r[i] - e_eq - (p00 * e + p01 * v[i])
            new_v[i] = p10 * e + p11 * v[i]
        if self._acceleration(new_x, new_v)[3]:
            return False
        self.position, self.velocity = new_x, new_v
        return True

    def _euler(self, dt: float) -> None:
        x, v = self.position, self.velocity
        ax, ay, az, _ = self._acceleration(x, v)
        v[0] += ax * dt
        v[1] += ay * dt
        v[2] += az * dt
        x[0] += v[0] * dt
        x[1] += v[1] * dt
        x[2] += v[2] * dt


class SimWorld:
    """Clock, robot and tissue of one simulated rig; every device's ``poll`` advances it."""

    def __init__(self, phantom: Phantom, tissue: TissueModel, settings: SimSettings | None = None):
        self.phantom = phantom
        self.tissue = tissue
        self.settings = settings if settings is not None else SimSettings()
        self.robot = RobotBody(self.settings.robot)
        self.dt_s = self.settings.substep_s
        self._max_steps = max(1, int(self.settings.max_catchup_s / self.dt_s))
        self.epoch_s: float | None = None
        self.step_index = 0
        self.skipped_s = 0.0  # host-stall time not integrated (see the module docstring)
        self._size = int(math.ceil(HISTORY_S / self.dt_s)) + 1
        self._history: list[tuple[float, ...]] = [()] * self._size
        self._oldest = 0

    @property
    def t_s(self) -> float:
        """Time of the current state (the newest grid point not after the last ``advance``)."""
        if self.epoch_s is None:
            raise RuntimeError("the simulated world has not been advanced yet")
        return self.epoch_s + self.step_index * self.dt_s

    def _record(self) -> None:
        x, v = self.robot.position, self.robot.velocity
        self._history[self.step_index % self._size] = (x[0], x[1], x[2], v[0], v[1], v[2])

    def advance(self, now_s: float) -> None:
        if not math.isfinite(now_s):
            raise ValueError(f"the simulated world cannot advance to {now_s!r} s")
        if self.epoch_s is None:
            self.epoch_s = float(now_s)
            self._record()
            return
        target = math.floor((now_s - self.epoch_s) / self.dt_s + _GRID_EPS)
        n = target - self.step_index
        if n <= 0:
            return
        robot, dt = self.robot, self.dt_s
        for _ in range(min(n, self._max_steps)):
            robot.step(dt)
            self.step_index += 1
            self._record()
        if n > self._max_steps:
            self.skipped_s += (n - self._max_steps) * dt
            robot.settle()
            self.step_index = target
            self._oldest = target
            self._record()
        self._oldest = max(self._oldest, self.step_index - self._size + 1)

    def state_at(self, t_s: float) -> tuple[Vec3, Vec3]:
        """TSI position and velocity at ``t_s``, interpolated between grid points.

        Times before the kept history (or inside a skipped stall) give the oldest kept state; times
        after the current state give the current state.
        """
        if self.epoch_s is None:
            raise RuntimeError("the simulated world has not been advanced yet")
        u = (t_s - self.epoch_s) / self.dt_s
        k0 = math.floor(u + _GRID_EPS)
        if k0 >= self.step_index:
            return self._unpack(self._history[self.step_index % self._size])
        if k0 < self._oldest:
            return self._unpack(self._history[self._oldest % self._size])
        a = self._history[k0 % self._size]
        frac = u - k0
        if frac <= _GRID_EPS:
            return self._unpack(a)
        b = self._history[(k0 + 1) % self._size]
        return self._unpack(tuple(p + frac * (q - p) for p, q in zip(a, b)))

    @staticmethod
    def _unpack(s: tuple[float, ...]) -> tuple[Vec3, Vec3]:
        return (s[0], s[1], s[2]), (s[3], s[4], s[5])

    def instant_index(self, rate_hz: float) -> int:
        """Index ``m`` of the newest instant ``epoch + m / rate_hz`` the world has reached."""
        return math.floor(self.step_index * self.dt_s * rate_hz + _GRID_EPS)

    def instant_s(self, m: int, rate_hz: float) -> float:
        return self.epoch_s + m / rate_hz


class SimDevice:
    """Connection state and the shared world, common to the simulated devices (a mixin before the ABC).

    ``poll`` always advances the world, connected or not: physics does not wait for a cable.
    """

    def __init__(self, world: SimWorld):
        self.world = world
        self._connection = ConnectionState.DISCONNECTED

    @property
    def connection(self) -> ConnectionState:
        return self._connection

    @property
    def connected(self) -> bool:
        return self._connection == ConnectionState.CONNECTED

    def open(self) -> None:
        self._connection = ConnectionState.CONNECTED
        self._on_open()

    def close(self) -> None:
        self._connection = ConnectionState.DISCONNECTED

    def simulate_unplug(self) -> None:
        """Fault injection: the device stops answering, as if its cable were pulled (``open`` reconnects)."""
        if self._connection == ConnectionState.CONNECTED:
            self._connection = ConnectionState.LOST

    def _next_sample(self, now_s: float, rate_hz: float, last_index: int) -> tuple[int, float] | None:
        """Advance the world to ``now_s``; the newest sampling instant (index, time) of a device reporting
        at ``rate_hz``, or None when disconnected or nothing newer than ``last_index`` is due."""
        world = self.world
        world.advance(now_s)
        if not self.connected:
            return None
        m = world.instant_index(rate_hz)
        if m <= last_index:
            return None
        return m, world.instant_s(m, rate_hz)

    def _on_open(self) -> None:
        """What a fresh connection resets beyond the state (the sensor re-takes its zero)."""
