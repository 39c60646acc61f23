"""Jacobian-inverse hybrid impedance control: the reference trajectory of Eq. 2 with Eq. 3's start.

    Xr'' = Md^-1 [ -Fe + (I - S) Fd - Bd (Xr' - S Xd') - Kd S (Xr - Xd) ] + S Xd''        (2)
    Xr(0) = Xs(0),  Xr'(0) = Xs'(0)                                                        (3)

Md, Bd, Kd and S are diagonal in the tissue frame, so the law is evaluated per axis with plain floats
(three scalar axes are several times cheaper than 3x3 numpy algebra at 1 kHz). Forces follow the paper's
sign: Fe is the force the probe exerts on the environment, so in force control (S = 0) the reference
settles where Fe = Fd. A palpation force of magnitude F pushing down into the tissue is Fd_z = -F.

The reference (Xr, Xr') is the integrator state; changing S changes only its acceleration, never the
state itself, so switching S_z at run time is bumpless by construction.

The integration is implicit (backward Euler) in the law's own damping and stiffness, with the measured
force held over the step: the reference's own dynamics are then stable for every positive M, B, K and
step, where the explicit (semi-implicit Euler) scheme diverged once dt * B / M or dt^2 * K / M passed 2
(M = 0.03 kg with B = 80 ran the reference to 1e8 m in 56 ms). What remains explicit is the tissue's
reaction through F_e; :func:`control.config.stable_for_environment` bounds it, and the configuration
refuses gains that fail it. The JI part (mapping Xr to joint references through the inverse Jacobian)
belongs to the slave's inner position loop.
"""

from __future__ import annotations

from control.config import ImpedanceGains

Vec3 = tuple[float, float, float]


class HybridImpedanceLaw:
    __slots__ = ("_m", "_b", "_k", "_s", "x_r", "v_r", "a_r")

    def __init__(self, gains: ImpedanceGains):
        self.set_gains(gains)
        self._s = [1.0, 1.0, 1.0]
        self.x_r = [0.0, 0.0, 0.0]
        self.v_r = [0.0, 0.0, 0.0]
        self.a_r = [0.0, 0.0, 0.0]

    def set_gains(self, gains: ImpedanceGains) -> None:
        self._m = list(gains.mass_kg)
        self._b = list(gains.damping_N_s_m)
        self._k = list(gains.stiffness_N_m)

    def reset(self, x_s: Vec3, v_s: Vec3) -> None:
        """Eq. 3: start the reference at the slave's measured state."""
        self.x_r = [float(v) for v in x_s]
        self.v_r = [float(v) for v in v_s]
        self.a_r = [0.0, 0.0, 0.0]

    def damping_N_s_m(self, axis: int) -> float:
        return self._b[axis]

    @property
    def sz(self) -> int:
        return int(self._s[2])

    def set_selection(self, axis: int, position_control: bool) -> None:
        self._s[axis] = 1.0 if position_control else 0.0

    def step(self, dt: float, x_d: Vec3, v_d: Vec3, a_d: Vec3, f_e: Vec3, f_d: Vec3) -> None:
        """Advance the reference by dt: backward Euler in B and K (module docstring), F_e held."""
        x_r, v_r, a_r = self.x_r, self.v_r, self.a_r
        for i in range(3):
            s, m, b, k = self._s[i], self._m[i], self._b[i], self._k[i]
            drive = -f_e[i] + (1.0 - s) * f_d[i] + b * s * v_d[i] - k * s * (x_r[i] - x_d[i]) + m * s * a_d[i]
            v = (m * v_r[i] + dt * drive) / (m + dt * b + dt * dt * k * s)
            a_r[i] = (v - v_r[i]) / dt if dt > 0 else 0.0
            v_r[i] = v
            x_r[i] += v * dt
