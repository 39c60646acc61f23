"""Phantoms nobody designed for: the same seed draws the same valid phantoms, of every kind of surface."""

import numpy as np

from tissue.generator import (
    SURFACES,
    RealisticConditions,
    StudyDistribution,
    draw_conditions,
    draw_phantom,
    surface_kind,
)
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


def test_conditions_drawn_for_a_phantom_stay_in_their_ranges_and_leave_its_kind_and_tumours():
    """issue 48: what the realistic world changes about a phantom, drawn from stated ranges."""
    dist = RealisticConditions()
    rng = np.random.default_rng(4)
    drawn = [draw_phantom(rng, f"r{k}") for k in range(30)]
    sides = set()
    for k, data in enumerate(drawn):
        changed, conditions = draw_conditions(np.random.default_rng(k), data)
        assert changed == draw_conditions(np.random.default_rng(k), data)[0]
        phantom = parse_phantom(changed, "changed")  # still valid
        assert surface_kind(changed) == surface_kind(data)
        assert changed["phantom"]["inclusions"] == data["phantom"]["inclusions"]
        assert dist.c2_over_c1[0] <= phantom.material.c2_over_c1 <= dist.c2_over_c1[1]
        assert dist.relief_rms_m[0] <= conditions["relief_rms_m"] <= dist.relief_rms_m[1]
        assert all(dist.tilt_deg[0] <= a <= dist.tilt_deg[1] for a in conditions["probe_tilt_deg"])
        assert dist.cover_spread_m[0] <= conditions["cover_spread_m"] <= dist.cover_spread_m[1]
        assert dist.face_friction[0] <= phantom.face_friction == conditions["face_friction"] <= dist.face_friction[1]
        sides.add(phantom.sides)
        paper, paper_conditions = draw_conditions(np.random.default_rng(1), data, paper=True)
        assert paper["phantom"]["sides"] == paper_conditions["sides"] == "free"
    assert sides == {"free", "mould"}
