"""The FE model against analytic elasticity: a rigid rectangular punch on a layer bonded to a rigid base.

Reference: the exact Fourier-domain surface kernel of a bonded elastic layer (Vorovich, Aleksandrov &
Babeshko 1974; Argatov & Mishuris 2015) with the punch's integral equation solved by boundary elements,
see tissue/mechanics/reference.py. The configuration is the paper's: the TSI's 8 x 30 mm face on a
25 mm layer of nearly incompressible silicone.
"""

import numpy as np
import pytest

from tissue.mechanics.reference import layer_kernel, layer_kernel_ode, pais_kausel_stiffness, rect_punch_stiffness
from tissue.mechanics.validation import layer_punch_fe_stiffness

E, H, SIZE = 20e3, 0.025, (0.008, 0.030)


@pytest.mark.parametrize("nu", [0.3, 0.49, 0.4999])
def test_the_closed_form_layer_kernel_solves_navier_equations(nu):
    for t in (0.02, 0.3, 1.0, 2.5):  # beyond, shooting across the layer loses digits
        assert layer_kernel(t, nu) == pytest.approx(layer_kernel_ode(t, nu), rel=1e-7)
    assert layer_kernel(40.0, nu) == pytest.approx(1.0, abs=1e-12)  # thick layer: the half-space
    assert layer_kernel(1e-3, nu) < 1e-2  # thin bonded layer: very stiff


def test_the_boundary_element_reference_reproduces_the_half_space_formula():
    # Pais & Kausel's fit is accurate to a few percent for rigid rectangles on a half-space.
    bem = rect_punch_stiffness(*SIZE, E, 0.49, thickness_m=None, panels=12)
    assert bem == pytest.approx(pais_kausel_stiffness(*SIZE, E, 0.49), rel=0.04)


@pytest.fixture(scope="module")
def reference_049():
    return rect_punch_stiffness(*SIZE, E, 0.49, H, panels=12)


def test_the_bonded_layer_is_much_stiffer_than_a_half_space_and_than_winkler_springs(reference_049):
    half_space = rect_punch_stiffness(*SIZE, E, 0.49, thickness_m=None, panels=12)
    winkler = E * SIZE[0] * SIZE[1] / H  # F = E A d / h, the local-spring model of the same layer
    assert 1.3 < reference_049 / half_space < 2.0
    assert reference_049 / winkler > 3.5


def test_fe_punch_stiffness_matches_the_analytic_layer_within_10_percent(reference_049):
    fe = layer_punch_fe_stiffness(*SIZE, E, 0.49, H, spacing_m=1e-3, layers=11, top_layer_m=1e-3)
    assert fe.all_compressive  # full contact is the consistent state for a flat punch
    assert fe.stiffness_N_m == pytest.approx(reference_049, rel=0.10)


def test_near_incompressibility_does_not_lock():
    # nu -> 1/2 multiplies the bulk modulus by 500 between these two; a locking element would follow
    # it, the continuum barely changes (the layer is confined but can still shear).
    ref = rect_punch_stiffness(*SIZE, E, 0.4999, H, panels=12)
    fe = layer_punch_fe_stiffness(*SIZE, E, 0.4999, H, spacing_m=2e-3, layers=6, top_layer_m=2e-3)
    assert fe.stiffness_N_m == pytest.approx(ref, rel=0.10)
    soft = layer_punch_fe_stiffness(*SIZE, E, 0.49, H, spacing_m=2e-3, layers=6, top_layer_m=2e-3)
    assert fe.stiffness_N_m / soft.stiffness_N_m == pytest.approx(ref / rect_punch_stiffness(*SIZE, E, 0.49, H, 12),
                                                                  rel=0.01)


def test_refining_the_mesh_converges_on_the_analytic_stiffness(reference_049):
    errors = []
    for spacing, layers, top in ((2e-3, 6, 2e-3), (1e-3, 11, 1e-3), (0.5e-3, 16, 0.5e-3)):
        fe = layer_punch_fe_stiffness(*SIZE, E, 0.49, H, spacing_m=spacing, layers=layers, top_layer_m=top)
        errors.append(fe.stiffness_N_m / reference_049 - 1.0)
    # A displacement model is too stiff, never too soft, and the 1 -> 0.5 mm step halves the error.
    assert all(e > -0.01 for e in errors)
    assert abs(errors[2]) < 0.6 * abs(errors[1])
    assert abs(errors[2]) < 0.03
    richardson = 2 * (1 + errors[2]) - (1 + errors[1]) - 1.0
    assert abs(richardson) < 0.015
    assert np.all(np.isfinite(errors))
