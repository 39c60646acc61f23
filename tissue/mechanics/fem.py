"""Linear-elastic finite elements of a tissue block on a rigid table, condensed onto its top surface.

The block is a structured hexahedral grid: a tensor product of node lines ``x_m`` and ``y_m`` in the
plane, and ``levels`` (0 at the table, 1 at the surface) through the depth, each node column stretched
to the surface height above it. The bottom nodes are bonded to the table (all displacements zero), the
sides and the top are free, and the only loads are vertical forces on top-surface nodes (frictionless
contact with a level punch pushes straight down).

Near-incompressibility (silicone, nu ~ 0.49-0.5) is handled by the mixed displacement-pressure
formulation with trilinear displacements and a constant pressure per element (Q1/P0, the "mean
dilatation" or B-bar element of Nagtegaal, Parks & Rice 1974 and Hughes 1980): the deviatoric energy
2 mu |dev eps|^2 is integrated exactly (2x2x2 Gauss), the volumetric part sees only the element's mean
dilatation, and because the pressure is discontinuous it is eliminated element by element, leaving a
symmetric positive definite stiffness in the displacements alone. The bulk modulus enters as
``1 / integral(1 / kappa)`` per element, so a volumetric constraint costs one equation per element
instead of one per Gauss point: no volumetric locking, however close nu is to 1/2. (Q1/P0 does not
satisfy the inf-sup condition and can show checkerboard pressure; the displacements and the nodal
forces summed over a 2 x 2 mm sensor element, which is what this model reports, are not affected.)

The expensive product is the condensed stiffness ``S`` of the top surface: vertical forces on the
retained top nodes against their vertical displacements, every other degree of freedom (including the
top nodes' horizontal ones, free because contact is frictionless) eliminated. It is computed by
nested substructuring: the grid is cut recursively into boxes of elements, each leaf's interior is
eliminated with a dense Cholesky factorisation, and sibling boxes are merged by eliminating the
interface they share. Dense BLAS-3 work on the separators makes this several times faster than a
general sparse factorisation, and no solve per retained node is needed. Boxes made of the same element
matrices, cut alike, have the same Schur complement: a block under a flat surface repeats many, and is
condensed in 60-80 % of the work; a :class:`SchurStore` carries them from one block to the next.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.linalg as sla

# Hex8 node order in reference coordinates (xi, eta, zeta).
_REF = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                 [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float)
# The same nodes as (di, dj, dk) index offsets in the grid.
_OFFS = ((_REF + 1) / 2).astype(int)

# (E, nu) at an (..., 3) array of points.
MaterialFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
Progress = Callable[[float, str], None]


def _gauss_2x2x2() -> tuple[np.ndarray, np.ndarray]:
    g = 1.0 / np.sqrt(3.0)
    pts = np.array([[a, b, c] for c in (-g, g) for b in (-g, g) for a in (-g, g)])
    return pts, np.ones(len(pts))


def graded_levels(n_layers: int, top_fraction: float) -> np.ndarray:
    """Level fractions 0..1, the top layer ``top_fraction`` thick, growing geometrically downwards."""
    if n_layers < 1:
        raise ValueError(f"n_layers must be >= 1, got {n_layers}")
    if not 0.0 < top_fraction <= 1.0 / n_layers + 1e-12:
        raise ValueError(f"top_fraction must be in (0, 1/n_layers], got {top_fraction:g} for {n_layers} layers")
    if abs(top_fraction * n_layers - 1.0) < 1e-9:
        return np.linspace(0.0, 1.0, n_layers + 1)
    # sum_{k<n} t r^k = 1 for the growth ratio r > 1: bisection on a monotone function.
    lo, hi = 1.0, 2.0
    while top_fraction * (hi**n_layers - 1) / (hi - 1) < 1.0:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if top_fraction * (mid**n_layers - 1) / (mid - 1) < 1.0:
            lo = mid
        else:
            hi = mid
    thickness = top_fraction * hi ** np.arange(n_layers)  # from the top down
    depth = np.concatenate([[0.0], np.cumsum(thickness)])
    depth /= depth[-1]
    return np.sort(1.0 - depth)


@dataclass(frozen=True)
class HexGrid:
    """A block of hexahedra: node lines in x and y, depth levels, the surface height of each column."""

    x_m: np.ndarray  # (nx+1,) increasing
    y_m: np.ndarray  # (ny+1,) increasing
    levels: np.ndarray  # (nz+1,) from 0 (table) to 1 (surface), increasing
    height_m: np.ndarray  # (nx+1, ny+1) surface height of each node column, > 0

    def __post_init__(self):
        for name in ("x_m", "y_m", "levels"):
            a = getattr(self, name)
            if a.ndim != 1 or len(a) < 2 or np.any(np.diff(a) <= 0):
                raise ValueError(f"HexGrid.{name} must be a strictly increasing 1-D array of >= 2 values")
        if self.levels[0] != 0.0 or self.levels[-1] != 1.0:
            raise ValueError("HexGrid.levels must run from 0 (table) to 1 (surface)")
        if self.height_m.shape != (len(self.x_m), len(self.y_m)) or np.any(self.height_m <= 0):
            raise ValueError("HexGrid.height_m must be positive, one value per node column")

    @property
    def shape(self) -> tuple[int, int, int]:
        """Number of elements along x, y, z."""
        return len(self.x_m) - 1, len(self.y_m) - 1, len(self.levels) - 1

    @property
    def node_shape(self) -> tuple[int, int, int]:
        nx, ny, nz = self.shape
        return nx + 1, ny + 1, nz + 1

    def node_index(self, i, j, k):
        _, ny1, nz1 = self.node_shape
        return (np.asarray(i) * ny1 + np.asarray(j)) * nz1 + np.asarray(k)

    def node_coords(self) -> np.ndarray:
        """(nx+1, ny+1, nz+1, 3) node positions."""
        gx, gy, gl = np.meshgrid(self.x_m, self.y_m, self.levels, indexing="ij")
        gz = gl * self.height_m[:, :, None]
        return np.stack([gx, gy, gz], axis=-1)

    def element_nodes(self) -> np.ndarray:
        """(nel, 8) node indices of every element, elements ordered (ex, ey, ez) C-style."""
        nx, ny, nz = self.shape
        ex, ey, ez = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
        ex, ey, ez = ex.ravel(), ey.ravel(), ez.ravel()
        return np.stack([self.node_index(ex + di, ey + dj, ez + dk) for di, dj, dk in _OFFS], axis=1)


def element_stiffness(grid: HexGrid, material: MaterialFn) -> np.ndarray:
    """(nel, 24, 24) Q1/P0 element stiffness matrices, dofs ordered (node a, component i) -> 3a + i."""
    coords = grid.node_coords().reshape(-1, 3)
    xe = coords[grid.element_nodes()]  # (nel, 8, 3)
    pts, wts = _gauss_2x2x2()
    n = (1.0 + pts[:, None, :] * _REF[None, :, :]).prod(axis=2) / 8.0  # (nq, 8) shape functions
    young, nu = material(np.einsum("qa,eai->eqi", n, xe))
    young = np.broadcast_to(young, (len(xe), len(pts)))
    nu = np.broadcast_to(nu, young.shape)
    mu = young / (2.0 * (1.0 + nu))
    kappa = young / (3.0 * (1.0 - 2.0 * nu))
    # A block meshed under a flat surface is a few element shapes repeated, one per layer: their geometry is
    # worked out once per shape (a solve of the depth model's spent a third of its time here otherwise).
    shapes, which = np.unique(np.round(xe - xe[:, :1], 12).reshape(len(xe), -1), axis=0, return_inverse=True)
    if len(shapes) * 8 > len(xe):
        grad, wdet = _element_geometry(xe, pts, wts)
        return _deviatoric(grad, wdet * mu) + _volumetric(grad, wdet, kappa)
    grad, wdet = _element_geometry(shapes.reshape(-1, 8, 3), pts, wts)
    k = np.empty((len(xe), 24, 24))
    for s in range(len(shapes)):
        members = np.flatnonzero(which.ravel() == s)
        # the deviatoric part is linear in the shear modulus at each Gauss point: one operator per point
        per_point = np.stack([_deviatoric(grad[s:s + 1], wdet[s:s + 1] * (np.arange(len(pts)) == q))[0]
                              for q in range(len(pts))]).reshape(len(pts), -1)
        k[members] = (mu[members] @ per_point).reshape(-1, 24, 24)
        k[members] += _volumetric(grad[s:s + 1], wdet[s:s + 1], kappa[members])
    return k


def _element_geometry(xe: np.ndarray, pts: np.ndarray, wts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dN_a/dx_i at each Gauss point, (n, nq, 8, 3); the points' weights times the Jacobian, (n, nq)) of the
    elements whose nodes are ``xe`` (n, 8, 3)."""
    # dN/dxi at each Gauss point: (nq, 8, 3)
    fac = 1.0 + pts[:, None, :] * _REF[None, :, :]
    dn = np.empty((len(pts), 8, 3))
    dn[..., 0] = _REF[None, :, 0] * fac[..., 1] * fac[..., 2] / 8.0
    dn[..., 1] = _REF[None, :, 1] * fac[..., 0] * fac[..., 2] / 8.0
    dn[..., 2] = _REF[None, :, 2] * fac[..., 0] * fac[..., 1] / 8.0
    jac = np.einsum("eai,qaj->eqij", xe, dn)  # dx_i/dxi_j
    det = np.linalg.det(jac)
    if np.any(det <= 0):
        raise ValueError("inverted or degenerate element in the mesh (non-positive Jacobian)")
    return np.einsum("qaj,eqji->eqai", dn, np.linalg.inv(jac)), det * wts[None, :]


def _deviatoric(grad: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(n, 24, 24): the sum over the Gauss points of ``weight`` (n, nq) times [d_ij g_a.g_b + g_aj g_bi - 2/3 g_ai
    g_bj] = 2 dev(eps(N_a e_i)) : dev(eps(N_b e_j)), the deviatoric stiffness for a weight of mu times the
    Jacobian; all three terms from one batched product m[e, (a,i), (b,j)] = sum_q weight g_ai g_bj."""
    g = grad.reshape(len(grad), grad.shape[1], 24)
    m = np.matmul((g * weight[:, :, None]).transpose(0, 2, 1), g).reshape(-1, 8, 3, 8, 3)
    k = m.transpose(0, 1, 4, 3, 2) - (2.0 / 3.0) * m
    gg = np.einsum("eakbk->eab", m)
    k += gg[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
    return k.reshape(-1, 24, 24)


def _volumetric(grad: np.ndarray, wdet: np.ndarray, kappa: np.ndarray) -> np.ndarray:
    """Mean dilatation: the element's pressure is eliminated, K_vol = b b^T / integral(1/kappa) ((n, 24, 24), or
    broadcast over ``kappa``'s elements where ``grad`` and ``wdet`` are one shape's)."""
    b = np.einsum("eq,eqai->eai", wdet, grad).reshape(-1, 24)
    inv_bulk = (wdet / kappa).sum(axis=1)
    return b[:, :, None] * b[:, None, :] / inv_bulk[:, None, None]


def element_dofs(grid: HexGrid) -> np.ndarray:
    conn = grid.element_nodes()
    return (3 * conn[:, :, None] + np.arange(3)).reshape(-1, 24)


class SchurStore:
    """Boxes' Schur complements kept from one condensation for the next, up to ``budget_bytes``, the ones
    made or asked for last kept first. Blocks alike but for an inclusion share every box the inclusion is
    not in (a flat block 40 x 30 x 25 mm with a sphere 5-12 mm wide: about 45 % of its work), and the
    largest boxes, made last, are the ones worth most."""

    def __init__(self, budget_bytes: int = 256 * 2**20):
        self.budget_bytes = budget_bytes
        self._kept: OrderedDict[bytes, np.ndarray] = OrderedDict()
        self._bytes = 0

    @property
    def held_bytes(self) -> int:
        return self._bytes

    def get(self, key: bytes) -> np.ndarray | None:
        s = self._kept.get(key)
        if s is not None:
            self._kept.move_to_end(key)
        return s

    def put(self, key: bytes, s: np.ndarray) -> None:
        if key in self._kept or s.nbytes > self.budget_bytes:
            return
        self._kept[key] = s
        self._bytes += s.nbytes
        while self._bytes > self.budget_bytes:
            self._bytes -= self._kept.popitem(last=False)[1].nbytes


@dataclass
class _Box:
    lo: tuple[int, int, int]  # element index ranges [lo, hi)
    hi: tuple[int, int, int]
    children: tuple["_Box", "_Box"] | None = None
    keep: np.ndarray | None = None  # global dofs left after this box is condensed
    order: np.ndarray | None = None  # the box's free dofs, those it eliminates first, then ``keep``
    cost: float = 0.0
    # What the box's Schur complement is made of, relative to its corner: boxes with the same key have the
    # same one to the bit (the same elements' matrices, the same dofs eliminated and kept, in the same order).
    key: bytes = b""


class _Substructurer:
    """Nested dissection of the element grid with dense Schur complements (see the module docstring)."""

    def __init__(self, grid: HexGrid, ke: np.ndarray, retained_dofs: np.ndarray, fixed: np.ndarray,
                 leaf_dofs: int = 900):
        self.grid = grid
        self.ke = ke
        self.edofs = element_dofs(grid)
        self.retained = np.zeros(3 * np.prod(grid.node_shape), dtype=bool)
        self.retained[retained_dofs] = True
        self.fixed = fixed
        if np.any(fixed[retained_dofs]):
            raise ValueError("a retained degree of freedom is also fixed")
        self.leaf_dofs = leaf_dofs
        nx, ny, nz = grid.shape
        self.root = self._build((0, 0, 0), (nx, ny, nz))

    def _box_dofs(self, lo, hi) -> np.ndarray:
        """The box's free (not fixed) dofs, sorted."""
        i, j, k = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1),
                              np.arange(lo[2], hi[2] + 1), indexing="ij")
        nodes = self.grid.node_index(i, j, k).ravel()
        dofs = np.sort((3 * nodes[:, None] + np.arange(3)).ravel())
        return dofs[~self.fixed[dofs]]

    def _boundary(self, lo, hi) -> np.ndarray:
        """Free dofs of the box shared with elements outside it, or retained."""
        nx, ny, nz = self.grid.shape
        dofs = self._box_dofs(lo, hi)
        node = dofs // 3
        _, ny1, nz1 = self.grid.node_shape
        i, rem = np.divmod(node, ny1 * nz1)
        j, k = np.divmod(rem, nz1)
        shared = np.zeros(len(dofs), dtype=bool)
        for axis, idx, n in ((0, i, nx), (1, j, ny), (2, k, nz)):
            if lo[axis] > 0:
                shared |= idx == lo[axis]
            if hi[axis] < n:
                shared |= idx == hi[axis]
        return dofs[shared | self.retained[dofs]]

    def _build(self, lo, hi) -> _Box:
        box = _Box(lo, hi)
        box.keep = self._boundary(lo, hi)
        sizes = [h - low for low, h in zip(lo, hi)]
        nodes = np.prod([s + 1 for s in sizes])
        if 3 * nodes > self.leaf_dofs:
            # Cut across the axis whose separator (a plane of nodes) is smallest.
            best = None
            for axis in range(3):
                if sizes[axis] >= 2:
                    sep = np.prod([s + 1 for a, s in enumerate(sizes) if a != axis])
                    if best is None or sep < best[0]:
                        best = (sep, axis)
            if best is not None:
                axis = best[1]
                mid = lo[axis] + sizes[axis] // 2
                hi1 = tuple(mid if a == axis else h for a, h in enumerate(hi))
                lo2 = tuple(mid if a == axis else low for a, low in enumerate(lo))
                box.children = (self._build(lo, hi1), self._build(lo2, hi))
        key = hashlib.blake2b(repr(sizes).encode(), digest_size=20)
        if box.children is None:
            dofs = self._box_dofs(lo, hi)
            key.update(np.ascontiguousarray(self.ke[self._leaf_elements(box)]))
        else:
            dofs = np.union1d(box.children[0].keep, box.children[1].keep)
            for child in box.children:
                key.update(child.key)
                key.update(self._local(child.keep, lo))
        kept = np.isin(dofs, box.keep, assume_unique=True)
        box.order = np.concatenate([dofs[~kept], dofs[kept]])
        key.update(self._local(box.order, lo))
        key.update(np.int64(len(box.keep)).tobytes())
        box.key = key.digest()
        n_elim = len(dofs) - len(box.keep)
        box.cost = n_elim**3 / 3.0 + n_elim**2 * len(box.keep) + n_elim * len(box.keep) ** 2
        return box

    def _local(self, dofs: np.ndarray, lo) -> np.ndarray:
        """(node i, j, k from the corner ``lo``, component) of each of ``dofs``."""
        _, ny1, nz1 = self.grid.node_shape
        i, rem = np.divmod(dofs // 3, ny1 * nz1)
        j, k = np.divmod(rem, nz1)
        return np.stack([i - lo[0], j - lo[1], k - lo[2], dofs % 3])

    def _walk(self, box: _Box, seen: dict[bytes, int], have: dict[bytes, np.ndarray]) -> float:
        """The cost of condensing ``box``, counting in ``seen`` how often each key is asked for: a box whose
        key was condensed before, or is in ``have``, is not condensed again, nor are its children visited."""
        seen[box.key] = seen.get(box.key, 0) + 1
        if seen[box.key] > 1 or box.key in have:
            return 0.0
        return box.cost + (sum(self._walk(c, seen, have) for c in box.children) if box.children else 0.0)

    def _keys(self, box: _Box):
        yield box.key
        for child in box.children or ():
            yield from self._keys(child)

    def run(self, progress: Progress | None, store: SchurStore | None = None) -> tuple[np.ndarray, np.ndarray]:
        # A block under a flat surface repeats the same boxes many times over (a library's block with one
        # sphere: all but the sphere's), and so do their unions: each is condensed once, and kept for as long
        # as another box with its key is still to come. ``store``'s boxes are taken as they are, and held here
        # for the run whatever the store lets go of meanwhile.
        kept: dict[bytes, np.ndarray] = {}
        if store is not None:
            kept = {key: s for key in set(self._keys(self.root)) if (s := store.get(key)) is not None}
        asked: dict[bytes, int] = {}
        total = max(self._walk(self.root, asked, kept), 1e-300)
        done = [0.0]

        def visit(box: _Box) -> np.ndarray:
            asked[box.key] -= 1
            if box.key in kept:
                return kept.pop(box.key) if asked[box.key] == 0 else kept[box.key]
            n, n_elim = len(box.order), len(box.order) - len(box.keep)
            mat = np.zeros((n, n))
            flat = mat.reshape(-1)
            dofs, rank = np.sort(box.order), np.argsort(box.order)  # where each of dofs is in the order
            if box.children is None:
                elems = self._leaf_elements(box)
                pos = rank[np.minimum(np.searchsorted(dofs, self.edofs[elems]), n - 1)]
                live = ~self.fixed[self.edofs[elems]]
                rows = np.broadcast_to(pos[:, :, None], (len(elems), 24, 24))
                cols = np.broadcast_to(pos[:, None, :], (len(elems), 24, 24))
                both = live[:, :, None] & live[:, None, :]
                flat += np.bincount(rows[both] * n + cols[both], weights=self.ke[elems][both], minlength=n * n)
            else:
                for child in box.children:
                    sub = visit(child)
                    pos = rank[np.searchsorted(dofs, child.keep)]
                    flat[(pos[:, None] * n + pos[None, :]).reshape(-1)] += sub.reshape(-1)
                    del sub
            s = _schur(mat, n_elim)
            if asked[box.key] > 0:
                kept[box.key] = s
            if store is not None:
                store.put(box.key, s)
            done[0] += box.cost
            if progress is not None:
                progress(done[0] / total, "condensing the tissue onto its surface")
            return s

        return self.root.keep, visit(self.root)

    def _leaf_elements(self, box: _Box) -> np.ndarray:
        """The leaf's element indices, (ex, ey, ez) C-style."""
        _, ny, nz = self.grid.shape
        ex, ey, ez = np.meshgrid(np.arange(box.lo[0], box.hi[0]), np.arange(box.lo[1], box.hi[1]),
                                 np.arange(box.lo[2], box.hi[2]), indexing="ij")
        return ((ex * ny + ey) * nz + ez).ravel()


def _schur(mat: np.ndarray, n_elim: int) -> np.ndarray:
    """S = A_kk - A_ke A_ee^-1 A_ek of a symmetric positive definite A ordered [eliminated, kept]."""
    if n_elim == 0:
        return mat
    # scipy's BLAS throughout: numpy ships its own OpenBLAS, and alternating the two makes their idle
    # spinning threads fight over the cores.
    chol, info = sla.lapack.dpotrf(np.asfortranarray(mat[:n_elim, :n_elim]), lower=1, overwrite_a=1, clean=1)
    if info != 0:
        raise np.linalg.LinAlgError("the stiffness matrix is not positive definite (is the block anchored?)")
    x = sla.solve_triangular(chol, mat[:n_elim, n_elim:], lower=True, check_finite=False)
    upper = sla.blas.dsyrk(1.0, np.asfortranarray(x), trans=1, lower=0)
    # dsyrk fills the upper triangle and leaves zeros below it.
    s = np.ascontiguousarray(mat[n_elim:, n_elim:])
    s -= upper.T
    s -= upper
    s[np.diag_indices_from(s)] += np.diagonal(upper)
    return s


def top_dofs(grid: HexGrid, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertical dofs of the top nodes (optionally only where ``mask`` (nx+1, ny+1) is True), and their
    (i, j) column indices, ordered i-major."""
    nx1, ny1, nz1 = grid.node_shape
    i, j = np.meshgrid(np.arange(nx1), np.arange(ny1), indexing="ij")
    sel = np.ones((nx1, ny1), dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    i, j = i[sel], j[sel]
    return 3 * grid.node_index(i, j, nz1 - 1) + 2, np.stack([i, j], axis=1)


def table_dofs(grid: HexGrid) -> np.ndarray:
    """Boolean mask of the dofs fixed by bonding the bottom nodes to the table."""
    fixed = np.zeros(3 * int(np.prod(grid.node_shape)), dtype=bool)
    nx1, ny1, _ = grid.node_shape
    i, j = np.meshgrid(np.arange(nx1), np.arange(ny1), indexing="ij")
    bottom = grid.node_index(i, j, 0).ravel()
    fixed[(3 * bottom[:, None] + np.arange(3)).ravel()] = True
    return fixed


def wall_dofs(grid: HexGrid) -> np.ndarray:
    """Boolean mask of the dofs fixed by frictionless walls at the block's four lateral faces (a phantom
    left in its casting tray): no displacement through a wall, free sliding along it."""
    fixed = np.zeros(3 * int(np.prod(grid.node_shape)), dtype=bool)
    nx1, ny1, nz1 = grid.node_shape
    j, k = np.meshgrid(np.arange(ny1), np.arange(nz1), indexing="ij")
    for i in (0, nx1 - 1):
        fixed[3 * grid.node_index(i, j, k).ravel()] = True
    i, k = np.meshgrid(np.arange(nx1), np.arange(nz1), indexing="ij")
    for j in (0, ny1 - 1):
        fixed[3 * grid.node_index(i, j, k).ravel() + 1] = True
    return fixed


def condensed_surface_stiffness(grid: HexGrid, material: MaterialFn, mask: np.ndarray | None = None,
                                progress: Progress | None = None, fixed: np.ndarray | None = None,
                                leaf_dofs: int = 900, store: SchurStore | None = None
                                ) -> tuple[np.ndarray, np.ndarray]:
    """Condensed vertical stiffness of the top nodes selected by ``mask``.

    Returns ``(ij, S)``: the (n, 2) column indices of the retained top nodes and the (n, n) symmetric
    positive definite matrix with ``f = S w`` (upward nodal forces against upward displacements) when
    all other top nodes are free of load. ``fixed`` (a mask over all dofs, 3 per node) defaults to the
    bottom nodes bonded to the table; symmetry planes can be added to it. ``leaf_dofs`` is the size
    below which a box is condensed directly rather than cut in two (a speed knob only); ``store`` keeps
    boxes from one call for the next (the same result to the bit, sooner).
    """
    ke = element_stiffness(grid, material)
    dofs, ij = top_dofs(grid, mask)
    fixed = table_dofs(grid) if fixed is None else fixed
    kept, s = _Substructurer(grid, ke, dofs, fixed, leaf_dofs).run(progress, store)
    order = np.searchsorted(kept, dofs)
    if len(kept) != len(dofs) or np.any(kept[order] != dofs):
        raise AssertionError("substructuring lost a retained degree of freedom")
    return ij, s[np.ix_(order, order)]


def assemble_sparse(grid: HexGrid, material: MaterialFn):
    """The full stiffness as a scipy CSR matrix (all dofs, no boundary conditions); for checks."""
    import scipy.sparse as sp

    ke = element_stiffness(grid, material)
    ed = element_dofs(grid)
    n = 3 * int(np.prod(grid.node_shape))
    rows = np.broadcast_to(ed[:, :, None], ke.shape).ravel()
    cols = np.broadcast_to(ed[:, None, :], ke.shape).ravel()
    return sp.csr_matrix((ke.ravel(), (rows, cols)), shape=(n, n))
