"""The rebuilt physics of the flat field at finite strain: tissue that stands higher under the face is pressed
further, and stiffens more than linear elasticity says."""

from __future__ import annotations

import numpy as np
import pytest

from session.physics import (
    SIDES,
    BlockResponse,
    _block_compliance,
    _block_stiffening,
    measured_surface,
    supported_sides,
)
from session.synthetic import level_record
from tests.session.test_stitch import levels_of
from tissue.mechanics.model import FiniteStrain

PITCH = 2e-3
BASE_M, RIDGE_M = 0.020, 0.023
RIDGE = slice(6, 9)  # a 6 mm ridge along the face, under its middle columns


def ridge_levels(face_heights_m):
    records = []
    for k, z in enumerate(face_heights_m):
        levels = levels_of(level_record(0, k, 1.0 + k, (0.004, 0.015), thickness_m=BASE_M))
        levels["tsi_position_m"][0, 2] = z
        onset = np.full((4, 15), BASE_M)
        onset[:, RIDGE] = RIDGE_M
        levels["onset_height_m"] = onset
        levels["dL_m"] = onset - z
        records.append(levels)
    return np.concatenate(records)


def test_a_ridge_pressed_further_carries_more_at_finite_strain(tmp_path):
    levels = ridge_levels((0.019, 0.017))
    block, origin = measured_surface(levels, PITCH, 0.0)
    compliance, nodes = _block_compliance(block, tmp_path)
    # every element alike, so that only the strain differs between the ridge and the base
    finite = FiniteStrain(np.stack([np.full(60, 0.5), np.full(60, 1.0)]), (0.5, 1.0))
    nonlinear = BlockResponse(block, origin, compliance, nodes, 0.0, PITCH, (4, 15), finite, 0.0)
    linear = BlockResponse(block, origin, compliance, nodes, 0.0, PITCH, (4, 15))
    ratio = nonlinear.pattern(levels).share / linear.pattern(levels).share
    ridge_over_base = ratio[:, 1:3, 7].mean(axis=1) / ratio[:, 1:3, 2].mean(axis=1)
    z = levels["tsi_position_m"][:, 2]
    expected = np.array([finite.scale(np.full(60, (RIDGE_M - h) / RIDGE_M))[0]
                         / finite.scale(np.full(60, (BASE_M - h) / BASE_M))[0] for h in z])
    # the ridge's strain (23 - z) / 23 runs ahead of the base's (20 - z) / 20: 5 to 10 % more load on it
    np.testing.assert_allclose(ridge_over_base, expected, rtol=0.02)
    assert np.all(expected > 1.04)
    assert "finite strain" in nonlinear.description and "finite strain" not in linear.description


def test_on_a_flat_surface_the_level_baseline_keeps_the_face_pattern_finite_strain_gives(tmp_path):
    # the face's edge rows stiffen faster than its inner rows; on a flat surface every area of a level shows
    # that alike, and the flat field's baseline measures it, so the physics leaves the pattern linear there
    levels = ridge_levels((0.019, 0.017))
    levels["onset_height_m"] = BASE_M
    levels["dL_m"] = BASE_M - levels["tsi_position_m"][:, 2][:, None, None]
    block, origin = measured_surface(levels, PITCH, 0.0)
    compliance, nodes = _block_compliance(block, tmp_path)
    a = np.where(np.arange(4)[:, None] % 3 == 0, 0.5, 0.57) * np.ones((4, 15))
    b = np.where(np.arange(4)[:, None] % 3 == 0, 2.5, -1.6) * np.ones((4, 15))
    finite = FiniteStrain(np.stack([a.ravel(), b.ravel()]), (0.5, 1.0))
    nonlinear = BlockResponse(block, origin, compliance, nodes, 0.0, PITCH, (4, 15), finite, 0.0)
    linear = BlockResponse(block, origin, compliance, nodes, 0.0, PITCH, (4, 15))
    np.testing.assert_allclose(nonlinear.pattern(levels).share, linear.pattern(levels).share, rtol=1e-9)


def test_the_rebuilt_surfaces_uncertainty_is_kept_as_modes_shared_between_elements(tmp_path):
    # the ridge's flanks: where the onsets step by 3 mm, the surface within those elements is unsure
    levels = ridge_levels((0.019, 0.017))
    block, origin = measured_surface(levels, PITCH, 0.0)
    compliance, nodes = _block_compliance(block, tmp_path)
    pattern = BlockResponse(block, origin, compliance, nodes, 0.0, PITCH, (4, 15)).pattern(levels)
    modes = pattern.modes
    assert modes.shape[0] == 2 and modes.shape[1] >= 8 and modes.shape[2:] == (4, 15)
    # a surface a little higher under one flank element loads it more and its neighbours less
    flank = np.abs(modes[:, :, :, [5, 6, 8, 9]]).max(axis=(1, 2, 3))
    assert np.all(flank > 0.5)
    # only the change of the pattern: the flat field fits each record's scale itself (the median)
    pressing = np.isfinite(pattern.share)[:, None] & (np.abs(modes).sum(axis=(2, 3)) > 0)[..., None, None]
    medians = np.nanmedian(np.where(pressing, modes, np.nan).reshape(*modes.shape[:2], -1), axis=2)
    np.testing.assert_allclose(medians[np.isfinite(medians)], 0.0, atol=1e-9)
    # and their part of each element's uncertainty is within it
    own = pattern.sigma ** 2 - (modes ** 2).sum(axis=1)
    assert np.all(own[np.isfinite(own)] >= -1e-12)


def test_the_sink_in_the_rebuild_adds_is_itself_an_uncertainty_shared_between_elements(tmp_path, monkeypatch):
    # The base beside the ridge touched only once the ridge had sunk it in; the rebuild adds back what the
    # block's linear response says (1.5 mm beside this 3 mm ridge), which next to a ridge pressed far was
    # 1.6 times what the simulated tissue did, and the base then reads tilted. How much it added is a mode
    # of the pattern's uncertainty: the base's elements are less sure the more was added.
    import session.physics

    levels = ridge_levels((0.019, 0.017))
    block, origin = measured_surface(levels, PITCH, 0.0)
    compliance, nodes = _block_compliance(block, tmp_path)
    _, sink_in = BlockResponse(block, origin, compliance, nodes, 0.0, PITCH, (4, 15))._surfaces(levels)
    assert sink_in[0][:, 5].min() > 1e-3 and np.all(sink_in[0][:, RIDGE] == 0.0)
    sure = {}
    for error in (0.0, session.physics.SINK_IN_ERROR):
        monkeypatch.setattr(session.physics, "SINK_IN_ERROR", error)
        # a block of its own each time: a block keeps the last pattern it made of the same levels
        sure[error] = BlockResponse(block, origin, compliance, nodes, 0.0, PITCH, (4, 15)).pattern(levels).sigma
    unsure = sure[session.physics.SINK_IN_ERROR] ** 2 - sure[0.0] ** 2
    beside, next_over = unsure[:, 1:3, 4], unsure[:, 1:3, 3]
    # at least a twentieth more spread beside the ridge, more the more was added (the nearer the ridge),
    # less the deeper the face pressed the base past its sink-in
    assert np.all(next_over > 0.05 ** 2) and np.all(beside > 2 * next_over)
    assert np.all(unsure[0, 1:3, 3:5] > unsure[1, 1:3, 3:5])
    assert np.all(unsure[np.isfinite(unsure)] >= -1e-12)


def test_where_the_tissue_ends_is_not_known_it_may_go_on_by_another_area(tmp_path):
    # Five flat areas side by side along x: the first and the last are at the block's ends. The live maps
    # without a plan do not know whether the tissue ends there (the newest area is where the operator has
    # got to), and taken to end there, the newest area's far edge read as a tumour.
    records = []
    for region, x in enumerate((0.004, 0.012, 0.020, 0.028, 0.036)):
        levels = levels_of(level_record(region, 0, 1.0, (x, 0.015), thickness_m=BASE_M))
        levels["tsi_position_m"][0, 2] = 0.019
        levels["onset_height_m"] = BASE_M
        levels["dL_m"] = BASE_M - 0.019
        records.append(levels)
    levels = np.concatenate(records)
    block, origin = measured_surface(levels, PITCH, 0.0)
    compliance, nodes = _block_compliance(block, tmp_path)
    known, unknown = (BlockResponse(block, origin, compliance, nodes, 0.0, PITCH, (4, 15), ends_known=ends)
                      for ends in (True, False))
    sure, unsure = known.pattern(levels), unknown.pattern(levels)
    np.testing.assert_allclose(unsure.share, sure.share)
    # the middle area is two areas from either end: nothing to doubt, nor where the face spans the width
    assert not sure.modes[2].any() and not unsure.modes[2].any()
    # the face an area short of an end feels where the tissue ends only if it is not known: by several %
    assert not sure.modes[[1, 3]].any()
    assert 0.03 < np.abs(unsure.modes[1]).max() < 0.5 and 0.03 < np.abs(unsure.modes[3]).max() < 0.5
    for end, row in ((0, 0), (4, 3)):  # each end area's row over the block's end
        # a millimetre more of tissue changes the end row's share by over half; another area's length, by
        # several times, and the whole face's by a fifth and more
        assert np.abs(sure.modes[end][:, row]).max() > 0.5
        assert np.all(np.abs(unsure.modes[end]).max(axis=(0, 2)) > 0.2)
        assert np.abs(unsure.modes[end][:, row]).max() > 4 * np.abs(sure.modes[end][:, row]).max()
    assert "where the tissue ends not known" in unknown.description
    assert "not known" not in known.description


def test_a_block_solved_before_answers_another_surface_of_its_extent_and_refuses_other_areas(tmp_path):
    levels = ridge_levels((0.019, 0.017))
    block, origin = measured_surface(levels, PITCH, 0.0)
    compliance, nodes = _block_compliance(block, tmp_path)
    solved = BlockResponse(block, origin, compliance, nodes, 0.0, PITCH, (4, 15))
    same = solved.on_surface_of(levels)
    assert same.description == solved.description  # its own surface: the block solved, exactly
    np.testing.assert_array_equal(same.pattern(levels).share, solved.pattern(levels).share)

    flat = levels.copy()
    flat["onset_height_m"] = BASE_M
    flat["dL_m"] = BASE_M - flat["tsi_position_m"][:, 2][:, None, None]
    on_flat = solved.on_surface_of(flat)
    assert on_flat.block.heights_m.max() < RIDGE_M - 1e-3 and "meshed on the 8 x 30 mm block" in on_flat.description
    ridge = solved.pattern(levels).share[:, 1:3, RIDGE].mean() / solved.pattern(levels).share[:, 1:3, 2].mean()
    level = on_flat.pattern(flat).share[:, 1:3, RIDGE].mean() / on_flat.pattern(flat).share[:, 1:3, 2].mean()
    assert ridge > 1.5 * level  # the contact is the new surface's: the ridge's load is gone

    elsewhere = levels.copy()
    elsewhere["tsi_position_m"][:, 0] += 0.004
    with pytest.raises(ValueError, match="reach beyond the 8 x 30 mm block"):
        solved.on_surface_of(elsewhere)


def five_flat_areas(thickness_m: float, face_heights_m: tuple[float, float]) -> np.ndarray:
    """Five flat areas along a 40 mm block of ``thickness_m``, each pressed to the two face heights."""
    records = []
    for k, z in enumerate(face_heights_m):
        for region, x in enumerate((0.004, 0.012, 0.020, 0.028, 0.036)):
            levels = levels_of(level_record(region, k, 1.0 + k, (x, 0.015), thickness_m=thickness_m))
            levels["tsi_position_m"][0, 2] = z
            levels["onset_height_m"] = thickness_m
            levels["dL_m"] = thickness_m - z
            records.append(levels)
    return np.concatenate(records)


@pytest.mark.parametrize("truth", SIDES)
def test_the_rebuilt_block_takes_the_sides_under_which_the_session_reads_most_alike(tmp_path, truth):
    # Five flat areas pressed at two levels, read through an array whose elements' gains spread by 5 %: the
    # areas' tissue is homogeneous, its sides held in a mould or free.
    levels = five_flat_areas(BASE_M, (0.019, 0.018))
    block, origin = measured_surface(levels, PITCH, 0.0)
    blocks = [BlockResponse(block, origin, *_block_compliance(block, tmp_path, sides=sides), 0.0, PITCH, (4, 15),
                            sides=sides) for sides in SIDES]
    free, held = (b.pattern(levels).share for b in blocks)
    # held by the mould's walls, the end areas' rows over the block's ends carry more than free ones
    assert held[0, 0].mean() > 1.1 * free[0, 0].mean() and held[4, 3].mean() > 1.1 * free[4, 3].mean()
    rng = np.random.default_rng(7)
    gain = np.exp(0.05 * rng.standard_normal((4, 15)))
    levels["pressure_pa"] = 2e3 * (1.0 + levels["level"])[:, None, None] * (held if truth == "mould" else free) * gain
    chosen = supported_sides(levels, blocks)
    assert chosen.sides == truth
    assert f"sides {truth}: the areas' stiffness contrast scatters" in chosen.description
    assert ("held in a mould" in chosen.description) == (truth == "mould")
    if truth == "mould":  # a block told on linear patterns is solved at finite strain, what was said of it kept
        final = chosen.at_finite_strain(tmp_path)
        assert final.sides == "mould" and final.finite_strain is not None and chosen.finite_strain is None
        assert "finite strain" in final.description and chosen.sides_why in final.description


@pytest.mark.parametrize("rough_m", [0.0, 2e-5, 3e-4])
def test_the_faces_contact_meets_the_contact_conditions(tmp_path, rough_m):
    # a flat face on a rough surface: from every node touching (rough 0) to a few peaks carrying it all, so
    # that both ways of solving the nodes in contact are taken (few nodes left out, or most)
    levels = ridge_levels((0.019,))
    block, origin = measured_surface(levels, PITCH, 0.0)
    compliance, nodes = _block_compliance(block, tmp_path)
    tissue = BlockResponse(block, origin, compliance, nodes, 0.0, PITCH, (4, 15))
    face = tissue._face(*(int(np.floor(c)) for c in tissue._face_lo(levels[0])))
    rng = np.random.default_rng(7)
    gap = 1e-4 + rough_m * rng.standard_normal(len(face.nodes))
    gap[:5] = np.nan  # never reaching the face
    f = face.contact(gap)
    pushed = face.compliance @ f
    carrying = f > 0
    scale = np.nanmax(np.abs(gap))
    assert np.all(f >= 0) and not np.any(f[:5])
    np.testing.assert_allclose(pushed[carrying], gap[carrying], atol=1e-9 * scale)  # exactly its gap
    reaching = np.isfinite(gap) & ~carrying
    assert np.all(pushed[reaching] >= gap[reaching] - 1e-9 * scale)  # the rest at or below the face
    assert 0 < carrying.sum() <= len(f) - 5
    if rough_m == 0.0:
        assert carrying.sum() == len(f) - 5
    if rough_m == 3e-4:
        assert carrying.sum() < (len(f) - 5) / 2


@pytest.mark.parametrize("stated, used", [(0.8e-3, 0.8e-3), (float("nan"), 0.0), (-1e-3, 0.0), ("thick", 0.0),
                                          (True, 0.0)])
def test_the_cover_is_the_one_the_calibration_states_and_a_value_that_is_no_spread_states_none(stated, used):
    """issue 48: the analysis takes the array's cover from its calibration, never from the simulated array's
    actual one, and a crafted file's cover cannot blur the pattern into NaN."""
    from session.info import SessionInfo
    from session.physics import _cover_of

    info = SessionInfo(config={"sim": {"sensor": {"cover_spread_m": 1.5e-3}}},
                       calibration={"cover_spread_m": stated}, rig={"backend": "sim"})
    assert _cover_of(info) == used


@pytest.fixture(scope="module")
def gripped_or_not(tmp_path_factory):
    """Five flat areas along a 40 mm block 10 mm thick, free sides, pressed at 5 and 10 % strain; the block at
    finite strain with the face frictionless and gripping it."""
    cache = tmp_path_factory.mktemp("grip")
    levels = five_flat_areas(0.010, (0.0095, 0.009))
    block, origin = measured_surface(levels, PITCH, 0.0)
    plain = BlockResponse(block, origin, *_block_compliance(block, cache), 0.0, PITCH, (4, 15),
                          _block_stiffening(block, (4, 15), PITCH, cache))
    return levels, plain, plain.gripped(cache)


@pytest.mark.parametrize("truth", ["frictionless", "gripped"])
def test_the_rebuilt_block_takes_the_face_gripping_it_where_the_session_reads_so(gripped_or_not, truth):
    """issue 48: a face that grips the tissue loads the array's end columns over its free sides far more than a
    frictionless one, and more the harder it presses; which it was, the session's own areas tell."""
    levels, plain, gripped = gripped_or_not
    assert plain.grip is None and gripped.grip is not None and "the face gripping it" in gripped.description
    free, held = (b.pattern(levels).share for b in (plain, gripped))
    ends = (slice(None), slice(1, 3), [0, -1])
    inside = (slice(None), slice(1, 3), slice(4, 11))
    assert (held[ends] / held[inside].mean(axis=(1, 2))[:, None, None]).mean() > \
        1.3 * (free[ends] / free[inside].mean(axis=(1, 2))[:, None, None]).mean()
    rng = np.random.default_rng(11)
    gain = np.exp(0.05 * rng.standard_normal((4, 15)))
    truth_share = held if truth == "gripped" else free
    levels["pressure_pa"] = 2e3 * (1.0 + levels["level"])[:, None, None] * truth_share * gain
    chosen = supported_sides(levels, [plain, gripped])
    assert (chosen.grip is not None) == (truth == "gripped")
    assert ("sides free, gripped:" in chosen.description) == (truth == "gripped")
