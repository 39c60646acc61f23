"""Winkler baseline tissue: Eq. 1 on a homogeneous column, inclusions in series, unilateral, uneven surfaces."""

import math

import numpy as np
import pytest

from hardware.interfaces import TactileConstraints
from tissue.phantom import load_phantom, parse_phantom
from tissue.winkler import WinklerTissue

A = TactileConstraints().element_area_m2
OFFSETS = TactileConstraints().element_offsets_m()


def phantom(**extra):
    table = {"name": "test", "length_m": 0.072, "width_m": 0.030, "thickness_m": 0.025,
             "youngs_modulus_pa": 20e3, "poisson_ratio": 0.49, **extra}
    return parse_phantom({"phantom": table})


def test_a_homogeneous_column_obeys_eq_1():
    tissue = WinklerTissue(phantom())
    for dL in (0.5e-3, 2e-3, 9.29e-3):
        f = tissue.element_forces_N(0.036, 0.015, 0.025 - dL)
        assert f.shape == (4, 15)
        assert np.allclose(f, 20e3 * A * dL / 0.025, rtol=1e-12)
    # Eq. 1 read back from the force gives the modulus
    f = tissue.element_forces_N(0.036, 0.015, 0.020)
    assert f[2, 7] * 0.025 / (A * 0.005) == pytest.approx(20e3, rel=1e-12)


def test_contact_is_unilateral():
    tissue = WinklerTissue(phantom())
    assert not tissue.element_forces_N(0.036, 0.015, 0.0251).any()
    assert not tissue.element_forces_N(0.036, 0.015, 0.025).any()
    assert (tissue.element_forces_N(0.036, 0.015, 0.0249) > 0).all()


def test_an_inclusion_is_a_stiffer_segment_in_series():
    flat = load_phantom("flat")  # 8 mm, 160 kPa sphere 2 mm under the surface at (12, 15) mm
    inc = flat.inclusions[0]
    tissue = WinklerTissue(flat)
    dL = 3e-3
    f = tissue.element_forces_N(inc.x_m, inc.y_m, 0.025 - dL)
    # element (1, 7) sits 1 mm from the sphere's axis: chord 2 * sqrt(4^2 - 1^2) mm
    chord = 2 * math.sqrt(4e-3**2 - 1e-3**2)
    compliance = (0.025 - chord) / 20e3 + chord / 160e3
    assert f[1, 7] == pytest.approx(A * dL / compliance, rel=1e-12)
    soft = 20e3 * A * dL / 0.025
    assert f[1, 7] > 1.3 * soft
    # elements whose columns miss the sphere feel plain tissue
    assert f[0, 0] == pytest.approx(soft, rel=1e-12)
    assert f[1, 7] > f[0, 7] > f[0, 0]  # 1 mm from the axis, then 3 mm, then clear of the sphere


def test_a_deeper_inclusion_stiffens_its_column_just_as_much():
    """A local-spring model only sees the chord, not its depth (one of the reasons it is only a baseline)."""
    flat = load_phantom("flat")
    tissue = WinklerTissue(flat)
    shallow, deep = flat.inclusions[0], flat.inclusions[2]
    f_shallow = tissue.element_forces_N(shallow.x_m, shallow.y_m, 0.022)
    f_deep = tissue.element_forces_N(deep.x_m, deep.y_m, 0.022)
    assert np.allclose(f_shallow, f_deep, rtol=1e-12)


def test_elements_over_a_lower_surface_lose_contact():
    bumpy = phantom(surface=[{"kind": "half_cylinder", "centre_y_m": 0.025, "radius_m": 0.005,
                              "x_range_m": [0.0, 0.024]}])
    tissue = WinklerTissue(bumpy)
    x, y = 0.012, 0.015  # the TSI spans y = 0..30 mm, the bump y = 20..30 mm
    f = tissue.element_forces_N(x, y, 0.027)
    ey = y + OFFSETS[0, :, 1]
    top = 0.025 + np.sqrt(np.clip(0.005**2 - (ey - 0.025) ** 2, 0.0, None))
    touching = top > 0.027
    assert touching.any() and not touching.all()
    assert (f[:, touching] > 0).all()
    assert not f[:, ~touching].any()
    # the column's own height is its L0
    j = int(np.argmax(top))
    assert f[0, j] == pytest.approx(20e3 * A * (top[j] - 0.027) / top[j], rel=1e-12)


def test_elements_off_the_phantom_touch_nothing():
    tissue = WinklerTissue(phantom())
    f = tissue.element_forces_N(0.036, 0.0, 0.020)  # half the TSI hangs over the edge at y = 0
    assert (f[:, 8:] > 0).all()
    assert not f[:, :7].any()


def test_pressing_to_the_table_stays_finite():
    tissue = WinklerTissue(phantom())
    f = tissue.element_forces_N(0.036, 0.015, 0.0)
    assert np.allclose(f, 20e3 * A)  # the whole column compressed: dL = L0
