"""Tumours: found where they are, from the level they first show at, with the paper's depth rule."""

from __future__ import annotations

import math

import numpy as np
import pytest

from session.detect import DetectError, DetectParams, detect, detect_session, match_ground_truth
from session.reader import open_session
from session.stitch import StitchParams, stitch, stitch_session
from session.synthetic import level_record

from tests.session.test_stitch import AREA, PITCH, levels_of

TUMOUR = (0.020, 0.015)
FORCES = (1.0, 2.0, 3.0, 4.0)


def strip_session(contrast_by_level, tumour=TUMOUR):
    """Three areas along x at each force; the middle one over a stiff spot whose contrast varies by level."""
    records = []
    for r, x in enumerate((0.012, 0.020, 0.028)):
        for k, force in enumerate(FORCES):
            factor = contrast_by_level[k]
            records.append(level_record(r, k, force, (x, 0.015), tumours_xy_m=(tumour,) if factor > 1 else (),
                                        tumour_factor=factor, noise=0.02, seed=100 * r + k))
    return levels_of(*records)


def test_a_spot_present_from_one_level_on_is_a_tumour_first_seen_there():
    levels = strip_session([1.0, 1.6, 1.6, 1.6])
    stitched = stitch(levels, PITCH, AREA, StitchParams(cell_m=1e-3))
    found = detect(stitched, levels, PITCH, "stiffness")
    assert len(found) == 1
    t = found[0]
    assert math.hypot(t.x_m - TUMOUR[0], t.y_m - TUMOUR[1]) < 1e-3
    assert t.first_level_N == 2.0 and t.levels_N == (2.0, 3.0, 4.0) and t.source == "stiffness"
    middle_at_2N = [i for i in range(len(levels)) if levels["region"][i] == 1 and levels["level"][i] == 1][0]
    assert t.depth_m == levels["indentation_m"][middle_at_2N]  # the TSI indentation at the first level
    assert t.peak_rise > 0.4 and t.area_m2 >= 8e-6


def test_a_spot_that_comes_and_goes_is_noise():
    levels = strip_session([1.6, 1.0, 1.0, 1.0])
    stitched = stitch(levels, PITCH, AREA)
    assert detect(stitched, levels, PITCH, "stiffness") == []
    levels = strip_session([1.6, 1.0, 1.6, 1.6])  # only the unbroken run up to the top counts
    found = detect(stitch(levels, PITCH, AREA), levels, PITCH, "stiffness")
    assert [t.first_level_N for t in found] == [3.0]


def test_threshold_and_minimum_area_are_re_analysis_parameters():
    levels = strip_session([1.3, 1.3, 1.3, 1.3])  # a 30 % rise
    stitched = stitch(levels, PITCH, AREA)
    assert len(detect(stitched, levels, PITCH, "stiffness", DetectParams(threshold=0.2))) == 1
    assert detect(stitched, levels, PITCH, "stiffness", DetectParams(threshold=0.4)) == []
    assert detect(stitched, levels, PITCH, "stiffness", DetectParams(min_area_m2=200e-6)) == []


def test_two_tumours_stay_apart_and_come_out_ordered_along_x():
    records = [level_record(r, k, f, (x, 0.015), tumours_xy_m=((0.012, 0.008), (0.028, 0.022)), tumour_factor=1.8,
                            noise=0.02, seed=7 * r + k)
               for r, x in enumerate((0.012, 0.020, 0.028)) for k, f in enumerate(FORCES)]
    levels = levels_of(*records)
    found = detect(stitch(levels, PITCH, AREA), levels, PITCH, "stiffness")
    assert [(round(t.x_m, 3), round(t.y_m, 3)) for t in found] == [(0.012, 0.008), (0.028, 0.022)]


@pytest.mark.parametrize("kwargs, message", [
    ({"threshold": 0.0}, "threshold must be a relative rise within (0, 10]"),
    ({"threshold": float("nan")}, "threshold"),
    ({"min_area_m2": -1.0}, "minimum spot area must be >= 0"),
    ({"merge_radius_m": 0.0}, "merge radius must be > 0"),
])
def test_bad_parameters_are_named(kwargs, message):
    with pytest.raises(DetectError) as info:
        DetectParams(**kwargs)
    assert message in str(info.value)


def test_unknown_map_is_refused():
    levels = strip_session([1.0, 1.0, 1.0, 1.0])
    with pytest.raises(DetectError, match="unknown map 'colour'"):
        detect(stitch(levels, PITCH, AREA), levels, PITCH, "colour")


def test_the_recorded_session_shows_both_palpated_tumours_in_both_maps(recorded):
    with open_session(recorded[0]) as s:
        stitched = stitch_session(s)
        found = detect_session(s, stitched)
        matches, false_positives = match_ground_truth(found, s.ground_truth, stitched=stitched)
    assert false_positives == {"stiffness": 0, "force": 0}
    by = {(m.source, m.truth_index): m for m in matches}
    for source in ("stiffness", "force"):
        for truth in (0, 1):  # under the first and the third area
            m = by[(source, truth)]
            assert m.found and m.palpated and m.error_xy_m < 1.5e-3
            assert m.first_level_N == 0.5
            assert m.depth_estimate_m == pytest.approx(s.levels["indentation_m"][0 if truth == 0 else 6], abs=0.3e-3)
        assert not by[(source, 2)].found and not by[(source, 2)].palpated  # x = 60 mm was never palpated
    stiffness = [t for t in found if t.source == "stiffness"]
    assert all(np.isfinite(t.depth_m) and t.levels_N == (0.5, 1.0, 1.5) for t in stiffness)
