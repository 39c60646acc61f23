"""Phantoms nobody designed for: the same seed draws the same valid phantoms, of every kind of surface."""

import numpy as np

from tissue.generator import SURFACES, StudyDistribution, draw_phantom, surface_kind
from tissue.phantom import parse_phantom


def test_the_same_seed_draws_the_same_valid_phantoms_of_every_surface():
    a = [draw_phantom(np.random.default_rng(5), f"p{k}") for k in range(2)]
    assert a == [draw_phantom(np.random.default_rng(5), f"p{k}") for k in range(2)]
    rng = np.random.default_rng(11)
    drawn = [draw_phantom(rng, f"q{k}") for k in range(20)]
    assert drawn != [draw_phantom(np.random.default_rng(12), f"q{k}") for k in range(20)]
    dist = StudyDistribution()
    for data in drawn:
        phantom = parse_phantom(data, data["phantom"]["name"])  # valid by construction
        assert dist.tumours[0] <= len(phantom.inclusions) <= dist.tumours[1]
        for inc in phantom.inclusions:
            assert inc.z_m - inc.radius_m >= dist.table_clearance_m - 1e-9
        assert surface_kind(data) in data["phantom"]["description"]
    assert {surface_kind(d) for d in drawn} == set(SURFACES)
