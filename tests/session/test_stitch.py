"""Stitching: placement by pose, overlaps averaged, coverage, one map per level, re-analysis parameters."""

from __future__ import annotations

import numpy as np
import pytest

from session.format import LEVEL_DTYPE, level_row
from session.reader import open_session
from session.stitch import (
    L0Source,
    StitchError,
    StitchParams,
    level_groups,
    recompute_stiffness,
    stitch,
    stitch_session,
)
from session.synthetic import level_record

PITCH = 2e-3
AREA = PITCH * PITCH


def levels_of(*records) -> np.ndarray:
    return np.array([level_row(r) for r in records], LEVEL_DTYPE)


def uniform(region: int, force_N: float, xy, pressure_pa: float):
    record = level_record(region, 0, force_N, xy)
    levels = levels_of(record)
    levels["pressure_pa"] = pressure_pa
    return levels


def test_elements_land_where_the_pose_puts_them():
    levels = levels_of(level_record(0, 0, 1.0, (0.010, 0.021)))  # element edges on the 2 mm grid
    levels["pressure_pa"] = np.arange(60, dtype=float).reshape(4, 15)
    result = stitch(levels, PITCH, AREA, StitchParams(cell_m=PITCH))
    g = result.grid
    assert (g.x0_m, g.y0_m, g.nx, g.ny) == pytest.approx((0.006, 0.006, 4, 15))
    assert np.allclose(result.levels[0].pressure_pa, levels["pressure_pa"][0], rtol=1e-12)  # rows = x, cols = y
    assert np.all(result.levels[0].coverage == pytest.approx(1.0))
    # the element at row 3 (largest x), column 0 (smallest y)
    assert result.levels[0].pressure_pa[g.cell_of(0.013, 0.0065)] == 45.0


def test_a_pose_off_the_grid_shares_each_element_between_two_cells():
    levels = levels_of(level_record(0, 0, 1.0, (0.010, 0.020)))  # elements from y = 5 mm, cells from 4 mm
    levels["pressure_pa"] = np.arange(60, dtype=float).reshape(4, 15)
    result = stitch(levels, PITCH, AREA, StitchParams(cell_m=PITCH))
    g = result.grid
    assert (g.y0_m, g.ny) == pytest.approx((0.004, 16))
    lm = result.levels[0]
    assert lm.coverage[0, 0] == pytest.approx(0.5) and lm.coverage[0, 1] == pytest.approx(1.0)
    assert lm.pressure_pa[0, 0] == 0.0 and lm.pressure_pa[0, 1] == pytest.approx(0.5)


def test_smaller_cells_repeat_the_element_and_anchor_at_the_origin():
    levels = levels_of(level_record(0, 0, 1.0, (0.0105, 0.020)))  # a pose off the 2 mm grid
    levels["pressure_pa"] = np.arange(60, dtype=float).reshape(4, 15)
    result = stitch(levels, PITCH, AREA, StitchParams(cell_m=0.5e-3))
    g = result.grid
    assert g.x0_m == pytest.approx(0.0065) and g.x0_m / 0.5e-3 == pytest.approx(round(g.x0_m / 0.5e-3))
    p = result.levels[0].pressure_pa
    assert p[g.cell_of(0.00660, 0.0051)] == 0.0 and p[g.cell_of(0.00840, 0.0069)] == 0.0  # 4x4 cells of element 0
    assert p[g.cell_of(0.00860, 0.0051)] == 15.0  # next element along x


def test_overlaps_are_averaged_and_counted_in_the_coverage():
    a = uniform(0, 1.0, (0.010, 0.015), 1000.0)
    b = uniform(1, 1.0, (0.014, 0.015), 3000.0)  # 4 mm further along x: half of the TSI overlaps
    result = stitch(np.concatenate([a, b]), PITCH, AREA, StitchParams(cell_m=1e-3))
    lm = result.levels[0]
    g = result.grid
    assert lm.pressure_pa[g.cell_of(0.0075, 0.015)] == pytest.approx(1000.0)
    assert lm.pressure_pa[g.cell_of(0.0125, 0.015)] == pytest.approx(2000.0)
    assert lm.pressure_pa[g.cell_of(0.0165, 0.015)] == pytest.approx(3000.0)
    assert lm.coverage[g.cell_of(0.0125, 0.015)] == pytest.approx(2.0)
    assert lm.coverage[g.cell_of(0.0075, 0.015)] == pytest.approx(1.0)
    assert g.extent_m[:2] == pytest.approx((0.006, 0.018))


def test_partial_overlap_weights_by_area():
    a = uniform(0, 1.0, (0.010, 0.015), 1000.0)
    b = uniform(1, 1.0, (0.0105, 0.015), 3000.0)  # shifted by a quarter element
    result = stitch(np.concatenate([a, b]), PITCH, AREA, StitchParams(cell_m=2e-3))
    lm = result.levels[0]
    cell = result.grid.cell_of(0.0070, 0.015)  # [6, 8) mm: 2 mm of a, 1.5 mm of b
    assert lm.coverage[cell] == pytest.approx(1.75)
    assert lm.pressure_pa[cell] == pytest.approx((2 * 1000 + 1.5 * 3000) / 3.5)


def test_gaps_have_no_value_and_no_coverage():
    a = uniform(0, 1.0, (0.010, 0.015), 1000.0)
    b = uniform(1, 1.0, (0.030, 0.015), 1000.0)
    lm = stitch(np.concatenate([a, b]), PITCH, AREA).levels[0]
    g = stitch(np.concatenate([a, b]), PITCH, AREA).grid
    assert np.isnan(lm.pressure_pa[g.cell_of(0.020, 0.015)]) and lm.coverage[g.cell_of(0.020, 0.015)] == 0.0


def test_elements_without_a_value_count_as_palpated_but_not_averaged():
    a = uniform(0, 1.0, (0.010, 0.015), 1000.0)
    b = uniform(1, 1.0, (0.010, 0.015), 3000.0)
    b["stiffness_pa"] = np.nan
    b["dL_m"] = np.nan  # no contact under b: Eq. 1 has nothing to say there
    levels = np.concatenate([a, b])
    lm = stitch(levels, PITCH, AREA, StitchParams(cell_m=PITCH)).levels[0]
    assert np.allclose(lm.stiffness_pa, recompute_stiffness(levels, AREA, StitchParams(), 0.2e-3)[0])
    assert np.allclose(lm.coverage, 2.0)


def test_one_map_per_force_level_lowest_first():
    records = [level_record(r, k, f, (0.004 + 0.008 * r, 0.015)) for r in range(3) for k, f in enumerate((1, 2, 3))]
    records.append(level_record(3, 0, 1.0004, (0.028, 0.015)))  # same level to within a mN
    levels = levels_of(*records)
    assert [(f, list(rows)) for f, rows in level_groups(levels)] == [
        (1.0, [0, 3, 6, 9]), (2.0, [1, 4, 7]), (3.0, [2, 5, 8])]
    result = stitch(levels, PITCH, AREA)
    assert result.level_forces_N() == [1.0, 2.0, 3.0]
    assert [len(lm.records) for lm in result.levels] == [4, 3, 3]
    assert result.levels[1].tsi_indentation_m == pytest.approx(levels["indentation_m"][[1, 4, 7]].mean())
    assert result.covered_fraction(0) == pytest.approx(1.0) and result.covered_fraction() == pytest.approx(0.75)


def test_coverage_is_of_the_tissue_where_its_size_is_known_not_of_what_was_palpated():
    # issue 13: 2 of the 9 areas of a 72 x 30 mm phantom palpated read "100 % of the grid covered"
    levels = levels_of(*[level_record(r, 0, 1.0, (0.004 + 0.008 * r, 0.015)) for r in range(2)])
    result = stitch(levels, PITCH, AREA, StitchParams(cell_m=1e-3))
    assert result.covered_fraction() == pytest.approx(1.0)  # of the palpated extent
    tissue = (0.0, 0.072, 0.0, 0.030)
    assert result.covered_fraction(extent_m=tissue) == pytest.approx(2 / 9)
    assert result.coverage_text(tissue) == "22 % of the tissue (72 x 30 mm) covered"
    assert "palpated extent" in result.coverage_text(None) and "not recorded" in result.coverage_text(None)


def test_l0_sources():
    record = level_record(0, 0, 2.0, (0.01, 0.015))
    levels = levels_of(record)
    levels["L0_m"][0, 0, :] = 0.020  # the first row of elements found the surface 5 mm lower
    element = recompute_stiffness(levels, AREA, StitchParams(l0_source="element"), 0.2e-3)[0]
    assert np.allclose(element[1:], record.stiffness_pa[1:]) and np.allclose(element[0], record.stiffness_pa[0] * 0.8)
    region = recompute_stiffness(levels, AREA, StitchParams(l0_source=L0Source.REGION), 0.2e-3)[0]
    assert np.allclose(region, record.stiffness_pa * (0.025 * 3 + 0.020) / 4 / 0.025)
    fixed = recompute_stiffness(levels, AREA, StitchParams(l0_source="fixed", l0_fixed_m=0.05), 0.2e-3)[0]
    assert np.allclose(fixed, record.stiffness_pa * 2.0)
    # below the minimum indentation Eq. 1 is not evaluated
    shallow = recompute_stiffness(levels, AREA, StitchParams(min_indentation_m=1.0), 0.2e-3)[0]
    assert np.isnan(shallow).all()


def test_the_recorded_stiffness_is_what_eq_1_gives(recorded):
    with open_session(recorded[0]) as s:
        result = stitch_session(s, StitchParams())
        recorded_E = s.levels["stiffness_pa"]
        assert np.array_equal(np.isnan(result.stiffness_pa), np.isnan(recorded_E))
        assert np.allclose(result.stiffness_pa, recorded_E, equal_nan=True, rtol=1e-12)
        assert result.level_forces_N() == [0.5, 1.0, 1.5]
        coarse = stitch_session(s, StitchParams(cell_m=4e-3))
        assert coarse.grid.cell_m == 4e-3 and coarse.grid.nx < result.grid.nx


@pytest.mark.parametrize("kwargs, message", [
    ({"cell_m": 0.0}, "cell size must be between 0.1 and 20 mm, got 0 mm"),
    ({"cell_m": 0.05}, "cell size"),
    ({"l0_source": "fixed"}, "L0 source 'fixed' needs a tissue thickness"),
    ({"l0_source": "fixed", "l0_fixed_m": -1.0}, "needs a tissue thickness > 0"),
    ({"l0_source": "guess"}, "unknown L0 source 'guess' (known: element, region, fixed)"),
    ({"min_indentation_m": 0.0}, "minimum indentation must be > 0"),
])
def test_bad_parameters_are_named(kwargs, message):
    with pytest.raises(StitchError) as info:
        StitchParams(**kwargs)
    assert message in str(info.value)


def test_no_levels_no_maps():
    result = stitch(np.empty(0, LEVEL_DTYPE), PITCH, AREA)
    assert result.levels == [] and result.covered_fraction() == 0.0
