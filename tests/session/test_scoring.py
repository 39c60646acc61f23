"""The study's figures from its cases' results: what was palpated, found and missed, by depth and surface."""

import pytest

from session.scoring import case_failures, score


def _result(name, truths, matches, fps, paper=False, surface="flat"):
    return {"name": name, "paper": paper, "surface": surface, "regions": 3, "regions_done": 3, "truths": truths,
            "matches": matches, "false_positives": {"stiffness": fps, "force": 0}, "tumours": []}


def _match(i, depth, found, error=0.0, rule=None, model=None, low=None, high=None, palpated=True):
    return {"truth_index": i, "source": "stiffness", "depth_m": depth, "found": found, "palpated": palpated,
            "error_xy_m": error if found else None, "depth_estimate_m": rule, "depth_model_m": model,
            "depth_low_m": low, "depth_high_m": high}


def test_scoring_counts_what_was_palpated_bands_by_depth_and_keeps_the_paper_apart():
    truth = {"x_m": 0.0, "y_m": 0.0, "diameter_m": 8e-3, "modulus_ratio": 5.0}
    results = [
        _result("a", [{**truth, "depth_m": 2e-3}, {**truth, "depth_m": 10e-3}],
                [_match(0, 2e-3, True, 1e-3, rule=2.5e-3, model=2.2e-3, low=1e-3, high=3e-3),
                 _match(1, 10e-3, False)], fps=1),
        _result("b", [{**truth, "depth_m": 5e-3}, {**truth, "depth_m": 4e-3}],
                [_match(0, 5e-3, True, 2e-3, rule=2e-3, model=6e-3, low=5.5e-3, high=7e-3),
                 _match(1, 4e-3, False, palpated=False)], fps=0, surface="bumpy"),
        _result("paper-flat", [{**truth, "depth_m": 2e-3}], [_match(0, 2e-3, True, 0.5e-3)], fps=2, paper=True),
    ]
    f = score(results)
    assert f["phantoms"] == 2 and f["tumours"] == 3  # the unpalpated one does not count against anyone
    assert f["sensitivity_pct"] == pytest.approx(200 / 3) and f["sensitivity_le6mm_pct"] == 100.0
    assert f["by_depth"]["0-3mm"] == {"tumours": 1, "found": 1, "sensitivity_pct": 100.0,
                                      "depth_err_rule_median_mm": pytest.approx(0.5),
                                      "depth_err_model_median_mm": pytest.approx(0.2),
                                      "depth_bias_rule_median_mm": pytest.approx(0.5),
                                      "depth_bias_model_median_mm": pytest.approx(0.2),
                                      "depth_interval_coverage_pct": 100.0,
                                      # cases from before the detector's statistic at the truth was recorded
                                      "signal_z_median": None, "signal_over_threshold_pct": None}
    assert f["by_depth"]["3-6mm"]["depth_bias_rule_median_mm"] == pytest.approx(-3.0)  # the rule reads shallow
    assert f["by_depth"]["3-6mm"]["depth_interval_coverage_pct"] == 0.0
    assert f["by_depth"]["9-12mm"]["sensitivity_pct"] == 0.0
    assert f["by_depth"]["9-12mm"]["depth_err_model_median_mm"] is None  # none found, nothing to say
    assert f["false_positives_per_phantom"] == 0.5
    assert f["depth_err_rule_median_mm"] == pytest.approx(1.75)  # 0.5 and 3.0 mm
    assert f["depth_err_model_median_mm"] == pytest.approx(0.6)  # 0.2 and 1.0 mm
    assert f["depth_bias_rule_median_mm"] == pytest.approx(-1.25)  # +0.5 and -3.0 mm
    assert f["depth_interval_coverage_pct"] == 50.0  # the second interval misses the truth
    assert f["paper_flat_found"] == 1 and f["paper_uneven_found"] is None and f["paper_false_positives"] == 2
    # the realistic world's case of the same phantom (app.study: realistic-paper-flat) counts as the paper's too
    results[-1] = {**results[-1], "name": "realistic-paper-flat"}
    assert score(results)["paper_flat_found"] == 1
    # by surface, the paper's phantom apart: where the two maps part ways
    assert f["by_surface"] == {
        "flat": {"phantoms": 1, "tumours": 2, "found": 1, "sensitivity_pct": 50.0, "false_positives_per_phantom": 1.0},
        "sloped": {"phantoms": 0, "tumours": 0, "found": 0, "sensitivity_pct": None,
                   "false_positives_per_phantom": None},
        "bumpy": {"phantoms": 1, "tumours": 1, "found": 1, "sensitivity_pct": 100.0,
                  "false_positives_per_phantom": 0.0}}


def test_each_case_says_where_it_missed_and_where_it_raised_a_false_positive():
    truth = {"x_m": 0.012, "y_m": 0.015, "depth_m": 8.4e-3, "diameter_m": 7e-3, "modulus_ratio": 3.6}
    found = {"source": "stiffness", "x_m": 0.0361, "y_m": 0.015, "score": 30.0, "contrast": 0.4, "first_level_N": 1.0}
    spurious = {**found, "x_m": 0.0475, "y_m": 0.0172, "score": 5.9, "contrast": 0.13, "first_level_N": 4.0}
    result = _result("c", [truth, {**truth, "x_m": 0.036}, {**truth, "x_m": 0.070}],
                     [{**_match(0, 8.4e-3, False), "detection": -1},
                      {**_match(1, 8.4e-3, True), "detection": 0},
                      {**_match(2, 8.4e-3, False, palpated=False), "detection": -1}], fps=1)
    result["tumours"] = [found, {**found, "source": "force"}, spurious]
    assert case_failures(result) == ["missed (12.0, 15.0) mm: 8.4 mm deep, 7.0 mm across, 3.6x stiffer",
                                     "false positive (47.5, 17.2) mm: z 5.9, contrast +13 %, first at 4 N"]
    # the force map's own matches (none here) decide its false positives
    assert case_failures(result, "force") == ["false positive (36.1, 15.0) mm: z 30.0, contrast +40 %, first at 1 N"]
    assert case_failures({"name": "d", "error": "PhantomError: bad"}) == []
    result.update(regions=11, regions_aborted={"Level timed out": 1, "Pressure ceiling exceeded": 7})
    assert case_failures(result)[0] == "8 of 11 areas aborted (pressure ceiling exceeded 7, level timed out 1)"


def test_each_band_says_how_many_of_its_tumours_stood_over_the_detectors_threshold_where_they_are():
    truth = {"x_m": 0.0, "y_m": 0.0, "diameter_m": 8e-3, "modulus_ratio": 5.0}
    results = [_result(name, [{**truth, "depth_m": d} for d in depths],
                       [{**_match(i, d, z > 4.0), "evidence_z": z} for i, (d, z) in enumerate(zip(depths, zs))],
                       fps=0) | {"detection_threshold_z": 4.0}
               for name, depths, zs in (("a", (4e-3, 10e-3), (9.0, 1.2)), ("b", (5e-3, 11e-3), (3.0, 4.5)))]
    bands = score(results)["by_depth"]
    # 3-6 mm: one tumour stood at 9, the other at 3, under the threshold: found or not, the physics decided
    assert bands["3-6mm"]["signal_z_median"] == pytest.approx(6.0)
    assert bands["3-6mm"]["signal_over_threshold_pct"] == 50.0
    assert bands["9-12mm"]["signal_z_median"] == pytest.approx(2.85)
    assert bands["9-12mm"]["signal_over_threshold_pct"] == 50.0
    assert bands["0-3mm"]["signal_z_median"] is None and bands["0-3mm"]["signal_over_threshold_pct"] is None
