"""The continuum tissue model as the rig uses it: per-element forces, symmetry, linearity, exactness, cache."""

import io
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sla
from scipy.optimize import nnls

import tissue.face
import tissue.phantom
from hardware.interfaces import TactileConstraints
from tissue.mechanics import cache as cache_mod
from tissue.mechanics import model as model_mod
from tissue.mechanics.contact import tributary_weights
from tissue.mechanics.fem import condensed_surface_stiffness
from tissue.mechanics.model import ContinuumTissue, MeshSettings, phantom_grid, phantom_material
from tissue.mechanics.progress import TextProgressBar
from tissue.phantom import load_phantom, parse_phantom
from tissue.winkler import WinklerTissue

SENSOR = TactileConstraints()
SMALL = MeshSettings(spacing_m=1e-3, layers=5, top_layer_m=1e-3, drift_y_m=1e-3)


def small(inclusions=(), surface=(), length=0.024, thickness=0.010, young=20e3):
    table = {"name": "small", "length_m": length, "width_m": 0.030, "thickness_m": thickness,
             "youngs_modulus_pa": young, "poisson_ratio": 0.49, "inclusions": list(inclusions),
             "surface": list(surface)}
    return parse_phantom({"phantom": table})


def tumour(x, y, depth):
    return {"centre_xy_m": [x, y], "diameter_m": 0.006, "youngs_modulus_pa": 160e3, "depth_m": depth}


BUMP = {"kind": "half_cylinder", "centre_y_m": 0.022, "radius_m": 0.004, "x_range_m": [0.0, 0.016]}
LEVEL = MeshSettings(spacing_m=1e-3, layers=5, top_layer_m=1e-3, drift_y_m=0.0)
COARSE = MeshSettings(spacing_m=2e-3, layers=3, top_layer_m=2e-3, drift_y_m=0.0)


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("tissue-cache")


@pytest.fixture(scope="module")
def flat(cache_dir):
    return ContinuumTissue.load(small(), cache_dir, settings=SMALL)


@pytest.fixture(scope="module")
def bumpy(cache_dir):
    return ContinuumTissue.load(small(length=0.016, surface=[BUMP], inclusions=[tumour(0.008, 0.012, 0.002)]),
                                cache_dir, settings=LEVEL)


def test_forces_are_per_element_non_negative_and_only_in_contact(flat):
    f = flat.element_forces_N(0.012, 0.015, 0.008)
    assert f.shape == (4, 15) and (f > 0).all()
    assert not flat.element_forces_N(0.012, 0.015, 0.0101).any()  # above the surface
    assert not flat.element_forces_N(-0.010, 0.015, 0.005).any()  # beside the phantom
    partly = flat.element_forces_N(-0.001, 0.015, 0.008)  # the face hangs over the phantom's end
    assert not partly[:2].any() and (partly[2:] > 0).all()
    rng = np.random.default_rng(0)
    for x, y, z in zip(rng.uniform(-0.01, 0.035, 200), rng.uniform(0.010, 0.020, 200), rng.uniform(0, 0.011, 200)):
        assert (flat.element_forces_N(x, y, z) >= 0).all()


def test_a_centred_face_on_a_homogeneous_phantom_gives_a_symmetric_map(flat):
    f = flat.element_forces_N(0.012, 0.015, 0.008)
    assert np.allclose(f, f[::-1, :], rtol=1e-9)
    assert np.allclose(f, f[:, ::-1], rtol=1e-9)
    # A rigid punch concentrates load at its edges; a spring bed would be uniform.
    assert f[0, 7] > 1.5 * f[1, 7]


def test_mirrored_phantoms_give_mirrored_maps(cache_dir):
    below = ContinuumTissue.load(small(inclusions=[tumour(0.012, 0.011, 0.002)]), cache_dir, settings=LEVEL)
    above = ContinuumTissue.load(small(inclusions=[tumour(0.012, 0.019, 0.002)]), cache_dir, settings=LEVEL)
    a, b = below.element_forces_N(0.012, 0.015, 0.008), above.element_forces_N(0.012, 0.015, 0.008)
    assert np.allclose(a, b[:, ::-1], rtol=1e-8)
    assert np.argmax(a[1]) == 5 and np.argmax(b[1]) == 9  # the peak sits over the tumour (y = 11 / 19 mm)


def test_superposition_holds_in_full_contact_and_not_while_contact_grows(flat, bumpy, cache_dir):
    one, two = flat.element_forces_N(0.012, 0.015, 0.009), flat.element_forces_N(0.012, 0.015, 0.008)
    assert np.allclose(two, 2.0 * one, rtol=1e-9)  # level face on a level surface: linear from first touch
    stiff = ContinuumTissue.load(small(young=40e3), cache_dir, settings=LEVEL)
    assert np.allclose(stiff.element_forces_N(0.012, 0.015, 0.009), 2.0 * one, rtol=1e-9)
    # On a bump the contact area grows with depth, so force grows faster than depth.
    top = 0.014
    shallow, deep = bumpy.total_force_N(0.008, 0.015, top - 1e-3), bumpy.total_force_N(0.008, 0.015, top - 2e-3)
    assert deep > 2.2 * shallow
    touching = bumpy.element_forces_N(0.008, 0.015, top - 1e-3) > 0
    assert touching[:, 10:12].all() and not touching[:, :8].any()  # only the elements on the bump touch


def test_tabulated_forces_are_the_contact_solution_at_lattice_poses(bumpy):
    # Independent recomputation at one lattice pose: condensed compliance, bound-constrained
    # least squares for the contact forces, nodes binned into elements.
    phantom = bumpy.phantom
    grid = phantom_grid(phantom, LEVEL)
    ij, s = condensed_surface_stiffness(grid, phantom_material(phantom))
    xs, ys, hs = grid.x_m[ij[:, 0]], grid.y_m[ij[:, 1]], grid.height_m[ij[:, 0], ij[:, 1]]
    cx, cy = 0.008, 0.015
    under = np.flatnonzero((np.abs(xs - cx) <= 0.004 + 1e-9) & (np.abs(ys - cy) <= 0.015 + 1e-9))
    c = np.linalg.inv(s)[np.ix_(under, under)]
    w = tributary_weights(xs[under], ys[under], (0, phantom.length_m, 0, phantom.width_m),
                          (cx - 0.004, cy - 0.015), SENSOR.pitch_m, SENSOR.shape)
    r = sla.cholesky(c)
    for z in (0.0135, 0.012, 0.0105, 0.009):
        f, _ = nnls(r, sla.solve_triangular(r, hs[under] - z, trans="T"), maxiter=20000)
        expected = (w @ f).reshape(4, 15)
        assert np.allclose(bumpy.element_forces_N(cx, cy, z), expected, rtol=1e-7, atol=1e-9)


def test_between_lattice_poses_forces_blend_smoothly(bumpy):
    a = bumpy.element_forces_N(0.008, 0.015, 0.011)
    b = bumpy.element_forces_N(0.009, 0.015, 0.011)
    mid = bumpy.element_forces_N(0.0085, 0.015, 0.011)
    assert np.allclose(mid, 0.5 * (a + b))
    # Offsets beyond the tabulated drift (none here) are evaluated at the last tabulated one.
    assert np.array_equal(bumpy.element_forces_N(0.008, 0.017, 0.011), a)


def test_a_hard_inclusion_shows_as_a_force_peak_above_it(flat, cache_dir):
    hard = ContinuumTissue.load(small(inclusions=[tumour(0.012, 0.015, 0.002)]), cache_dir, settings=LEVEL)
    f_hard, f_soft = hard.element_forces_N(0.012, 0.015, 0.008), flat.element_forces_N(0.012, 0.015, 0.008)
    assert f_hard[1:3, 7].mean() > 1.5 * f_soft[1:3, 7].mean()
    assert f_hard[1:3, 0].mean() == pytest.approx(f_soft[1:3, 0].mean(), rel=0.15)  # far from it, little change
    assert hard.ground_truth() == hard.phantom.ground_truth()


def test_the_continuum_needs_two_to_three_times_the_winkler_force_on_the_papers_phantom(cache_dir):
    phantom = load_phantom("flat")
    coarse = MeshSettings(spacing_m=2e-3, layers=6, top_layer_m=2e-3, drift_y_m=0.0)
    continuum = ContinuumTissue.load(phantom, cache_dir, settings=coarse)
    winkler = WinklerTissue(phantom)
    z = phantom.thickness_m - 2e-3
    for x in (0.028, 0.044):  # tumour-free regions
        ratio = continuum.total_force_N(x, 0.015, z) / winkler.element_forces_N(x, 0.015, z).sum()
        assert 2.0 < ratio < 4.0


def test_the_cache_is_reused_keyed_by_content_and_never_trusted_when_damaged(cache_dir, monkeypatch, caplog):
    phantom = small(length=0.016, inclusions=[tumour(0.010, 0.015, 0.003)])
    calls = []
    real = model_mod.precompute
    monkeypatch.setattr(model_mod, "precompute", lambda *a, **k: calls.append(1) or real(*a, **k))
    first = ContinuumTissue.load(phantom, cache_dir, settings=COARSE)
    again = ContinuumTissue.load(phantom, cache_dir, settings=COARSE)
    assert len(calls) == 1
    probe = (0.009, 0.015, 0.008)
    assert np.array_equal(first.element_forces_N(*probe), again.element_forces_N(*probe))
    path = cache_mod.cache_path(cache_dir, model_mod.cache_key(phantom, COARSE, SENSOR))
    assert path.is_file() and not list(cache_dir.glob("*.tmp"))

    blob = path.read_bytes()
    key = model_mod.cache_key(phantom, COARSE, SENSOR)
    stored = cache_mod.load(path, key)
    for damaged in (blob[: len(blob) // 2], blob[:-10] + b"0123456789", b"not a cache file", b""):
        path.write_bytes(damaged)
        rebuilt = ContinuumTissue.load(phantom, cache_dir, settings=COARSE)
        assert np.array_equal(rebuilt.element_forces_N(*probe), first.element_forces_N(*probe))
        rewritten = cache_mod.load(path, key)  # recomputed and rewritten whole
        assert all(np.array_equal(rewritten[k], stored[k]) for k in ("lattice", "offsets", "t", "f0", "df"))
    assert len(calls) == 5

    moved = small(length=0.016, inclusions=[tumour(0.011, 0.015, 0.003)])
    assert model_mod.cache_key(moved, COARSE, SENSOR) != key
    assert model_mod.cache_key(phantom, MeshSettings(), SENSOR) != key
    assert cache_mod.load(path, "another-key") is None
    monkeypatch.setattr(cache_mod, "code_digest", lambda: "other-mechanics")  # the solver's code changed
    assert cache_mod.load(path, key) is None
    ContinuumTissue.load(phantom, cache_dir, settings=COARSE)
    assert len(calls) == 6 and cache_mod.load(path, key) is not None  # recomputed, and stored as that code's
    monkeypatch.undo()

    not_a_dir = cache_dir / "a-file"
    not_a_dir.write_text("x")
    with caplog.at_level(logging.WARNING):
        ContinuumTissue.load(phantom, not_a_dir, settings=COARSE)
    assert "could not write the tissue cache" in caplog.text


def test_the_default_cache_lives_where_the_environment_says(tmp_path, monkeypatch):
    monkeypatch.setenv("PALPATION_CACHE_DIR", str(tmp_path / "here"))
    ContinuumTissue.load(small(length=0.012), settings=MeshSettings(spacing_m=2e-3, layers=3, top_layer_m=2e-3))
    assert len(list((tmp_path / "here").glob("tissue-*.bin"))) == 1


def test_progress_is_reported_from_zero_to_done(cache_dir):
    seen = []
    ContinuumTissue.load(small(length=0.016, thickness=0.012), cache_dir, settings=LEVEL,
                         progress=lambda f, m: seen.append((f, m)))
    fractions = [f for f, _ in seen]
    assert fractions[-1] == 1.0 and all(b >= a for a, b in zip(fractions, fractions[1:]))
    assert any("condensing" in m for _, m in seen) and "ready" in seen[-1][1]
    out = io.StringIO()
    bar = TextProgressBar(out, width=10, interval_s=0.0)
    bar(0.5, "halfway")
    bar(1.0, "done")
    assert "[#####     ]  50% halfway" in out.getvalue() and "100% done" in out.getvalue()
    assert out.getvalue().endswith("\n")


def test_the_terminal_bar_keeps_to_one_line_of_the_terminal(monkeypatch):
    monkeypatch.setenv("COLUMNS", "60")
    out = io.StringIO()
    bar = TextProgressBar(out, width=30, interval_s=0.0)
    bar(0.25, "compressed tables: condensing the tissue onto its surface")
    bar(1.0, "tissue model of 'uneven' ready")
    drawn = out.getvalue().replace("\n", "\r").split("\r")
    assert max(len(line.rstrip()) for line in drawn) <= 59 and drawn[1].endswith("25% compressed tables: co")


def test_a_tilted_face_presses_its_low_side_first_and_harder_and_mirrors_with_the_tilt(cache_dir):
    """issue 48: the probe tilted by hand, which the analysis does not know of."""
    import math
    from dataclasses import replace

    block = small(length=0.016)
    level = ContinuumTissue.load(block, cache_dir, settings=LEVEL)
    tilt = math.radians(1.5)
    along_x = ContinuumTissue.load(block, cache_dir, settings=replace(LEVEL, tilt_rad=(tilt, 0.0)))
    along_y = ContinuumTissue.load(block, cache_dir, settings=replace(LEVEL, tilt_rad=(0.0, tilt)))
    back = ContinuumTissue.load(block, cache_dir, settings=replace(LEVEL, tilt_rad=(0.0, -tilt)))
    z = 0.009
    flat, fx, fy, fb = (m.element_forces_N(0.008, 0.015, z) for m in (level, along_x, along_y, back))
    # rising along y, the face is 0.39 mm lower at its first column than at its last
    assert fy[:, 0].sum() > 1.3 * fy[:, -1].sum() and np.allclose(fb, fy[:, ::-1], rtol=1e-6)
    assert fx[0].sum() > fx[-1].sum() and not np.allclose(fx, flat)
    assert fy.sum() == pytest.approx(flat.sum(), rel=0.05)  # tilted about its centre, the same mean depth
    # the low corner touches before a level face would
    assert along_y.element_forces_N(0.008, 0.015, 0.0101).any()
    assert not level.element_forces_N(0.008, 0.015, 0.0101).any()
    with pytest.raises(ValueError, match="tilt_rad"):
        ContinuumTissue.load(block, cache_dir, settings=replace(LEVEL, tilt_rad=(0.2, 0.0)))


def test_bad_mesh_settings_are_refused():
    with pytest.raises(ValueError, match="spacing_m.*divide the sensor pitch"):
        ContinuumTissue.load(small(), settings=MeshSettings(spacing_m=0.7e-3))
    with pytest.raises(ValueError, match="layers"):
        ContinuumTissue.load(small(), settings=MeshSettings(layers=1))


def test_the_cache_knows_the_code_beside_the_mechanics_that_its_tables_come_from(tmp_path):
    """A table is computed from the mechanics' own modules and from how the phantom draws its surface and the
    face its elements: a change to any of them is other code, so the tables it made are stale."""
    assert {Path(tissue.phantom.__file__), Path(tissue.face.__file__)} <= set(cache_mod.sources())
    copy = tmp_path / "tissue"
    shutil.copytree(Path(tissue.phantom.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    before = cache_mod.digest_of(copy / "mechanics")
    assert before == cache_mod.code_digest()
    relief = copy / "phantom.py"
    relief.write_text(relief.read_text() + "\n# another way to draw a relief\n")
    assert cache_mod.digest_of(copy / "mechanics") != before
