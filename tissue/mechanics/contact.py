"""Frictionless unilateral contact of a rigid, level, flat face with a linear-elastic surface.

The surface is represented by the nodes under the face and their compliance ``C`` (vertical
displacement per vertical force, every other surface node free of load). With the face at height z,
node i (undeformed height h_i) carries a downward force f_i >= 0 and sinks by w = C f; it may not end
above the face, and it carries force only where it touches it:

    f >= 0,   w - (h - z) >= 0,   f . (w - (h - z)) = 0          (a linear complementarity problem)

``C`` is symmetric positive definite, so the solution is unique for every z and, because z enters
linearly, it is piecewise linear in z: between two events (a node touching down or lifting off) the
set of nodes in contact is fixed and f = C_AA^-1 (h_A - z). :func:`contact_path` follows the face
down from first touch and records every event, which makes the table of forces against depth exact
for the linear model: nothing is interpolated between samples, and past the last event the
response stays linear for ever.

Where several nodes change state at the same depth (a level face on a flat surface touches every
node at once) the new contact set is found by Murty's principal pivoting on the tied nodes, which is
finite for the positive definite matrices met here.

All linear algebra here goes through numpy's own BLAS/LAPACK: mixing it with scipy's (a second
OpenBLAS with its own spinning threads) in these many small operations makes them fight over the
cores.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ContactPath:
    """Nodal forces along the descent: for t = -z in [t[k], t[k+1]), f = f0[k] + (t - t[k]) * df[k].

    ``t`` is empty when the face never touches (no nodes under it)."""

    t: np.ndarray  # (K,) increasing; t[0] = -(highest node) is the first touch
    f0: np.ndarray  # (K, n) nodal forces at each event
    df: np.ndarray  # (K, n) their rate of change per metre of further descent

    def forces(self, z_m: float) -> np.ndarray:
        t = -z_m
        k = int(np.searchsorted(self.t, t, side="right")) - 1
        if k < 0:
            return np.zeros(self.f0.shape[1])
        return self.f0[k] + (t - self.t[k]) * self.df[k]

    def mapped(self, weights: np.ndarray) -> "ContactPath":
        """The same path for linear combinations of the nodal forces (e.g. per sensor element)."""
        return ContactPath(self.t, self.f0 @ weights.T, self.df @ weights.T)


class ContactError(RuntimeError):
    """The contact path could not be followed (a non-positive-definite compliance or a cycling pivot)."""


def contact_path(compliance: np.ndarray, heights_m: np.ndarray, tol_m: float = 1e-12,
                 max_events: int | None = None) -> ContactPath:
    """Exact piecewise-linear contact forces of the nodes under a descending rigid level face.

    Between events the inverse of the active block of ``C`` is kept up to date by bordering (a node
    touching down) and by its Schur-complement formula (a node lifting off), O(n^2) per event; it is
    refactorised from scratch every ``_REFRESH`` updates so rounding cannot build up, and whenever
    several nodes change state at once.
    """
    c = np.ascontiguousarray(compliance, dtype=float)
    h = np.asarray(heights_m, dtype=float)
    n = len(h)
    if n == 0:
        return ContactPath(np.zeros(0), np.zeros((0, 0)), np.zeros((0, 0)))
    max_events = max_events or 4 * n + 10
    t = -float(h.max())
    active = _resolve(c, h >= h.max() - tol_m, np.zeros(n, dtype=bool))
    idx = np.flatnonzero(active)
    inv, alpha, beta = _fresh(c, idx, h)
    updates = 0
    ts, f0s, dfs = [], [], []
    for _ in range(max_events):
        f = np.zeros(n)
        f[idx] = alpha + t * beta
        df = np.zeros(n)
        df[idx] = beta
        ts.append(t)
        f0s.append(f)
        dfs.append(df)
        # Next event: an active node whose force falls to zero, or an idle node whose gap closes.
        # (Two matrix-vector products: at this size they are several times faster than one
        # matrix-matrix product with two columns.)
        gap = c @ f - h - t
        gap_rate = c @ df - 1.0
        # Rates within rounding of zero are zero: they would only schedule spurious far-off events.
        falling = beta < -_RATE_TOL * np.abs(beta).max(initial=0.0)
        closing = ~active & (gap_rate < -_RATE_TOL)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_leave = np.where(falling, -(alpha + t * beta) / beta, np.inf)
            t_enter = np.where(closing, -gap / gap_rate, np.inf)
        step = min(t_leave.min(initial=np.inf), t_enter.min(initial=np.inf))
        if not np.isfinite(step):
            return ContactPath(np.array(ts), np.array(f0s), np.array(dfs))
        step = max(step, 0.0)
        t += step
        leaving = idx[t_leave <= step + tol_m]
        entering = np.flatnonzero(t_enter <= step + tol_m)
        if len(leaving) + len(entering) == 1 and updates < _REFRESH:
            # One node changes state: in the non-degenerate case the new set is always consistent.
            if len(entering):
                k = int(entering[0])
                inv, alpha, beta = _border(inv, alpha, beta, c, idx, k, h[k])
                idx = np.append(idx, k)
            else:
                p = int(np.flatnonzero(idx == leaving[0])[0])
                inv, alpha, beta = _unborder(inv, alpha, beta, p)
                idx = np.delete(idx, p)
            active[entering] = True
            active[leaving] = False
            updates += 1
        else:
            keep = active.copy()
            keep[leaving] = False
            tight = active.copy()
            tight[entering] = True
            active = _resolve(c, tight, keep)
            idx = np.flatnonzero(active)
            inv, alpha, beta = _fresh(c, idx, h)
            updates = 0
    raise ContactError(f"contact path did not settle after {max_events} events")


_REFRESH = 64
_RATE_TOL = 1e-10


def _fresh(c: np.ndarray, idx: np.ndarray, h: np.ndarray):
    """Inverse of the active block and alpha, beta with forces = alpha + t beta."""
    if len(idx) == 0:
        return np.zeros((0, 0)), np.zeros(0), np.zeros(0)
    block = c[np.ix_(idx, idx)]
    try:
        np.linalg.cholesky(block)  # only to refuse a matrix that is not positive definite
    except np.linalg.LinAlgError:
        raise ContactError("the surface compliance is not positive definite") from None
    inv = np.linalg.inv(block)
    inv = 0.5 * (inv + inv.T)
    return inv, inv @ h[idx], inv.sum(axis=1)


def _border(inv, alpha, beta, c, idx, k, h_k):
    """Append node k to the active set: bordered inverse and updated alpha, beta, all O(n^2)."""
    u = c[idx, k]
    v = inv @ u
    s = c[k, k] - u @ v
    if s <= 0:
        raise ContactError("the surface compliance is not positive definite")
    m = len(idx)
    out = np.empty((m + 1, m + 1))
    np.multiply((v / s)[:, None], v[None, :], out=out[:m, :m])
    out[:m, :m] += inv
    out[:m, m] = out[m, :m] = -v / s
    out[m, m] = 1.0 / s
    ga = (h_k - u @ alpha) / s
    gb = (1.0 - u @ beta) / s
    return out, np.append(alpha - ga * v, ga), np.append(beta - gb * v, gb)


def _unborder(inv, alpha, beta, p):
    """Remove the p-th active node: inverse by its Schur complement, updated alpha, beta."""
    col = np.delete(inv[:, p], p)
    pivot = inv[p, p]
    keep = np.arange(len(inv)) != p
    rest = inv[np.ix_(keep, keep)]
    rest -= (col / pivot)[:, None] * col[None, :]
    return rest, np.delete(alpha, p) - col * (alpha[p] / pivot), np.delete(beta, p) - col * (beta[p] / pivot)


def _resolve(c: np.ndarray, tight: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The contact set leaving a point where the nodes in ``tight`` touch the face.

    Nodes in ``keep`` carry force (their rate of change is free); the other tight nodes carry none
    and may stay in contact only if their force then grows, or leave only if their gap then opens:
    a small LCP in the force rates, solved by Murty's least-index principal pivoting.
    """
    free = np.flatnonzero(tight & keep)
    pivot = np.flatnonzero(tight & ~keep)
    if len(pivot) == 0:
        return tight & keep
    inside = np.ones(len(pivot), dtype=bool)  # start with every tied node in contact
    for _ in range(20 * len(pivot) + 10):
        idx = np.concatenate([free, pivot[inside]])
        rate = np.zeros(len(tight))
        if len(idx):
            try:
                rate[idx] = np.linalg.solve(c[np.ix_(idx, idx)], np.ones(len(idx)))
            except np.linalg.LinAlgError:
                raise ContactError("the surface compliance is not positive definite") from None
        scale = max(1e-300, float(np.abs(rate).max(initial=0.0)))
        gap_rate = c[pivot][:, idx] @ rate[idx] - 1.0
        bad = np.flatnonzero((inside & (rate[pivot] < -_RATE_TOL * scale)) | (~inside & (gap_rate < -_RATE_TOL)))
        if len(bad) == 0:
            out = np.zeros(len(tight), dtype=bool)
            out[free] = True
            out[pivot[inside]] = True
            return out
        inside[bad[0]] = ~inside[bad[0]]
    raise ContactError("principal pivoting did not settle the contact set")


def tributary_weights(x_nodes: np.ndarray, y_nodes: np.ndarray, extent: tuple[float, float, float, float],
                      face_lo: tuple[float, float], pitch_m: float, shape: tuple[int, int]) -> np.ndarray:
    """(rows*cols, n) share of each node's force taken by each sensor element.

    Each node stands for the patch of surface nearest to it (half-way to its neighbours, clipped to the
    phantom ``extent`` = (x0, x1, y0, y1)); its force is split between elements in proportion to the
    part of that patch each element covers, normalised over the face so no force is lost at its edges.
    Nodes are given by their coordinates, one pair per node.
    """
    xs, ys = np.asarray(x_nodes, float), np.asarray(y_nodes, float)
    rows, cols = shape
    x0, y0 = face_lo
    weights = np.zeros((rows * cols, len(xs)))
    if len(xs) == 0:
        return weights
    px = _patches(xs, extent[0], extent[1])
    py = _patches(ys, extent[2], extent[3])
    ex = x0 + pitch_m * np.arange(rows + 1)
    ey = y0 + pitch_m * np.arange(cols + 1)
    ox = np.clip(np.minimum(px[1][None, :], ex[1:, None]) - np.maximum(px[0][None, :], ex[:-1, None]), 0, None)
    oy = np.clip(np.minimum(py[1][None, :], ey[1:, None]) - np.maximum(py[0][None, :], ey[:-1, None]), 0, None)
    weights = (ox[:, None, :] * oy[None, :, :]).reshape(rows * cols, len(xs))
    total = weights.sum(axis=0)
    # A node exactly on the face's outline can have a zero-width patch inside it only if the face
    # touches the phantom along a line; such a node carries no force worth assigning.
    return np.divide(weights, total, out=np.zeros_like(weights), where=total > 0)


def _patches(coord: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-node intervals of nodes on a tensor line, from each node's own sorted line of values."""
    line = np.unique(coord)
    mids = 0.5 * (line[1:] + line[:-1])
    left = np.concatenate([[lo], mids])
    right = np.concatenate([mids, [hi]])
    pos = np.searchsorted(line, coord)
    return left[pos], right[pos]
