"""Finite elements of the tissue block: element correctness, and the condensation against a direct solve."""

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from tissue.mechanics.fem import (
    HexGrid,
    assemble_sparse,
    condensed_surface_stiffness,
    element_stiffness,
    graded_levels,
    table_dofs,
    top_dofs,
)


def homogeneous(young=20e3, nu=0.49):
    return lambda p: (np.full(p.shape[:-1], young), np.full(p.shape[:-1], nu))


def wavy_grid(nx=5, ny=4, nz=3):
    """A small block whose surface is far from flat, so every element is distorted."""
    x = np.linspace(0, nx * 1e-3, nx + 1)
    x[1:-1] += 0.25e-3 * np.sin(3.0 * np.arange(1, nx))
    y = np.linspace(0, ny * 1e-3, ny + 1)
    gx, gy = np.meshgrid(x, y, indexing="ij")
    height = 3e-3 + 0.8e-3 * np.sin(900 * gx) * np.cos(700 * gy)
    return HexGrid(x, y, graded_levels(nz, 0.2), height)


def test_graded_levels_start_thin_at_the_surface_and_fill_the_depth():
    lv = graded_levels(8, 0.04)
    assert lv[0] == 0.0 and lv[-1] == 1.0 and np.all(np.diff(lv) > 0)
    assert lv[-1] - lv[-2] == pytest.approx(0.04)
    assert np.all(np.diff(np.diff(lv)) < 0)  # layers thin out towards the surface
    assert np.allclose(graded_levels(4, 0.25), np.linspace(0, 1, 5))
    with pytest.raises(ValueError, match="top_fraction"):
        graded_levels(4, 0.3)


def test_element_stiffness_is_symmetric_and_blind_to_rigid_motion():
    grid = wavy_grid()
    ke = element_stiffness(grid, homogeneous())
    assert np.allclose(ke, ke.transpose(0, 2, 1), rtol=0, atol=1e-9 * np.abs(ke).max())
    k = assemble_sparse(grid, homogeneous())
    p = grid.node_coords().reshape(-1, 3)
    modes = []
    for axis in range(3):
        t = np.zeros_like(p)
        t[:, axis] = 1.0
        modes.append(t)
    for a, b in ((0, 1), (1, 2), (2, 0)):  # small rotations: u_a = -x_b, u_b = x_a
        r = np.zeros_like(p)
        r[:, a], r[:, b] = -p[:, b], p[:, a]
        modes.append(r)
    scale = abs(k).max() * 1e-3
    for mode in modes:
        assert np.abs(k @ mode.ravel()).max() < 1e-9 * scale


def test_a_block_of_repeated_element_shapes_is_worked_out_per_shape_as_element_by_element(monkeypatch):
    # a flat block (one shape per layer) with a stiff sphere cutting through elements, so that the material
    # differs between an element's Gauss points; the same block with every node line moved by a hair has no
    # two elements alike, and is worked out element by element
    from tissue.mechanics import fem

    def sphere(p):
        inside = np.sum((p - np.array([3e-3, 2e-3, 2e-3])) ** 2, axis=-1) <= (1.3e-3) ** 2
        return np.where(inside, 160e3, 20e3), np.full(p.shape[:-1], 0.49)

    x, y = np.linspace(0, 6e-3, 7), np.linspace(0, 4e-3, 5)
    flat = HexGrid(x, y, graded_levels(4, 0.1), np.full((7, 5), 4e-3))
    rng = np.random.default_rng(3)
    hair = HexGrid(x + 1e-10 * rng.random(7), y + 1e-10 * rng.random(5), graded_levels(4, 0.1), np.full((7, 5), 4e-3))
    worked_out = []
    geometry = fem._element_geometry
    monkeypatch.setattr(fem, "_element_geometry", lambda xe, *a: worked_out.append(len(xe)) or geometry(xe, *a))
    per_shape, per_element = element_stiffness(flat, sphere), element_stiffness(hair, sphere)
    assert worked_out == [4, 6 * 4 * 4]
    np.testing.assert_allclose(per_shape, per_element, rtol=0, atol=1e-6 * np.abs(per_element).max())
    assert np.ptp(per_element[:, 0, 0]) > 1.0 * per_element[:, 0, 0].min()  # the sphere is in it


def test_a_uniform_strain_leaves_interior_nodes_in_equilibrium_on_a_distorted_mesh():
    # The patch test: any linear displacement field is reproduced exactly, with zero residual
    # at nodes that are not on the block's boundary, however distorted the elements.
    grid = wavy_grid()
    k = assemble_sparse(grid, homogeneous(nu=0.4999))
    p = grid.node_coords().reshape(-1, 3)
    grad = np.array([[1.0, 0.3, -0.2], [0.1, -0.5, 0.4], [0.2, 0.0, -0.7]]) * 1e-2
    residual = (k @ (p @ grad.T).ravel()).reshape(-1, 3)
    nx1, ny1, nz1 = grid.node_shape
    i, j, kk = np.meshgrid(range(nx1), range(ny1), range(nz1), indexing="ij")
    interior = ((i > 0) & (i < nx1 - 1) & (j > 0) & (j < ny1 - 1) & (kk > 0) & (kk < nz1 - 1)).ravel()
    boundary_force = np.abs(residual[~interior]).max()
    assert np.abs(residual[interior]).max() < 1e-9 * boundary_force


def test_substructured_condensation_equals_the_direct_schur_complement():
    grid = wavy_grid(7, 6, 4)

    def material(p):  # a stiff inclusion, and a different Poisson ratio inside it
        inside = np.sum((p - [3e-3, 2e-3, 1.5e-3]) ** 2, axis=-1) < (1.2e-3) ** 2
        return np.where(inside, 160e3, 20e3), np.where(inside, 0.45, 0.49)

    mask = np.zeros(grid.node_shape[:2], dtype=bool)
    mask[1:6, 2:5] = True
    # Leaves this small force several levels of merging even on a small block.
    ij, s = condensed_surface_stiffness(grid, material, mask=mask, leaf_dofs=60)
    # Direct: solve K u = e_i with the table fixed, read the retained vertical displacements.
    k = assemble_sparse(grid, material).tocsc()
    free = np.flatnonzero(~table_dofs(grid))
    kff = k[free][:, free].tocsc()
    dofs, ij_direct = top_dofs(grid, mask)
    assert np.array_equal(ij, ij_direct)
    pos = np.searchsorted(free, dofs)
    rhs = np.zeros((len(free), len(dofs)))
    rhs[pos, np.arange(len(dofs))] = 1.0
    compliance = spla.splu(kff).solve(rhs)[pos]
    assert np.allclose(np.linalg.inv(s), compliance, rtol=1e-8, atol=1e-10 * np.abs(compliance).max())
    assert np.allclose(s, s.T)


def test_a_bad_grid_is_refused_with_a_reason():
    x = np.linspace(0, 1e-3, 3)
    with pytest.raises(ValueError, match="height_m"):
        HexGrid(x, x, np.linspace(0, 1, 3), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="x_m"):
        HexGrid(x[::-1], x, np.linspace(0, 1, 3), np.ones((3, 3)))
    with pytest.raises(ValueError, match="levels"):
        HexGrid(x, x, np.linspace(0.1, 1, 3), np.ones((3, 3)))


def test_boxes_alike_are_condensed_once_and_a_store_carries_them_to_the_next_block(monkeypatch):
    # a flat block repeats its boxes (and a block with a sphere all those the sphere is not in): each is
    # condensed once, to the same result to the bit as condensing every box, which the direct solve checks
    from tissue.mechanics import fem

    x, y = np.linspace(0, 12e-3, 13), np.linspace(0, 6e-3, 7)
    grid = HexGrid(x, y, graded_levels(3, 0.25), np.full((13, 7), 3e-3))

    def sphere(p):
        inside = np.sum((p - [9.5e-3, 3e-3, 1.5e-3]) ** 2, axis=-1) < (1.2e-3) ** 2
        return np.where(inside, 160e3, 20e3), np.full(p.shape[:-1], 0.49)

    condensed = []
    schur = fem._schur
    monkeypatch.setattr(fem, "_schur", lambda mat, n: condensed.append(len(mat)) or schur(mat, n))
    boxes = []
    build = fem._Substructurer._build
    monkeypatch.setattr(fem._Substructurer, "_build", lambda self, lo, hi: boxes.append(lo) or build(self, lo, hi))

    _, alone = condensed_surface_stiffness(grid, sphere, leaf_dofs=60)
    n_boxes = len(boxes)
    assert len(condensed) < 0.8 * n_boxes
    k = assemble_sparse(grid, sphere).tocsc()
    free = np.flatnonzero(~table_dofs(grid))
    dofs, _ = top_dofs(grid)
    pos = np.searchsorted(free, dofs)
    rhs = np.zeros((len(free), len(dofs)))
    rhs[pos, np.arange(len(dofs))] = 1.0
    compliance = spla.splu(k[free][:, free].tocsc()).solve(rhs)[pos]
    assert np.allclose(np.linalg.inv(alone), compliance, rtol=1e-8, atol=1e-10 * np.abs(compliance).max())

    store = fem.SchurStore()
    condensed_surface_stiffness(grid, homogeneous(), leaf_dofs=60, store=store)
    condensed.clear()
    _, after = condensed_surface_stiffness(grid, sphere, leaf_dofs=60, store=store)
    assert np.array_equal(after, alone)
    assert 0 < len(condensed) < 0.5 * n_boxes  # the boxes the sphere is not in came from the store

    small = fem.SchurStore(budget_bytes=8 * 30**2)  # too small for most boxes: it keeps what fits, no more
    condensed_surface_stiffness(grid, homogeneous(), leaf_dofs=60, store=small)
    assert 0 < small.held_bytes <= small.budget_bytes
    assert np.array_equal(condensed_surface_stiffness(grid, sphere, leaf_dofs=60, store=small)[1], alone)
