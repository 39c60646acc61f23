"""Phantom files: the paper's two phantoms as shipped, and a clear message for every kind of bad file."""

import copy
from dataclasses import replace

import numpy as np
import pytest

from tissue.phantom import PHANTOM_DIR, Phantom, PhantomError, load_phantom, parse_phantom


def base(**extra):
    table = {"name": "t", "length_m": 0.072, "width_m": 0.030, "thickness_m": 0.025,
             "youngs_modulus_pa": 20e3, "poisson_ratio": 0.49, **extra}
    return {"phantom": table}


def sphere(**extra):
    return {"centre_xy_m": [0.036, 0.015], "diameter_m": 0.008, "youngs_modulus_pa": 160e3, **extra}


def test_the_flat_phantom_has_the_papers_three_tumours_at_2_7_and_10_mm():
    p = load_phantom("flat")
    truth = p.ground_truth()
    assert [t["x_m"] for t in truth] == pytest.approx([0.012, 0.036, 0.060])
    assert [t["y_m"] for t in truth] == pytest.approx([0.015] * 3)
    assert [t["depth_m"] for t in truth] == pytest.approx([0.002, 0.007, 0.010])
    assert all(t["diameter_m"] == 0.008 and t["youngs_modulus_pa"] == 8 * p.youngs_modulus_pa for t in truth)
    assert p.surface_height_m(0.03, 0.01) == pytest.approx(0.025)


def test_the_uneven_phantom_has_bumps_a_flat_middle_and_tumours_under_the_base_surface():
    p = load_phantom("uneven")
    h = lambda x, y: float(p.surface_height_m(x * 1e-3, y * 1e-3)) * 1e3  # noqa: E731
    assert h(12, 25) == pytest.approx(27.0)  # left part: bump over y = 20..30 mm
    assert h(12, 15) == pytest.approx(22.0) and h(12, 5) == pytest.approx(22.0)
    assert h(36, 5) == h(36, 15) == h(36, 25) == pytest.approx(22.0)  # flat middle
    assert h(60, 5) == pytest.approx(27.0) and h(60, 25) == pytest.approx(27.0)  # right part: two bumps
    assert h(60, 15) == pytest.approx(22.0)  # the gap over the third tumour
    assert h(12, 22) == pytest.approx(22.0 + (25 - 9) ** 0.5)  # a half-cylinder profile
    truth = p.ground_truth()
    assert [t["z_m"] + t["diameter_m"] / 2 for t in truth] == pytest.approx([0.020] * 3)  # tops 20 mm up
    assert [t["depth_m"] for t in truth] == pytest.approx([0.002] * 3)


def test_default_regions_are_tsi_long_strips_along_the_phantom():
    regions = load_phantom("flat").palpation_regions()
    assert [x for x, _ in regions] == pytest.approx([0.004 + 0.008 * k for k in range(9)])
    assert all(y == pytest.approx(0.015) for _, y in regions)


def test_depth_and_height_describe_the_same_sphere():
    by_depth = parse_phantom(base(inclusions=[sphere(depth_m=0.007)]))
    by_height = parse_phantom(base(inclusions=[sphere(height_m=0.025 - 0.007 - 0.004)]))
    (a,), (b,) = by_depth.ground_truth(), by_height.ground_truth()
    assert a == pytest.approx(b)


def test_the_sides_and_the_law_default_to_free_and_neo_hookean_and_can_be_chosen():
    flat = load_phantom("flat")
    assert flat.sides == "free" and flat.material.law == "neo_hookean"
    chosen = parse_phantom(base(sides="mould", material={"law": "yeoh", "c2_over_c1": -0.1, "c3_over_c1": 0.01}))
    assert chosen.sides == "mould"
    assert (chosen.material.law, chosen.material.c2_over_c1, chosen.material.c3_over_c1) == ("yeoh", -0.1, 0.01)
    assert chosen.content_hash() != parse_phantom(base()).content_hash()  # a new model, not a cached one


def test_friction_at_the_face_defaults_to_none_and_a_frictionless_phantom_keeps_its_hash():
    """issue 48: a phantom states its face's friction; without it, its cached mechanics and the hash its
    sessions recorded stay what they were (the flat phantom's, as of before friction existed)."""
    flat = load_phantom("flat")
    assert flat.face_friction == 0.0 and flat.content_hash() == "335954298b3a7c69"
    gripped = parse_phantom(base(face_friction=0.6))
    assert gripped.face_friction == 0.6
    assert gripped.content_hash() != parse_phantom(base()).content_hash() == parse_phantom(
        base(face_friction=0.0)).content_hash()


def test_the_content_hash_follows_the_content_only():
    a = parse_phantom(base(inclusions=[sphere(depth_m=0.007)]))
    b = parse_phantom(copy.deepcopy(base(inclusions=[sphere(depth_m=0.007)])))
    c = parse_phantom(base(inclusions=[sphere(depth_m=0.006)]))
    assert a.content_hash() == b.content_hash() != c.content_hash()
    assert load_phantom("flat").content_hash() == load_phantom(PHANTOM_DIR / "flat.toml").content_hash()
    # a phantom built in code (the analysis's rebuilt block) is told apart by its content too
    built = Phantom("rebuilt", "a block", 0.07, 0.03, 0.025, youngs_modulus_pa=20e3, poisson_ratio=0.49)
    assert built.content_hash() != replace(built, thickness_m=0.031).content_hash()
    assert built.content_hash() == replace(built).content_hash()


@pytest.mark.parametrize("data, key, words", [
    ({}, "phantom", "missing table"),
    (base(length_m=-1), "phantom.length_m", "> 0"),
    (base(width_m="wide"), "phantom.width_m", "finite number"),
    (base(poisson_ratio=0.5), "phantom.poisson_ratio", "[0, 0.5)"),
    (base(colour="pink"), "phantom.colour", "unknown key"),
    (base(surface=[{"kind": "dome", "x_range_m": [0, 0.01]}]), "phantom.surface[0].kind", "unknown surface feature"),
    (base(surface=[{"kind": "slope", "x_range_m": [0.02, 0.01], "gradient": [0.1, 0]}]),
     "phantom.surface[0].x_range_m", "upper bound"),
    (base(surface=[{"kind": "slope", "x_range_m": [0, 0.072], "gradient": [-0.5, 0]}]), "phantom.surface",
     "above the table"),
    (base(inclusions=[sphere()]), "phantom.inclusions[0].depth_m", "exactly one"),
    (base(inclusions=[sphere(depth_m=0.002, height_m=0.01)]), "phantom.inclusions[0].depth_m", "exactly one"),
    (base(inclusions=[sphere(height_m=0.002)]), "phantom.inclusions[0].height_m", "through the table"),
    (base(inclusions=[sphere(height_m=0.0225)]), "phantom.inclusions[0].height_m", "breaks through the surface"),
    (base(inclusions=[sphere(centre_xy_m=[0.036, 0.002], depth_m=0.005)]), "phantom.inclusions[0].centre_xy_m",
     "pokes out"),
    (base(inclusions=[sphere(centre_xy_m=[0.1, 0.015], depth_m=0.005)]), "phantom.inclusions[0].centre_xy_m",
     "outside"),
    (base(inclusions=[sphere(depth_m=0.005), sphere(depth_m=0.009)]), "phantom.inclusions[1].centre_xy_m",
     "overlaps inclusions[0]"),
    (base(regions=[{"centre_xy_m": [0.2, 0.0]}]), "phantom.regions[0].centre_xy_m", "outside"),
    # issue 14, finding 8: sizes checked before anything is allocated (a 10 m phantom asked for 12 GiB)
    (base(length_m=10.0), "phantom.length_m", "at most 0.5 (a bench phantom)"),
    (base(thickness_m=2.0), "phantom.thickness_m", "at most 0.1"),
    (base(youngs_modulus_pa=1e300), "phantom.youngs_modulus_pa", "at most 1e+09"),
    (base(surface=[{"kind": "half_cylinder", "centre_y_m": 0.015, "radius_m": 1e200, "x_range_m": [0, 0.07]}]),
     "phantom.surface[0].radius_m", "at most 1"),
    (base(surface=[{"kind": "slope", "x_range_m": [0, 0.072], "gradient": [1e300, 0]}]),
     "phantom.surface[0].gradient", "within +-10"),
    (base(inclusions=[sphere(depth_m=0.005, diameter_m=0.5)]), "phantom.inclusions[0].diameter_m", "fit in the layer"),
    # issue 15: the sides and the law at finite strain
    (base(sides="tray"), "phantom.sides", "one of free, mould"),
    # issue 48: micro-relief
    (base(surface=[{"kind": "relief", "x_range_m": [0, 0.07], "rms_m": 2e-3, "wavelength_m": 4e-3}]),
     "phantom.surface[0].rms_m", "at most 0.001"),
    (base(surface=[{"kind": "relief", "x_range_m": [0, 0.07], "rms_m": 2e-4, "wavelength_m": 1e-3}]),
     "phantom.surface[0].wavelength_m", "at least 0.002"),
    (base(surface=[{"kind": "relief", "x_range_m": [0, 0.07], "rms_m": 2e-4, "wavelength_m": 4e-3, "seed": -1}]),
     "phantom.surface[0].seed", "non-negative integer"),
    (base(surface=[{"kind": "relief", "x_range_m": [0, 0.07], "rms_m": 2e-4, "wavelength_m": 4e-3,
                    "gradient": [0, 0]}]), "phantom.surface[0].gradient", "unknown key"),
    (base(material={"law": "ogden"}), "phantom.material.law", "one of neo_hookean, yeoh"),
    (base(material={"law": "neo_hookean", "c2_over_c1": 0.1}), "phantom.material.c2_over_c1", "unknown key"),
    (base(material={"law": "yeoh", "c2_over_c1": -0.5, "c3_over_c1": 0.05}), "phantom.material.c2_over_c1",
     "stops rising"),
    (base(material={"law": "yeoh", "c3_over_c1": -0.1}), "phantom.material.c2_over_c1", "stops rising"),
    (base(material="yeoh"), "phantom.material", "must be a table"),
    (base(face_friction=-0.1), "phantom.face_friction", ">= 0"),
    (base(face_friction=5.0), "phantom.face_friction", "within +-2"),
    (base(face_friction=float("nan")), "phantom.face_friction", "finite number"),
    # issue 49: too small, too soft, too many (3,000 inclusions took 272 s and 4.8 GB; 4,000 features, the
    # parser alone more than 15 min)
    (base(length_m=1e-9), "phantom.length_m", "at least 0.004"),
    (base(youngs_modulus_pa=1e-300), "phantom.youngs_modulus_pa", "at least 100"),
    (base(inclusions=[sphere(depth_m=0.005)] * 3000), "phantom.inclusions",
     "3000 of them; a bench phantom has at most 20"),
    (base(surface=[{"kind": "slope", "x_range_m": [0, 0.01], "gradient": [0, 0]}] * 4000), "phantom.surface",
     "at most 20"),
])
def test_a_bad_phantom_names_the_key_and_the_problem(data, key, words):
    with pytest.raises(PhantomError) as err:
        parse_phantom(data, "bad.toml")
    assert err.value.key == key
    assert words in err.value.problem
    assert str(err.value).startswith(f"bad.toml: {key}: ")


def test_micro_relief_has_the_rms_asked_for_is_fixed_by_its_seed_and_carries_the_tumours_with_it():
    def relief(seed, rms=0.2e-3):
        return {"kind": "relief", "x_range_m": [0.0, 0.072], "rms_m": rms, "wavelength_m": 4e-3, "seed": seed}

    a, b = parse_phantom(base(surface=[relief(1)])), parse_phantom(base(surface=[relief(2)]))
    x, y = np.meshgrid(np.linspace(0, 0.072, 289), np.linspace(0, 0.030, 121), indexing="ij")
    ha, hb = a.surface_height_m(x, y) - a.thickness_m, b.surface_height_m(x, y) - b.thickness_m
    assert 0.14e-3 < ha.std() < 0.26e-3 and abs(ha.mean()) < 0.1e-3
    assert np.array_equal(ha, parse_phantom(base(surface=[relief(1)])).surface_height_m(x, y) - a.thickness_m)
    assert not np.allclose(ha, hb) and a.content_hash() != b.content_hash()
    sunk = parse_phantom(base(surface=[relief(1)], inclusions=[sphere(depth_m=0.004)]))
    assert sunk.ground_truth()[0]["depth_m"] == pytest.approx(0.004)


def test_a_sphere_under_a_bump_must_clear_the_bump_edge_not_only_its_centre():
    bump = {"kind": "half_cylinder", "centre_y_m": 0.015, "radius_m": 0.003, "x_range_m": [0.0, 0.072]}
    # 1 mm under the 3 mm bump's crest, an 8 mm sphere bulges out beside the bump.
    with pytest.raises(PhantomError, match="breaks through the surface"):
        parse_phantom(base(thickness_m=0.010, surface=[bump], inclusions=[sphere(depth_m=0.001)]))
    assert parse_phantom(base(thickness_m=0.010, surface=[bump], inclusions=[sphere(depth_m=0.004)])).inclusions


def test_missing_and_malformed_files_are_reported(tmp_path):
    with pytest.raises(PhantomError, match="no such phantom.*flat.*uneven"):
        load_phantom("no-such-phantom")
    bad = tmp_path / "bad.toml"
    bad.write_text("[phantom\nname = 1", encoding="utf-8")
    with pytest.raises(PhantomError, match="not valid TOML"):
        load_phantom(bad)
    deep = tmp_path / "deep.toml"
    deep.write_text("a = " + "[" * 100_000 + "]" * 100_000, encoding="utf-8")
    with pytest.raises(PhantomError, match="nested too deeply"):
        load_phantom(deep)
    huge = tmp_path / "huge.toml"
    huge.write_bytes(b"#" * (2 << 20))
    with pytest.raises(PhantomError, match="larger than 1024 kB"):
        load_phantom(huge)
