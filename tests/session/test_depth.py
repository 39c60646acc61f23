"""The model-based depth (session/depth.py): the shipped library is what the project's mechanics gives, a
damaged one is refused in one line, and the inversion's interval covers a tumour the library never held."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from session.depth import (
    LIBRARY_PATH,
    LIBRARY_PATHS,
    DepthModel,
    DepthModelError,
    LibraryGrid,
    _block_solve,
    _kept_block_solve,
    _level_mean,
    build_library,
    level_correlation,
    load_library,
)
from session.detect import DepthParams

PITCH = 2e-3
SHAPE = (4, 15)


@pytest.fixture(scope="module")
def library():
    return load_library()


def test_the_shipped_library_is_what_the_mechanics_gives(library):
    grid = LibraryGrid()
    t, d, a, r = 0, grid.depth_m.index(2.5e-3), 0, 1  # 20 mm layer, top 2.5 mm deep, 5 mm across, 6 times stiffer
    solved = _block_solve(grid, grid.thickness_m[t], (grid.depth_m[d], grid.diameter_m[a], grid.modulus_ratio[r]))
    np.testing.assert_allclose(library.inclusion[t, d, a, r], solved, rtol=1e-5)
    np.testing.assert_allclose(library.homogeneous[t], _block_solve(grid, grid.thickness_m[t], None), rtol=1e-5)
    # a sphere that does not fit in the layer has no solve
    assert np.isnan(library.inclusion[0, -1, -1, 0]).all()


def test_the_shipped_mould_library_is_what_the_mechanics_gives_between_a_moulds_walls(library):
    # the same layer and sphere as above, its lateral faces on a mould's walls: its own solve, and a sphere's
    # contrast there is not the free layer's (the walls hold the tissue the sphere would push aside)
    mould = load_library(LIBRARY_PATHS["mould"])
    assert mould.sides == "mould" and library.sides == "free"
    grid = LibraryGrid()
    t, d, a, r = 0, grid.depth_m.index(2.5e-3), 0, 1
    sphere = (grid.depth_m[d], grid.diameter_m[a], grid.modulus_ratio[r])
    solved = _block_solve(grid, grid.thickness_m[t], sphere, sides="mould")
    np.testing.assert_allclose(mould.inclusion[t, d, a, r], solved, rtol=1e-5)
    np.testing.assert_allclose(mould.homogeneous[t], _block_solve(grid, grid.thickness_m[t], None, sides="mould"),
                               rtol=1e-5)
    free_rise = (library.inclusion[t, d, a, r] / library.homogeneous[t]).max()
    mould_rise = (mould.inclusion[t, d, a, r] / mould.homogeneous[t]).max()
    assert mould_rise - 1.0 < 0.8 * (free_rise - 1.0)


def test_a_model_for_tissue_in_a_mould_reads_a_moulds_sphere_at_its_depth_where_the_free_one_reads_it_deeper():
    model = DepthModel.for_info(SimpleNamespace(calibration={"rows": 4, "cols": 15, "pitch_m": PITCH,
                                                             "cover_spread_m": 0.0}))
    assert model.sides == "free" and model.with_sides("free") is model
    mould = model.with_sides("mould")
    assert mould.sides == "mould" and mould.library.sides == "mould" and mould.with_sides("mould") is mould
    # a deep sphere (8 mm, 10.25 mm across, 12 times stiffer): the walls take its contrast from +0.31 to +0.18,
    # which the free layer reads as a sphere 1.4 mm deeper (its shape, not only its height, tells the depth:
    # one 4 mm deep reads alike in both)
    thickness, y, depth = 0.026, SHAPE[1] * PITCH / 2, 8e-3
    entry = (list(mould.library.depth_m).index(depth), list(mould.library.diameter_m).index(10.25e-3), 2)
    seen = mould.predict(thickness, 0.0, y)[entry]
    rows, measured, tumour = _one_area(seen, 0.02, thickness, 0.030, y, 0.030)
    read = mould.estimate(tumour, rows, measured)
    assert read[1] <= depth <= read[2]
    assert model.estimate(tumour, rows, measured)[0] > read[0] + 0.5e-3
    with pytest.raises(DepthModelError, match="no depth model library for sides 'tray'"):
        model.with_sides("tray")


def test_a_damaged_foreign_or_missing_library_is_refused_in_one_line(tmp_path):
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, format=np.array("something else"), version=np.array(1))
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(LIBRARY_PATH.read_bytes()[:5000])
    for path, said in ((foreign, "not a version"), (truncated, "cannot be read"),
                       (tmp_path / "missing.npz", "cannot be read")):
        with pytest.raises(DepthModelError, match=said) as caught:
            load_library(path)
        assert "\n" not in str(caught.value)


def test_an_array_the_library_was_not_built_for_is_refused(library):
    with pytest.raises(DepthModelError, match="built for a 4 x 15 array"):
        DepthModel(library, (4, 16), PITCH, 0.0)


def _one_area(contrast: np.ndarray, sigma: float, thickness_m: float, tumour_x: float, tumour_y: float,
              face_x: float, levels: int = 3, pressed_m=0.0):
    """Level records of one area, its face centred at (face_x, mid-array), flat surface at ``thickness_m``,
    every element pressed ``pressed_m`` (0: the small-strain limit, where the contrast is the library's; or
    one per level, with ``contrast`` one per level)."""
    rows = np.zeros(levels, dtype=[("region", "i4"), ("tsi_position_m", "f8", 3), ("onset_height_m", "f8", SHAPE),
                                   ("dL_m", "f8", SHAPE)])
    pressed_m = np.broadcast_to(pressed_m, (levels,))
    rows["tsi_position_m"] = np.stack([np.full(levels, face_x), np.full(levels, SHAPE[1] * PITCH / 2),
                                       thickness_m - pressed_m], axis=1)
    rows["onset_height_m"] = thickness_m
    rows["dL_m"] = pressed_m[:, None, None]
    rng = np.random.default_rng(7)
    noisy = np.broadcast_to(contrast, (levels, *SHAPE)) + rng.normal(0.0, sigma, (levels, *SHAPE))
    measured = SimpleNamespace(contrast=noisy, sigma=np.full_like(noisy, sigma))
    return rows, measured, SimpleNamespace(x_m=tumour_x, y_m=tumour_y)


def test_the_interval_covers_a_tumour_the_library_never_held(library):
    """An independent solve: a 25 mm layer (the library holds 20 and 32), the sphere's top 5 mm deep, 7 mm
    across, 8 times stiffer, the face 2 mm off it; sensor noise on top. The estimate comes within the
    library's spacing, the interval covers the truth and says something (narrower than the prior)."""
    thickness, depth = 0.025, 5e-3
    grid = replace(LibraryGrid(), offset_x_m=(2e-3,))
    nodal_with = _block_solve(grid, thickness, (depth, 7e-3, 8.0))[0]
    nodal_without = _block_solve(grid, thickness, None)[0]
    model = DepthModel(library, SHAPE, PITCH, 0.0)
    q = model._elements(nodal_with) / model._elements(nodal_without)
    truth = q / np.median(q) - 1.0
    tumour_x = 0.030
    rows, measured, tumour = _one_area(truth, 0.02, thickness, tumour_x, SHAPE[1] * PITCH / 2, tumour_x + 2e-3)
    estimate, low, high = model.estimate(tumour, rows, measured)
    assert low <= depth <= high
    assert abs(estimate - depth) < 2e-3
    assert high - low < 0.6 * (library.depth_m[-1] - library.depth_m[0])


def test_the_tissues_side_does_not_draw_the_depth(library):
    """A sphere 1 mm from a free side of the tissue (the face spans the tissue's width, as in the paper's
    protocol), 3 mm deep at rest, 9 mm across, 5 times stiffer, in a 25 mm layer pressed to 30 %: it shows
    as one 3 (1 - 0.3) - 4.5 x 0.3 = 0.75 mm deep does at rest (an independent solve of that, with the
    side). The library shifts a mid-array signature sideways and knows no side, so the elements on the side
    are left out: what they read (the simulated sessions of the validation study read down to -0.2 there
    beside a shallow tumour) does not move the estimate, which covers the truth."""
    thickness, depth, pressed, tumour_y = 0.025, 3e-3, 7.5e-3, 24.5e-3
    grid = replace(LibraryGrid(), offset_x_m=(2e-3,))
    nodal_with = _block_solve(grid, thickness, (0.75e-3, 9e-3, 5.0), tumour_y_m=tumour_y)[0]
    nodal_without = _block_solve(grid, thickness, None)[0]
    model = DepthModel(library, SHAPE, PITCH, 0.0)
    q = model._elements(nodal_with) / model._elements(nodal_without)
    seen = q / np.median(q) - 1.0
    estimates = []
    for side in (seen[:, -1], np.full(SHAPE[0], -0.2)):
        rows, measured, tumour = _one_area(np.concatenate([seen[:, :-1], side[:, None]], axis=1), 0.02, thickness,
                                           0.030, tumour_y, 0.032, pressed_m=pressed)
        estimates.append(model.estimate(tumour, rows, measured))
    assert estimates[0] == estimates[1]
    estimate, low, high = estimates[0]
    assert low <= depth <= high
    assert abs(estimate - depth) < 1e-3


def test_a_tumour_seen_pressed_deep_is_read_at_its_depth_at_rest(library):
    """At finite strain the tissue over a tumour thins: pressed to 30 % the 6 mm deep, 7 mm sphere shows as
    one 6 (1 - 0.3) - 3.5 x 0.3 = 3.15 mm deep does at rest (an independent solve of that). The estimate
    is the depth at rest, and without the strain it would have been the shallower one."""
    thickness, depth, pressed = 0.025, 6e-3, 7.5e-3
    grid = replace(LibraryGrid(), offset_x_m=(2e-3,))
    nodal_with = _block_solve(grid, thickness, (3.15e-3, 7e-3, 8.0))[0]
    nodal_without = _block_solve(grid, thickness, None)[0]
    model = DepthModel(library, SHAPE, PITCH, 0.0)
    q = model._elements(nodal_with) / model._elements(nodal_without)
    seen = q / np.median(q) - 1.0
    args = (seen, 0.02, thickness, 0.030, SHAPE[1] * PITCH / 2, 0.032)
    rows, measured, tumour = _one_area(*args, pressed_m=pressed)
    estimate, low, high = model.estimate(tumour, rows, measured)
    assert low <= depth <= high and abs(estimate - depth) < 1e-3
    rows, measured, tumour = _one_area(*args)
    at_rest, *_ = model.estimate(tumour, rows, measured)
    assert abs(at_rest - 3.15e-3) < 1e-3


def test_the_forward_model_shows_a_pressed_tumour_as_the_rigs_reduced_model_does(library):
    """The simulated rig tabulates each inclusion at rest and where a layer compressed by COMPRESSED_STRAIN
    carries it, and an element pressed part-way sees the two mixed in proportion to its strain
    (tissue.mechanics.model). At half that strain a sphere 3 mm deep, 8 mm across, 6 times stiffer
    shows half as at rest and half as one 3 (1 - 0.3) - 4 x 0.3 = 0.9 mm deep does, which is more than the
    sphere half-way between (2.0 mm) shows: a tumour's contrast grows ever faster as it nears the surface."""
    from tissue.mechanics.model import COMPRESSED_STRAIN

    assert COMPRESSED_STRAIN == 0.3
    model = DepthModel(library, SHAPE, PITCH, 0.0)
    fine = model._fine(model.predict(0.025, 2e-3, SHAPE[1] * PITCH / 2)).reshape(*model.depths.shape, 8, 7, -1)
    d, a, r = (int(np.argmin(np.abs(axis - v))) for axis, v in ((model.depths, 3e-3), (model.diameters, 8e-3),
                                                                  (model.ratios, 6.0)))
    at = {v: fine[int(np.argmin(np.abs(model.depths - v))), a, r] for v in (3e-3, 2e-3, 1e-3, 0.75e-3)}
    moved = 0.4 * at[0.75e-3] + 0.6 * at[1e-3]  # 0.9 mm, between the fine grid's depths
    shown = model._pressed(fine, np.array([0.15]), np.ones((1, fine.shape[-1])), np.array([1.0]))[0, d, a, r]
    np.testing.assert_allclose(shown, 0.5 * (at[3e-3] + moved), atol=1e-9)
    assert shown.max() > 1.05 * at[2e-3].max()


def test_a_shallow_tumour_is_read_at_its_depth_at_rest_from_levels_pressed_ever_deeper(library):
    """Levels pressed to 10, 20 and 30 %: a sphere 2 mm deep at rest, 6 mm across, 8 times stiffer shows as
    the simulated rig's reduced model says, its contrast at rest and where a layer compressed by 30 % carries
    it, 2 (1 - 0.3) - 3 x 0.3 = 0.5 mm deep (two independent solves), mixed in proportion 1/3, 2/3 and 1.
    That is nearer the surface than any tumour is taken to lie at rest but not than the library reaches,
    and not the sphere at the depth each level's strain alone would carry it to (a tumour's contrast grows
    ever faster as it nears the surface). The estimate is the depth at rest and its interval covers it."""
    thickness, depth, strains = 0.025, 2e-3, np.array([0.1, 0.2, 0.3])
    grid = replace(LibraryGrid(), offset_x_m=(2e-3,))
    nodal_without = _block_solve(grid, thickness, None)[0]
    model = DepthModel(library, SHAPE, PITCH, 0.0)
    states = []
    for at in (depth, 0.5e-3):
        q = model._elements(_block_solve(grid, thickness, (at, 6e-3, 8.0))[0]) / model._elements(nodal_without)
        states.append(q / np.median(q) - 1.0)
    mix = (strains / 0.3)[:, None, None]
    rows, measured, tumour = _one_area((1 - mix) * states[0] + mix * states[1], 0.02, thickness, 0.030,
                                       SHAPE[1] * PITCH / 2, 0.032, pressed_m=strains * thickness)
    estimate, low, high = model.estimate(tumour, rows, measured)
    assert low <= depth <= high
    assert abs(estimate - depth) < 0.5e-3


@pytest.mark.parametrize("depth, ratio, growth", [(2e-3, 10.0, 1.5), (3e-3, 4.0, 0.5)])
def test_the_interval_covers_a_tumour_in_tissue_whose_law_is_not_the_models(library, depth, ratio, growth):
    """Levels pressed to 10, 20 and 30 % of a 25 mm layer over a sphere 6 mm across, its contrast at rest and
    where a layer compressed by 30 % carries it (two independent solves), but grown with the press 1.5 or 0.5
    times as fast as the reduced model's law grows it (a stiffening or a softer tissue). Trusting that law
    (law spread 0) the interval misses the sphere; weighing the laws around it, it covers it. At a model error
    of 0.25: at the default 0.10 the stiffening tissue's sphere is read close enough for either to cover it."""
    thickness, strains = 0.025, np.array([0.1, 0.2, 0.3])
    grid = replace(LibraryGrid(), offset_x_m=(2e-3,))
    nodal_without = _block_solve(grid, thickness, None)[0]
    model = DepthModel(library, SHAPE, PITCH, 0.0)
    states = []
    for at in (depth, depth * 0.7 - 3e-3 * 0.3):
        q = model._elements(_block_solve(grid, thickness, (at, 6e-3, ratio))[0]) / model._elements(nodal_without)
        states.append(q / np.median(q) - 1.0)
    grown = growth * (strains / 0.3)[:, None, None] * (states[1] - states[0])
    rows, measured, tumour = _one_area(states[0] + grown, 0.02, thickness, 0.030, SHAPE[1] * PITCH / 2, 0.032,
                                       pressed_m=strains * thickness)
    _, low, high = model.with_params(DepthParams(model_error=0.25, law_spread=0.0)).estimate(tumour, rows, measured)
    assert not low <= depth <= high
    _, low, high = model.with_params(DepthParams(model_error=0.25)).estimate(tumour, rows, measured)
    assert low <= depth <= high


def test_the_sphere_that_made_the_contrast_explains_it_best(library):
    """A contrast the model itself predicts, for a sphere 3 or 6 mm deep, 8 mm across, 6 times stiffer, with
    little noise: the posterior's mode is that sphere. With the model's error taken relative to each
    sphere's own prediction, a sphere predicting less than was measured fitted better (6 mm deep read as a
    sphere 3 times stiffer, 9 mm across, 5.25 mm deep)."""
    model = DepthModel(library, SHAPE, PITCH, 0.0)
    thickness, y = 0.026, SHAPE[1] * PITCH / 2
    fine = model._fine(model.predict(thickness, 2e-3, y))
    j, k = int(np.argmin(np.abs(model.diameters - 8e-3))), int(np.argmin(np.abs(model.ratios - 6.0)))
    for depth in (3e-3, 6e-3):
        i = int(np.argmin(np.abs(model.depths - depth)))
        rows, measured, tumour = _one_area(fine[i, j, k], 0.002, thickness, 0.030, y, 0.032)
        log_post, _ = model._posterior(tumour, rows, measured, np.array([1.0]))
        assert np.unravel_index(int(np.argmax(log_post)), log_post.shape) == (0, i, j, k)


def _whole_covariance(model, terms, mode):
    """The Gaussian's whole covariance of the areas' level groups ``terms``, flattened area by area, group by
    group, element by element, and the residuals on the grid: D, the shared error of each element's levels,
    and the scale error on what the sphere at ``mode`` predicts."""
    diagonal, shared, p, residual = [], [], [], []
    size = sum(len(area[0][0]) * len(area) for area in terms)
    start = 0
    for area in terms:
        groups, elements = len(area), len(area[0][0])
        for measured, own, _, predicted in area:
            pm = predicted[mode]
            diagonal.append(own**2 + groups * ((model.model_error * pm) ** 2 + model.contrast_floor**2))
            p.append(pm)
            residual.append(measured - predicted)
        for e in range(elements):
            vector = np.zeros(size)
            for b, (_, _, u, _) in enumerate(area):
                vector[start + b * elements + e] = u[e]
            shared.append(vector)
        start += groups * elements
    p = np.concatenate(p)
    covariance = np.diag(np.concatenate(diagonal)) + sum(np.outer(v, v) for v in shared)
    return covariance, p, np.concatenate(residual, axis=-1)


def _areas(rng):
    """Three areas' level groups: (measured, own error, shared error, predicted on a small grid) each."""
    out = []
    for n, groups in ((5, 2), (4, 2), (7, 1)):
        out.append([(rng.normal(0.2, 0.1, n), rng.uniform(0.01, 0.05, n), rng.uniform(0.0, 0.05, n),
                     rng.normal(0.2, 0.1, (3, 2, 2, n))) for _ in range(groups)])
    return out


def test_the_likelihood_is_the_gaussian_with_the_whole_covariance_of_the_errors(library):
    """The likelihood with each element's levels sharing part of their error, and a scale error shared by every
    element, group and area (Sherman-Morrison twice) is the Gaussian one with the whole covariance, up to a
    constant the spheres share."""
    model = DepthModel(library, SHAPE, PITCH, 0.0, params=DepthParams(0.25, 0.3))
    terms = _areas(np.random.default_rng(3))
    mode = (1, 0, 1)
    covariance, p, residual = _whole_covariance(model, terms, mode)
    inverse = np.linalg.inv(covariance + 0.3**2 * np.outer(p, p))
    whole = -0.5 * np.einsum("...i,ij,...j->...", residual, inverse, residual)
    got = model._log_like(terms, mode)
    np.testing.assert_allclose(got - got[mode], whole - whole[mode], rtol=1e-9, atol=1e-9)


def test_the_first_pass_is_the_gaussian_with_each_spheres_own_covariance(library):
    """Each sphere's own likelihood (its own prediction setting the model's error, no scale error) is the
    Gaussian's, its determinant included, with the levels' shared error."""
    model = DepthModel(library, SHAPE, PITCH, 0.0)
    terms = _areas(np.random.default_rng(5))
    got = model._own_log_like(terms)
    for index in np.ndindex(got.shape):
        covariance, _, residual = _whole_covariance(model, terms, index)
        r = residual[index]
        want = -0.5 * (r @ np.linalg.solve(covariance, r) + np.linalg.slogdet(covariance)[1])
        assert got[index] == pytest.approx(want, rel=1e-9, abs=1e-9)


def test_an_error_every_level_shares_does_not_average_away():
    """Ten levels that share all their error know the element's contrast no better than one does; ten that
    share none know it three times better."""
    contrast, sigma = np.full((10, 3), 0.1), np.full((10, 3), 0.04)
    _, own, shared, weights = _level_mean(contrast, sigma, 0.0)
    assert np.allclose(own, 0.04 / np.sqrt(10)) and np.allclose(shared, 0.0) and np.allclose(weights, 0.1)
    _, own, shared, _ = _level_mean(contrast, sigma, 0.95)
    assert np.allclose(np.hypot(own, shared), 0.04 * np.sqrt(0.95 + 0.05 / 10))


def test_how_much_of_its_error_an_element_shares_between_levels_is_read_from_the_healthy_tissue():
    """Contrasts made of an element's offset kept through its area's ramp (a share rho of the variance) and
    an error of each level: the correlation of consecutive levels comes back as rho, and a tumour's elements,
    far from homogeneous tissue, do not count."""
    rng = np.random.default_rng(11)
    regions, per_region, shape = 40, 6, (4, 15)
    for rho in (0.0, 0.5, 0.8):
        kept = rng.normal(0, 1, (regions, 1, *shape))
        z = np.sqrt(rho) * kept + np.sqrt(1 - rho) * rng.normal(0, 1, (regions, per_region, *shape))
        z = z.reshape(-1, *shape)
        z[:per_region, 1:3, 5:8] += 8.0  # a tumour under the first area
        levels = np.zeros(len(z), dtype=[("region", "i4")])
        levels["region"] = np.repeat(np.arange(regions), per_region)
        sigma = np.full(z.shape, 0.03)
        measured = level_correlation(levels, SimpleNamespace(contrast=0.03 * z, sigma=sigma))
        assert measured == pytest.approx(rho, abs=0.05)


def test_deeper_tumours_read_deeper(library):
    model = DepthModel(library, SHAPE, PITCH, 0.0)
    thickness, y = 0.026, SHAPE[1] * PITCH / 2 + 1e-3
    found = []
    depths = [list(library.depth_m).index(v) for v in (2.5e-3, 6e-3, 10e-3)]
    middle = list(library.diameter_m).index(8.5e-3)
    for d in depths:  # 8.5 mm across, 6 times stiffer
        truth = model.predict(thickness, -2e-3, y)[d, middle, 1]
        rows, measured, tumour = _one_area(truth, 0.02, thickness, 0.030, y, 0.028)
        found.append(model.estimate(tumour, rows, measured))
    assert found[0][0] < found[1][0] < found[2][0]
    for (estimate, low, high), d in zip(found, depths):
        assert low <= library.depth_m[d] <= high and low <= estimate <= high


def test_no_estimate_without_an_area_over_the_tumour(library):
    model = DepthModel(library, SHAPE, PITCH, 0.0)
    rows, measured, tumour = _one_area(np.zeros(SHAPE), 0.02, 0.025, 0.030, 0.015, 0.040)  # face 10 mm away
    assert all(math.isnan(v) for v in model.estimate(tumour, rows, measured))


def test_the_library_builder_writes_what_the_loader_reads(tmp_path):
    grid = LibraryGrid(thickness_m=(0.006, 0.008), depth_m=(1e-3, 2e-3), diameter_m=(2e-3, 3e-3),
                       modulus_ratio=(3.0, 6.0), offset_x_m=(4e-3,), length_m=0.016)
    lib = load_library(build_library(tmp_path / "small.npz", grid))
    assert lib.inclusion.shape[:5] == (2, 2, 2, 2, 1)
    assert np.isfinite(lib.inclusion[1, 0, 0, 0]).all()


def test_a_tumour_in_the_gap_between_two_areas_is_read_from_the_nearer_one(library):
    """Areas laid evenly along a tissue leave gaps of a few tenths of a millimetre: a tumour fitted 4.2 mm
    from the nearest face's centre (0.2 mm outside it) is read at the library's farthest offset, 4 mm,
    rather than left without an estimate; 1 mm outside it, it is not read at all."""
    model = DepthModel(library, SHAPE, PITCH, 0.0)
    thickness, y = 0.026, SHAPE[1] * PITCH / 2
    depth = 4e-3  # 8.5 mm across, 6 times stiffer
    entry = (list(library.depth_m).index(depth), list(library.diameter_m).index(8.5e-3), 1)
    seen = model.predict(thickness, 4e-3, y)[entry]
    rows, measured, tumour = _one_area(seen, 0.02, thickness, 0.030, y, 0.0342)
    estimate, low, high = model.estimate(tumour, rows, measured)
    assert low <= depth <= high and low <= estimate <= high
    rows, measured, tumour = _one_area(seen, 0.02, thickness, 0.030, y, 0.035)
    assert all(math.isnan(v) for v in model.estimate(tumour, rows, measured))


def test_the_signature_carries_a_spheres_far_field_to_the_tissues_far_side(library):
    """A stiff sphere 11 mm from one side of a 27 mm layer, 1.5 mm deep, 9 mm across, 5 times stiffer (an
    independent solve of the face over it): it lowers the near side's elements and raises the far side's
    (by 0.03 here, without a cover).
    The library's mid-array signature shifted sideways knows no side and puts both at about zero; the
    signature solved where the sphere lies gives them within 0.02."""
    thickness, tumour_y = 0.027, 11e-3
    grid = replace(LibraryGrid(), offset_x_m=(0.0,))
    model = DepthModel(library, SHAPE, PITCH, 0.0)
    q = model._elements(_block_solve(grid, thickness, (1.5e-3, 9e-3, 5.0), tumour_y_m=tumour_y)[0]) / model._elements(
        _block_solve(grid, thickness, None)[0])
    truth = q / np.median(q) - 1.0
    assert truth[:, -1].mean() > 0.02 and truth[:, 0].mean() < -0.02
    rows, measured, tumour = _one_area(truth, 0.01, thickness, 0.030, tumour_y, 0.030)
    made, error = model.signature(tumour, rows, measured, np.array([0]))
    np.testing.assert_allclose(made[0][:, [0, -1]], truth[:, [0, -1]], atol=0.02)
    assert np.all(error >= 0) and error[0].max() > 0.1  # the model's error, largest over the sphere
    nearest = (list(library.depth_m).index(2.5e-3), list(library.diameter_m).index(8.5e-3), 1)  # 6x
    shifted = model.predict(thickness, 0.0, tumour_y)[nearest]  # the nearest library entry
    assert abs(shifted[:, -1].mean()) < 0.02
    # a face beyond the sphere's reach feels nothing of it, whether or not the tumour has a fit
    far = SimpleNamespace(x_m=0.030 + 13e-3, y_m=tumour_y)
    made, error = model.signature(far, rows, SimpleNamespace(contrast=np.full_like(measured.contrast, np.nan),
                                                             sigma=measured.sigma), np.array([0]))
    assert not made.any() and not error.any()


def test_a_spheres_solve_is_kept_for_the_next_analysis_and_a_damaged_one_solved_again(tmp_path, monkeypatch):
    import session.depth as depth_model
    from tissue.mechanics import cache as cache_mod

    monkeypatch.setenv(cache_mod.ENV_VAR, str(tmp_path))
    grid = replace(LibraryGrid(), offset_x_m=(0.0, 1e-3))
    solved = []

    def solve(grid, thickness_m, inclusion, tumour_y_m, store=None, sides="free"):  # checked against the library
        solved.append((thickness_m, inclusion, tumour_y_m, sides))
        return np.full((2, 9, 31), thickness_m + sum(inclusion) + tumour_y_m)

    monkeypatch.setattr(depth_model, "_block_solve", solve)
    first = _kept_block_solve(grid, 0.005, (1e-3, 2e-3, 5.0), 0.015)
    assert np.array_equal(_kept_block_solve(grid, 0.005, (1e-3, 2e-3, 5.0), 0.015), first)
    assert solved == [(0.005, (1e-3, 2e-3, 5.0), 0.015, "free")]
    _kept_block_solve(grid, 0.005, (1e-3, 2e-3, 6.0), 0.015)  # another sphere is another solve
    _kept_block_solve(grid, 0.005, (1e-3, 2e-3, 5.0), 0.015, sides="mould")  # and so is a mould's
    assert solved[1:] == [(0.005, (1e-3, 2e-3, 6.0), 0.015, "free"), (0.005, (1e-3, 2e-3, 5.0), 0.015, "mould")]
    for entry in tmp_path.iterdir():
        entry.write_bytes(entry.read_bytes()[:-7])
    assert np.array_equal(_kept_block_solve(grid, 0.005, (1e-3, 2e-3, 5.0), 0.015), first) and len(solved) == 4


def test_a_sphere_the_library_cannot_tell_from_one_solved_already_shares_its_solve(library, monkeypatch):
    """The fits' sweeps move a deep tumour's best sphere along the ridge of spheres that explain it alike: one
    a quarter of a millimetre deeper is not solved again at a model error of 0.25 (twins differ by less than
    half of it; at the default 0.10 the library tells these two apart), and what the two differ by is told with
    it; a sphere the library tells apart (a shallow one) is solved."""
    import session.depth as depth_model

    solved = []

    def solve(grid, thickness_m, inclusion, tumour_y_m=None, solving=None, store=None, sides="free"):
        solved.append(inclusion)
        return np.full(grid.face_shape, 1.0 + (0.0 if inclusion is None else inclusion[0]))

    monkeypatch.setattr(depth_model, "_kept_block_solve", solve)
    model = DepthModel(library, SHAPE, PITCH, 0.0).with_params(DepthParams(model_error=0.25))
    first, own = model._solved(0.027, 6e-3, 10e-3, 6.0, 0.0, 12e-3)
    spheres = len(solved)  # the sphere and its layer without it
    twin, apart = model._solved(0.027, 6.25e-3, 10e-3, 6.0, 0.0, 12e-3)
    assert own == 0.0 and 0.0 < apart <= depth_model.TWIN_SHARE * model.model_error
    assert len(solved) == spheres and np.array_equal(twin, first)
    _, own = model._solved(0.027, 1e-3, 10e-3, 6.0, 0.0, 12e-3)
    assert own == 0.0 and len(solved) == spheres + 1
