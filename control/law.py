"""Jacobian-inverse hybrid impedance control: the reference trajectory of Eq. 2 with Eq. 3's start.

    Xr'' = Md^-1 [ -Fe + (I - S) Fd - Bd (Xr' - S Xd') - Kd S (Xr - Xd) ] + S Xd''        (2)
    Xr(0) = Xs(0),  Xr'(0) = Xs'(0)                                                        (3)

Md, Bd, Kd and S are diagonal in the tissue frame, so the law is evaluated per axis with plain floats
(three scalar axes are several times cheaper than 3x3 numpy algebra at 1 kHz). Forces follow the paper's
sign: Fe is the force the probe exerts on the environment, so in force control (S = 0) the reference
settles where Fe = Fd. A palpation force of magnitude F pushing down into the tissue is Fd_z = -F.

The reference (Xr, Xr') is the integrator state; changing S changes only its acceleration, never the
state itself, so switching S_z at run time is bumpless by construction. The JI part (mapping Xr to joint
references through the inverse Jacobian) belongs to the slave's inner position loop.
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

    @property
    def sz(self) -> int:
        return int(self._s[2])

    def set_selection(self, axis: int, position_control: bool) -> None:
        self._s[axis] = 1.0 if position_control else 0.0

    def step(self, dt: float, x_d: Vec3, v_d: Vec3, a_d: Vec3, f_e: Vec3, f_d: Vec3) -> None:
        """Advance the reference by dt (semi-implicit Euler: velocity first, then position)."""
        x_r, v_r, a_r = self.x_r, self.v_r, self.a_r
        for i in range(3):
            s = self._s[i]
            a = (-f_e[i] + (1.0 - s) * f_d[i] - self._b[i] * (v_r[i] - s * v_d[i])
                 - self._k[i] * s * (x_r[i] - x_d[i])) / self._m[i] + s * a_d[i]
            a_r[i] = a
            v_r[i] += a * dt
            x_r[i] += v_r[i] * dt
