"""The palpation study used for reports: Eq. 1 read back, onsets, unreachable levels, tumour contrast."""

import numpy as np
import pytest

from tissue.mechanics.study import height_for_force, palpate, tumour_contrast, without_inclusions
from tissue.phantom import load_phantom, parse_phantom
from tissue.winkler import WinklerTissue


def test_eq_1_gives_back_the_modulus_of_a_spring_bed_and_its_indentation():
    phantom = parse_phantom({"phantom": {"name": "w", "length_m": 0.016, "width_m": 0.030, "thickness_m": 0.025,
                                         "youngs_modulus_pa": 20e3, "poisson_ratio": 0.49}})
    (level,) = palpate(WinklerTissue(phantom), [2.0], regions=[(0.008, 0.015)])[0]
    assert level.forces_N.sum() == pytest.approx(2.0, rel=1e-6)
    assert np.allclose(level.onset_m, 0.025, atol=1e-5)
    assert np.allclose(level.stiffness_pa, 20e3, rtol=2e-3)
    assert level.tsi_indentation_m == pytest.approx(2.0 / (20e3 * 2.4e-4 / 0.025), rel=2e-3)


def test_a_level_the_tissue_cannot_reach_is_nan_not_an_error():
    phantom = load_phantom("flat")
    assert np.isnan(height_for_force(WinklerTissue(phantom), 0.036, 0.015, 6.0))  # springs top out at 4.8 N
    (level,) = palpate(WinklerTissue(phantom), [6.0], regions=[(0.036, 0.015)])[0]
    assert np.isnan(level.tsi_indentation_m) and np.isnan(level.stiffness_pa).all()


def test_contrast_is_measured_against_the_same_phantom_without_tumours():
    phantom = load_phantom("flat")
    clean = without_inclusions(phantom)
    assert not clean.inclusions and clean.surface_height_m(0.03, 0.01) == phantom.surface_height_m(0.03, 0.01)
    regions = [(0.012, 0.015)]
    study = palpate(WinklerTissue(phantom), [2.0], regions)
    reference = palpate(WinklerTissue(clean), [2.0], regions)
    relative, excess = tumour_contrast(study, reference, 0, phantom.ground_truth()[0], "stiffness_pa")
    assert relative > 0.15 and excess > 0  # a hard sphere 2 mm down stiffens the springs above it
    assert tumour_contrast(reference, reference, 0, phantom.ground_truth()[0], "forces_N") == (0.0, 0.0)
