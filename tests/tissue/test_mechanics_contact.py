"""Unilateral contact of a level rigid face: the exact path against an independent solver."""

import numpy as np
import pytest
import scipy.linalg as sla
from scipy.optimize import nnls

from tissue.mechanics.contact import contact_path, tributary_weights


def reference_forces(c, h, z):
    """The LCP as a bound-constrained least-squares problem: min 1/2 f'Cf - (h - z)'f, f >= 0."""
    r = sla.cholesky(c)
    f, _ = nnls(r, sla.solve_triangular(r, h - z, trans="T"), maxiter=50 * len(h))
    return f


def surface_like_compliance(n_side, coupling, rng):
    """A compliance like a surface's: positive, decaying with distance, symmetric positive definite."""
    g = np.stack(np.meshgrid(np.arange(n_side), np.arange(n_side), indexing="ij"), -1).reshape(-1, 2)
    dist = np.linalg.norm(g[:, None] - g[None], axis=-1)
    c = coupling / (1.0 + dist) + np.eye(len(g)) * (1.0 + 0.1 * rng.random(len(g)))
    return c * 1e-3


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_path_is_the_exact_lcp_solution_at_every_depth(seed):
    rng = np.random.default_rng(seed)
    c = surface_like_compliance(7, 0.8, rng)
    x = rng.random(c.shape[0])
    h = 1e-3 * (np.sin(7 * x) + 0.5 * x)  # an uneven surface: nodes touch down one by one
    path = contact_path(c, h)
    assert len(path.t) > 10 and np.all(np.diff(path.t) >= 0)
    for z in np.linspace(h.max() + 1e-4, h.min() - 2e-3, 25):
        expected = reference_forces(c, h, z)
        assert np.allclose(path.forces(z), expected, rtol=1e-9, atol=1e-12 * max(1.0, expected.max()))


def test_a_node_that_is_pushed_up_by_its_neighbours_lifts_off_again():
    # Node 1 touches first; once its strongly coupled neighbours are pressed they drag it down
    # faster than the face descends, so it unloads and leaves the face.
    c = np.array([[1.0, 0.7, 0.3], [0.7, 1.0, 0.7], [0.3, 0.7, 1.0]]) * 1e-3
    h = np.array([0.0, 0.2e-3, 0.0])
    path = contact_path(c, h)
    lifted = [k for k in range(1, len(path.t)) if path.f0[k - 1][1] > 0 and path.df[k][1] == 0]
    assert lifted, "node 1 never lifted off"
    for z in np.linspace(0.3e-3, -3e-3, 40):
        assert np.allclose(path.forces(z), reference_forces(c, h, z), atol=1e-12)


def test_a_level_face_on_a_level_surface_touches_everywhere_at_once_and_stays_linear():
    rng = np.random.default_rng(3)
    c = surface_like_compliance(6, 0.5, rng)
    h = np.full(c.shape[0], 2e-3)
    path = contact_path(c, h)
    assert len(path.t) == 1 and path.t[0] == pytest.approx(-2e-3)
    assert np.allclose(path.forces(1e-3), np.linalg.solve(c, h - 1e-3))
    assert np.allclose(path.forces(0.0), 2 * path.forces(1e-3))  # superposition holds in full contact
    assert not path.forces(2.1e-3).any()


def test_element_weights_share_each_nodes_patch_and_lose_no_force():
    # Nodes every 1 mm over a 4 x 6 mm face made of 2 x 2 mm elements, the phantom ending at y = 5 mm.
    xs, ys = np.meshgrid(np.arange(5) * 1e-3, np.arange(6) * 1e-3, indexing="ij")
    w = tributary_weights(xs.ravel(), ys.ravel(), (0.0, 0.010, 0.0, 0.005), (0.0, 0.0), 2e-3, (2, 3))
    assert w.shape == (6, 30)
    assert np.allclose(w.sum(axis=0), 1.0)
    node = lambda i, j: i * 6 + j  # noqa: E731
    assert np.isclose(w[0, node(0, 0)], 1.0)  # a corner node belongs to its corner element
    assert np.allclose(w[[0, 3], node(2, 0)], 0.5)  # a node on an element edge is shared by two
    assert np.allclose(w[[0, 1, 3, 4], node(2, 2)], 0.25)  # and at a corner by four
    # The last element column hangs over the phantom's edge: it gets only the nodes at y = 4, 5 mm.
    assert np.isclose(w[2, node(1, 5)], 1.0) and np.isclose(w[2, node(1, 4)], 0.5)
