"""Reference solutions the finite-element model is validated against.

**Elastic layer bonded to a rigid base, frictionless surface load.** In the Fourier domain the
surface deflection under a normal pressure is exact and closed-form (the layer kernel of Vorovich,
Aleksandrov & Babeshko, *Non-classical mixed problems of elasticity*, 1974; also Argatov & Mishuris,
*Contact Mechanics of Articular Cartilage Layers*, Springer 2015, eq. 1.48):

    w^(xi) = 2 (1 - nu^2) / (E xi) * L(xi h) * p^(xi),
    L(t) = (2 k sinh 2t - 4 t) / (2 k cosh 2t + 1 + k^2 + 4 t^2),   k = 3 - 4 nu,

with L -> 1 (the half-space, Boussinesq) as h -> infinity. :func:`layer_kernel_ode` recomputes L by
integrating Navier's equations across the layer, which the tests compare with the closed form.

**Rigid rectangular punch on that layer** (:func:`rect_punch_stiffness`): the integral equation
"deflection = indentation over the contact area" is solved by collocation with uniform-pressure
panels. Each panel's influence is Love's exact half-space solution for a uniformly loaded rectangle
plus the layer's smooth correction (the Hankel transform of L - 1, which decays like exp(-2 xi h)),
and the stiffness is extrapolated to zero panel size (Richardson, first order, which the
square-root edge singularity of a flat punch dictates). For the half-space it reproduces the
rectangular-foundation formula of Pais & Kausel (:func:`pais_kausel_stiffness`) to within its stated
accuracy; it is independent of the finite-element code in everything but the elastic constants.
"""

from __future__ import annotations

import numpy as np
from scipy import integrate, special
from scipy.interpolate import CubicSpline
from scipy.linalg import expm


def layer_kernel(t: np.ndarray, nu: float) -> np.ndarray:
    """L(t), t = xi h, of a layer bonded to a rigid base (closed form, see the module docstring)."""
    t = np.asarray(t, dtype=float)
    k = 3.0 - 4.0 * nu
    # Divide through by cosh 2t so large t does not overflow.
    with np.errstate(over="ignore"):
        sech = 1.0 / np.cosh(2.0 * t)
    return (2.0 * k * np.tanh(2.0 * t) - 4.0 * t * sech) / (2.0 * k + (1.0 + k * k + 4.0 * t * t) * sech)


def layer_kernel_ode(t: float, nu: float) -> float:
    """L(t) from Navier's equations in plane strain (one Fourier mode across the bonded layer)."""
    young = 1.0
    lam = young * nu / ((1 + nu) * (1 - 2 * nu))
    mu = young / (2 * (1 + nu))
    kx, h = 1.0, float(t)
    # State (U, U', W, W') for u = U(z) sin kx, w = W(z) cos kx.
    a = np.array([[0, 1, 0, 0],
                  [(lam + 2 * mu) * kx**2 / mu, 0, 0, (lam + mu) * kx / mu],
                  [0, 0, 0, 1],
                  [0, -(lam + mu) * kx / (lam + 2 * mu), mu * kx**2 / (lam + 2 * mu), 0]])
    prop = expm(a * h)
    ya, yb = prop[:, 1], prop[:, 3]  # bonded base: U = W = 0, so only U'(0), W'(0) are free
    # Top: shear traction mu (U' - k W) = 0 and normal traction lam k U + (lam + 2 mu) W' = -1.
    m = np.array([[ya[1] - kx * ya[2], yb[1] - kx * yb[2]],
                  [lam * kx * ya[0] + (lam + 2 * mu) * ya[3], lam * kx * yb[0] + (lam + 2 * mu) * yb[3]]])
    ca, cb = np.linalg.solve(m, [0.0, -1.0])
    w_top = ya[2] * ca + yb[2] * cb
    return float(-w_top * kx / (2 * (1 - nu**2) / young))


def _love_rect(u1, u2, v1, v2):
    """Integral of 1/r over the rectangle [u1, u2] x [v1, v2] seen from the origin."""

    def prim(u, v):
        # u asinh(v/|u|) + v asinh(u/|v|): odd in u and in v, its mixed derivative is 1/r.
        a = np.where(u != 0, u * np.arcsinh(v / np.where(u != 0, np.abs(u), 1.0)), 0.0)
        b = np.where(v != 0, v * np.arcsinh(u / np.where(v != 0, np.abs(v), 1.0)), 0.0)
        return a + b

    return prim(u2, v2) - prim(u1, v2) - prim(u2, v1) + prim(u1, v1)


def _layer_correction(nu: float, thickness_m: float, r_max_m: float):
    """g(r): deflection of the layer minus that of the half-space, per unit point load, times pi E/(1-nu^2)."""
    s_max = 40.0  # L(s) - 1 < 1e-30 beyond

    def value(rho: float) -> float:
        f = lambda s: (layer_kernel(s, nu) - 1.0) * special.j0(s * rho)  # noqa: E731
        val, _ = integrate.quad(f, 0.0, s_max, limit=400, epsabs=1e-12)
        return val

    rho = np.linspace(0.0, r_max_m / thickness_m + 1e-6, 300)
    table = np.array([value(r) for r in rho]) / thickness_m
    return CubicSpline(rho * thickness_m, table)


def _punch_stiffness_at(half_x: float, half_y: float, young: float, nu: float, thickness_m: float | None,
                        n_x: int, n_y: int, correction) -> float:
    """Collocation with n_x x n_y panels over a quarter of the punch (the load is doubly symmetric)."""
    dx, dy = half_x / n_x, half_y / n_y
    xc = (np.arange(n_x) + 0.5) * dx
    yc = (np.arange(n_y) + 0.5) * dy
    gx, gy = np.meshgrid(xc, yc, indexing="ij")
    px, py = gx.ravel(), gy.ravel()
    infl = np.zeros((len(px), len(px)))
    for sx in (1.0, -1.0):
        for sy in (1.0, -1.0):
            # Panel j mirrored to (sx x_j, sy y_j); its influence on collocation point i.
            cx = sx * px[None, :] - px[:, None]
            cy = sy * py[None, :] - py[:, None]
            infl += _love_rect(cx - dx / 2, cx + dx / 2, cy - dy / 2, cy + dy / 2)
            if correction is not None:
                infl += dx * dy * correction(np.hypot(cx, cy))
    infl *= (1 - nu**2) / (np.pi * young)
    pressure = np.linalg.solve(infl, np.ones(len(px)))  # for a unit indentation
    return float(4.0 * pressure.sum() * dx * dy)


def rect_punch_stiffness(size_x_m: float, size_y_m: float, young_pa: float, nu: float,
                         thickness_m: float | None, panels: int = 24) -> float:
    """Normal stiffness (N/m) of a rigid frictionless rectangular punch on a bonded layer (or, with
    ``thickness_m=None``, a half-space), extrapolated from ``panels`` and ``panels/2`` panels along
    the short half-side of the punch."""
    half_x, half_y = size_x_m / 2.0, size_y_m / 2.0
    short, long_ = min(half_x, half_y), max(half_x, half_y)
    correction = None if thickness_m is None else _layer_correction(nu, thickness_m, 2.0 * np.hypot(half_x, half_y))

    def solve(n: int) -> float:
        m = max(1, int(round(n * long_ / short)))
        nx, ny = (n, m) if half_x <= half_y else (m, n)
        return _punch_stiffness_at(half_x, half_y, young_pa, nu, thickness_m, nx, ny, correction)

    fine, coarse = solve(panels), solve(panels // 2)
    return 2.0 * fine - coarse


def pais_kausel_stiffness(size_x_m: float, size_y_m: float, young_pa: float, nu: float) -> float:
    """Static vertical stiffness of a rigid rectangular foundation on a half-space (Pais & Kausel,
    Soil Dyn. Earthquake Eng. 7(4), 1988): K = G b / (1 - nu) * (3.1 (a/b)^0.75 + 1.6), a >= b half-sides."""
    a, b = max(size_x_m, size_y_m) / 2.0, min(size_x_m, size_y_m) / 2.0
    shear = young_pa / (2.0 * (1.0 + nu))
    return shear * b / (1.0 - nu) * (3.1 * (a / b) ** 0.75 + 1.6)
