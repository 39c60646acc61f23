"""What small strain costs: the punch on a homogeneous block, solved again at finite strain.

A 10 mm indentation of a 25 mm layer is a 40 % compression under the face: far outside small strain.
This module solves the same problem as the linear model for a homogeneous block with the TSI at its
centre, but geometrically and materially nonlinear:

* material: compressible neo-Hookean, ``W = mu/2 (J^-2/3 I1 - 3) + kappa/2 (J_bar - 1)^2``, whose
  small-strain limit is the linear model's (same mu and kappa);
* elements: the same trilinear hexahedra, total Lagrangian, with the volumetric energy evaluated on
  the element's mean dilatation ``J_bar`` (the finite-strain form of the Q1/P0 element of Simo, Taylor
  & Pister 1985), so it does not lock either;
* contact: the nodes under the face follow it down and slide freely (frictionless); the face is level
  and the surface flat, so they stay in contact as long as they push on it, which is checked;
* solution: Newton's method on load steps, with element tangents from complex-step differentiation of
  the element forces (exact to rounding, no hand-derived geometric stiffness to get wrong).

A quarter of the block is meshed (symmetry planes through the face's centre). The result is the
ratio of the nonlinear to the linear force at each indentation, ``stiffening(d)``; the tissue model can
apply it per element (see :class:`~hardware.sim.mechanics.model.MeshSettings`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from hardware.sim.mechanics.fem import _REF, HexGrid, element_dofs, graded_levels, table_dofs
from hardware.sim.mechanics.progress import Progress
from hardware.sim.mechanics.validation import graded_line


def _cofactor(f):
    """Cofactor matrix (= det F * F^-T) and determinant of (..., 3, 3) arrays; complex-safe."""
    c = np.empty_like(f)
    c[..., 0, 0] = f[..., 1, 1] * f[..., 2, 2] - f[..., 1, 2] * f[..., 2, 1]
    c[..., 0, 1] = f[..., 1, 2] * f[..., 2, 0] - f[..., 1, 0] * f[..., 2, 2]
    c[..., 0, 2] = f[..., 1, 0] * f[..., 2, 1] - f[..., 1, 1] * f[..., 2, 0]
    c[..., 1, 0] = f[..., 0, 2] * f[..., 2, 1] - f[..., 0, 1] * f[..., 2, 2]
    c[..., 1, 1] = f[..., 0, 0] * f[..., 2, 2] - f[..., 0, 2] * f[..., 2, 0]
    c[..., 1, 2] = f[..., 0, 1] * f[..., 2, 0] - f[..., 0, 0] * f[..., 2, 1]
    c[..., 2, 0] = f[..., 0, 1] * f[..., 1, 2] - f[..., 0, 2] * f[..., 1, 1]
    c[..., 2, 1] = f[..., 0, 2] * f[..., 1, 0] - f[..., 0, 0] * f[..., 1, 2]
    c[..., 2, 2] = f[..., 0, 0] * f[..., 1, 1] - f[..., 0, 1] * f[..., 1, 0]
    det = np.einsum("...j,...j->...", f[..., 0, :], c[..., 0, :])
    return c, det


class NeoHookeanBlock:
    """Element forces and tangents of a hexahedral grid at finite strain (see the module docstring)."""

    def __init__(self, grid: HexGrid, young_pa: float, nu: float):
        self.grid = grid
        self.mu = young_pa / (2.0 * (1.0 + nu))
        self.kappa = young_pa / (3.0 * (1.0 - 2.0 * nu))
        coords = grid.node_coords().reshape(-1, 3)
        self.conn = grid.element_nodes()
        self.edofs = element_dofs(grid)
        xe = coords[self.conn]
        g = 1.0 / np.sqrt(3.0)
        pts = np.array([[a, b, c] for c in (-g, g) for b in (-g, g) for a in (-g, g)])
        fac = 1.0 + pts[:, None, :] * _REF[None, :, :]
        dn = np.empty((8, 8, 3))
        dn[..., 0] = _REF[None, :, 0] * fac[..., 1] * fac[..., 2] / 8.0
        dn[..., 1] = _REF[None, :, 1] * fac[..., 0] * fac[..., 2] / 8.0
        dn[..., 2] = _REF[None, :, 2] * fac[..., 0] * fac[..., 1] / 8.0
        jac = np.einsum("eai,qaj->eqij", xe, dn)
        self.w0 = np.linalg.det(jac)  # Gauss weights are 1
        self.g0 = np.einsum("qaj,eqji->eqai", dn, np.linalg.inv(jac))  # dN_a/dX_i
        self.v0 = self.w0.sum(axis=1)
        self.n_dofs = 3 * coords.shape[0]

    def element_forces(self, ue: np.ndarray) -> np.ndarray:
        """(..., nel, 8, 3) internal nodal forces for element displacements ``ue`` (..., nel, 8, 3)."""
        f = np.eye(3) + np.einsum("...eai,eqaj->...eqij", ue, self.g0)
        cof, det = _cofactor(f)
        i1 = np.einsum("...ij,...ij->...", f, f)
        j23 = det ** (-2.0 / 3.0)
        # mu J^-2/3 (F - I1/3 F^-T), with F^-T = cof / J
        p_iso = self.mu * j23[..., None, None] * (f - (i1 / (3.0 * det))[..., None, None] * cof)
        j_bar = np.einsum("...eq,eq->...e", det, self.w0) / self.v0
        p = p_iso + (self.kappa * (j_bar - 1.0))[..., None, None, None] * cof  # kappa (J_bar - 1) J F^-T
        return np.einsum("...eqij,eqaj,eq->...eai", p, self.g0, self.w0)

    def forces_and_tangent(self, u: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
        ue = u[self.edofs].reshape(-1, 8, 3)
        fe = self.element_forces(ue)
        step = 1e-30 * max(1.0, float(np.abs(ue).max()))
        pert = np.broadcast_to(ue, (24,) + ue.shape).astype(complex)
        pert = pert.reshape(24, -1, 24).copy()
        pert[np.arange(24), :, np.arange(24)] += 1j * step
        ke = self.element_forces(pert.reshape(24, -1, 8, 3)).imag.reshape(24, -1, 24) / step  # [col, e, row]
        ke = ke.transpose(1, 2, 0)
        f = np.bincount(self.edofs.ravel(), weights=fe.reshape(-1), minlength=self.n_dofs)
        rows = np.broadcast_to(self.edofs[:, :, None], ke.shape).ravel()
        cols = np.broadcast_to(self.edofs[:, None, :], ke.shape).ravel()
        k = sp.csr_matrix((ke.ravel(), (rows, cols)), shape=(self.n_dofs, self.n_dofs))
        return f, k


@dataclass(frozen=True)
class StiffeningCurve:
    indentation_m: np.ndarray  # (n,) from 0
    force_linear_N: np.ndarray  # the small-strain model on the same mesh
    force_nonlinear_N: np.ndarray
    all_compressive: bool  # every node under the face pushed on it at every step

    def ratio(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            r = self.force_nonlinear_N / self.force_linear_N
        r[0] = 1.0
        return r


class _NoConvergence(RuntimeError):
    pass


def _contact_step(block, u, depth, active, fixed, top, top_x, initially_under, half_face, spacing_m):
    """Newton iterations with the contact set updated in the deformed configuration.

    A top node is held on the face while it is under the face (its current x within the face) and
    pushes on it; material drawn in under the face's edge joins the contact, and a node pulled away
    from the face leaves it.
    """
    zdof = 3 * top + 2
    for _ in range(60):
        f, kt = block.forces_and_tangent(u)
        reaction = -f[zdof]
        current_x = top_x + u[3 * top]
        height = u[zdof] + depth  # > 0: above the face
        grown = (active | ((current_x <= half_face) & (height > 0))) & (current_x <= half_face + 0.25 * spacing_m)
        released = grown & (reaction < 0) & (np.abs(height) < 1e-12) & ~initially_under
        new_active = grown & ~released
        cdofs = zdof[new_active]
        fixed_now = fixed.copy()
        fixed_now[cdofs] = True
        free = np.flatnonzero(~fixed_now)
        step = np.zeros(block.n_dofs)
        step[cdofs] = -depth - u[cdofs]
        res = f[free]
        scale = max(1e-12, float(np.abs(f[cdofs]).max()))
        if np.array_equal(new_active, active) and not step.any() and np.abs(res).max() < 1e-9 * scale:
            return u, f, active
        active = new_active
        du = np.zeros(block.n_dofs)
        du[cdofs] = step[cdofs]
        du[free] = spla.spsolve(kt[free][:, free].tocsc(), -(f + kt @ step)[free])
        # Backtrack if the full Newton step would invert an element (the energy has no meaning there).
        for _ in range(20):
            trial = u + du
            if np.all(np.isfinite(block.element_forces(trial[block.edofs].reshape(-1, 8, 3)))):
                break
            du[free] *= 0.5
        else:
            raise _NoConvergence
        u = trial
    raise _NoConvergence


def punch_on_block(length_m: float, width_m: float, thickness_m: float, young_pa: float, nu: float,
                   face_x_m: float = 8e-3, max_indentation_m: float = 12e-3, step_m: float = 0.5e-3,
                   spacing_m: float = 1e-3, layers: int = 8, progress: Progress | None = None) -> StiffeningCurve:
    """Force against indentation of a level face (``face_x_m`` along x, the block's whole width along y)
    pressed into the centre of a homogeneous block bonded to the table, linear and at finite strain."""
    half_l, half_w, half_face = length_m / 2.0, width_m / 2.0, face_x_m / 2.0
    x = graded_line(half_face + 2e-3, spacing_m, half_l, growth=1.25)
    y = np.linspace(0.0, half_w, max(2, int(round(half_w / (1.5 * spacing_m)))) + 1)
    levels = graded_levels(layers, min(1.5 * spacing_m / thickness_m, 1.0 / layers))
    grid = HexGrid(x, y, levels, np.full((len(x), len(y)), thickness_m))
    block = NeoHookeanBlock(grid, young_pa, nu)
    nx1, ny1, nz1 = grid.node_shape
    i, j, k = np.meshgrid(np.arange(nx1), np.arange(ny1), np.arange(nz1), indexing="ij")
    nodes = grid.node_index(i, j, k)
    fixed = table_dofs(grid)
    fixed[3 * nodes[0].ravel()] = True  # symmetry plane through the face's centre, x = 0
    fixed[3 * nodes[:, 0].ravel() + 1] = True  # the phantom's mid-line, y = 0
    top = nodes[:, :, -1].ravel()  # top nodes, x-major
    top_x = np.repeat(x, ny1)
    initially_under = top_x <= half_face + 1e-12
    under = 3 * top[initially_under] + 2
    u = np.zeros(block.n_dofs)
    _, k0 = block.forces_and_tangent(u)
    # Linear model: the same mesh and the small-strain tangent (identical to the Q1/P0 stiffness).
    held = fixed.copy()
    held[under] = True
    lin_free = np.flatnonzero(~held)
    unit = np.zeros(block.n_dofs)
    unit[under] = -1.0
    u_lin = unit.copy()
    u_lin[lin_free] = spla.spsolve(k0[lin_free][:, lin_free].tocsc(), -(k0 @ unit)[lin_free])
    linear_per_m = -4.0 * float((k0 @ u_lin)[under].sum())  # quarter model: 4x the reaction
    depths = np.arange(0.0, max_indentation_m + 1e-12, step_m)
    forces = [0.0]
    compressive = True
    active = initially_under.copy()
    for n, depth in enumerate(depths[1:], start=1):
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"), warnings.catch_warnings():
            # A singular tangent or an inverted trial element means the mesh has reached its limit.
            warnings.simplefilter("error", spla.MatrixRankWarning)
            try:
                u, f, active = _contact_step(block, u, depth, active, fixed, top, top_x, initially_under,
                                             half_face, spacing_m)
            except (spla.MatrixRankWarning, _NoConvergence):
                # The elements at the face's sharp edge have sheared past what the mesh can follow
                # (the edge is a strain singularity); the curve ends at the last converged depth.
                depths = depths[:n]
                break
        reaction = -f[3 * top[active] + 2]
        compressive &= bool(reaction.min() > 0)
        forces.append(4.0 * float(reaction.sum()))
        if progress:
            progress(n / (len(depths) - 1), "solving the punch at finite strain")
    return StiffeningCurve(depths, linear_per_m * depths, np.array(forces), compressive)
