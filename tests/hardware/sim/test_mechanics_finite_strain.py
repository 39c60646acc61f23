"""Finite strain: the neo-Hookean element, the stiffening it predicts, and the model's correction."""

import numpy as np

from hardware.sim.mechanics.fem import HexGrid, assemble_sparse, graded_levels
from hardware.sim.mechanics.finite_strain import NeoHookeanBlock, punch_on_block
from hardware.sim.mechanics.model import ContinuumTissue, MeshSettings
from hardware.sim.phantom import parse_phantom


def block(nu=0.49):
    x = np.linspace(0, 3e-3, 4)
    height = np.full((4, 3), 2e-3) + np.linspace(0, 0.5e-3, 4)[:, None]  # a sloping top: distorted elements
    return NeoHookeanBlock(HexGrid(x, x[:3], graded_levels(3, 0.2), height), 20e3, nu)


def test_at_rest_the_finite_strain_element_is_the_linear_element():
    b = block()
    f, k = b.forces_and_tangent(np.zeros(b.n_dofs))
    linear = assemble_sparse(b.grid, lambda p: (np.full(p.shape[:-1], 20e3), np.full(p.shape[:-1], 0.49)))
    assert not f.any()
    assert abs(k - linear).max() < 1e-12 * abs(linear).max()


def test_the_complex_step_tangent_is_the_derivative_of_the_forces():
    b = block()
    rng = np.random.default_rng(1)
    u = 4e-5 * rng.standard_normal(b.n_dofs)  # strains of several percent, every element differently
    _, k = b.forces_and_tangent(u)
    v = rng.standard_normal(b.n_dofs)
    h = 1e-9
    forward, _ = b.forces_and_tangent(u + h * v)
    backward, _ = b.forces_and_tangent(u - h * v)
    assert np.allclose(k @ v, (forward - backward) / (2 * h), rtol=1e-5, atol=1e-6 * np.abs(k @ v).max())
    assert abs(k - k.T).max() < 1e-9 * abs(k).max()  # the forces derive from an energy


def test_a_punch_stiffens_as_it_compresses_the_layer():
    curve = punch_on_block(0.024, 0.030, 0.010, 20e3, 0.49, max_indentation_m=3e-3, step_m=0.5e-3,
                           spacing_m=2e-3, layers=5)
    assert curve.all_compressive
    ratio = curve.ratio()
    assert len(ratio) == 7 and ratio[0] == 1.0
    assert 1.0 < ratio[1] < 1.06  # 5 % strain: close to linear
    assert np.all(np.diff(ratio) > 0) and ratio[-1] > 1.3  # 30 %: much stiffer


def test_the_model_scales_element_forces_by_the_stiffening_of_their_own_strain(tmp_path):
    phantom = parse_phantom({"phantom": {"name": "s", "length_m": 0.024, "width_m": 0.030, "thickness_m": 0.010,
                                         "youngs_modulus_pa": 20e3, "poisson_ratio": 0.49}})
    mesh = MeshSettings(spacing_m=1e-3, layers=4, top_layer_m=1e-3, drift_y_m=0.0)
    linear = ContinuumTissue.load(phantom, tmp_path, settings=mesh)
    stiff = ContinuumTissue.load(phantom, tmp_path, settings=MeshSettings(**{**mesh.__dict__, "finite_strain": True}))
    assert linear.stiffening is None and stiff.stiffening is not None
    assert len(list(tmp_path.glob("tissue-*.bin"))) == 2  # the tables are shared, the stiffening is its own entry
    a, b = stiff.stiffening
    for depth in (0.5e-3, 2e-3, 3.5e-3):
        s = depth / 0.010
        z = 0.010 - depth
        ratio = stiff.element_forces_N(0.012, 0.015, z) / linear.element_forces_N(0.012, 0.015, z)
        assert np.allclose(ratio, 1 + a * s + b * s * s)
    assert 1.0 + a * 0.3 + b * 0.09 > 1.08
    assert not stiff.element_forces_N(0.012, 0.015, 0.0101).any()
