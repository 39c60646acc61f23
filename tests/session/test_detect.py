"""Tumours: significant contrast, found where they are, from the level they first show at, with a score and
the paper's depth rule."""

from __future__ import annotations

import math
import shutil
from dataclasses import replace

import h5py
import numpy as np
import pytest

from session.analysis import SessionAnalysis
from session.detect import (
    DetectError,
    DetectParams,
    Tumour,
    detect,
    evidence,
    evidence_at,
    evidence_by_width,
    match_ground_truth,
    significant_peaks,
    spots,
    threshold,
)
from session.flatfield import Reference, contrast
from session.reader import open_session
from session.synthetic import level_record
from tests.session.test_stitch import PITCH, levels_of
from tissue.face import element_offsets_m

TUMOUR = (0.020, 0.015)
FORCES = (1.0, 2.0, 3.0, 4.0)
AREAS_X = (0.012, 0.020, 0.028, 0.036, 0.044)


def strip_session(factor_by_level, tumour=TUMOUR, noise=0.02):
    """Five areas along x at each force; the second over a stiff spot whose factor varies by level."""
    records = []
    for r, x in enumerate(AREAS_X):
        for k, force in enumerate(FORCES):
            factor = factor_by_level[k]
            records.append(level_record(r, k, force, (x, 0.015), tumours_xy_m=(tumour,) if factor > 1 else (),
                                        tumour_factor=factor, noise=noise, seed=100 * r + k))
    return levels_of(*records)


def found_in(levels, params=None, source="stiffness") -> list[Tumour]:
    return detect(levels, contrast(levels, source), PITCH, params)


def test_a_spot_present_from_one_level_on_is_a_tumour_first_seen_there():
    levels = strip_session([1.0, 1.6, 1.6, 1.6])
    found = found_in(levels)
    assert len(found) == 1
    t = found[0]
    assert math.hypot(t.x_m - TUMOUR[0], t.y_m - TUMOUR[1]) < 1e-3
    assert t.first_level_N == 2.0 and t.levels_N == (2.0, 3.0, 4.0) and t.source == "stiffness"
    over_it_at_2N = [i for i in range(len(levels)) if levels["region"][i] == 1 and levels["level"][i] == 1][0]
    assert t.depth_m == levels["indentation_m"][over_it_at_2N]  # the TSI indentation at the first level
    assert t.contrast > 0.4 and t.score > threshold(0.01, (4, 15), PITCH, DetectParams().kernel_widths_m)
    assert math.isnan(t.depth_model_m)  # no model-based estimate was asked for


def test_a_spot_that_comes_and_goes_is_noise():
    assert found_in(strip_session([1.6, 1.0, 1.0, 1.0])) == []
    found = found_in(strip_session([1.6, 1.0, 1.6, 1.6]))  # only the unbroken run up to the top counts
    assert [t.first_level_N for t in found] == [3.0]


def test_healthy_tissue_raises_no_spot_however_noisy_its_elements():
    # 5 % element-to-element scatter in the modulus: the healthy scatter is measured, not assumed
    assert found_in(strip_session([1.0] * 4, noise=0.05)) == []
    assert found_in(strip_session([1.0] * 4, noise=0.05), source="force") == []


def test_the_false_alarm_rate_sets_how_strong_a_spot_must_be():
    weak = strip_session([1.12] * 4)
    scores = [t.score for t in found_in(weak, DetectParams(false_alarm_per_area=0.5))]
    assert scores, "a 12 % rise is seen when false alarms are cheap"
    strict = DetectParams(false_alarm_per_area=1e-6)
    assert threshold(1e-6, (4, 15), PITCH, strict.kernel_widths_m) > threshold(0.5, (4, 15), PITCH,
                                                                                strict.kernel_widths_m)
    assert len(found_in(weak, strict)) <= len(scores)
    assert found_in(strip_session([1.6] * 4), strict)  # a strong one survives any rate


def test_two_tumours_under_one_face_stay_two():
    records = [level_record(r, k, f, (x, 0.015), tumours_xy_m=((0.012, 0.009), (0.028, 0.021)), tumour_factor=1.8,
                            tumour_radius_m=2.5e-3, noise=0.02, seed=7 * r + k)
               for r, x in enumerate(AREAS_X) for k, f in enumerate(FORCES)]
    found = found_in(levels_of(*records))
    assert len(found) == 2
    for t, (x, y) in zip(sorted(found, key=lambda t: t.x_m), ((0.012, 0.009), (0.028, 0.021))):
        assert math.hypot(t.x_m - x, t.y_m - y) < 1.5e-3


@pytest.mark.parametrize("kwargs, message", [
    ({"false_alarm_per_area": 0.0}, "false-alarm rate per area must be within [1e-6, 0.5]"),
    ({"false_alarm_per_area": float("nan")}, "false-alarm rate"),
    ({"accuracy": 0.9}, "accuracy must be a relative scatter within [0.001, 0.5]"),
    ({"merge_radius_m": 0.0}, "merge radius must be within (0, 50] mm"),
    ({"kernel_widths_m": ()}, "blob widths must be one or more within [0.5, 20] mm, got none"),
    ({"fit_radius_m": 1e-3}, "fit radius must be within [2, 50] mm, got 1 mm"),
])
def test_bad_parameters_are_named(kwargs, message):
    with pytest.raises(DetectError) as info:
        DetectParams(**kwargs)
    assert message in str(info.value)


def test_unknown_map_is_refused():
    with pytest.raises(ValueError, match="unknown map 'colour'"):
        contrast(strip_session([1.0] * 4), "colour")


def test_the_detectors_statistic_where_a_tumour_is_says_whether_it_stood_over_healthy_tissue():
    params = DetectParams()
    limit = threshold(params.false_alarm_per_area, (4, 15), PITCH, params.kernel_widths_m)
    strong, faint = strip_session([1.6] * 4), strip_session([1.015] * 4)
    at = {name: evidence_at(levels, contrast(levels, "stiffness"), PITCH, params, *TUMOUR)
          for name, levels in (("strong", strong), ("faint", faint))}
    assert at["strong"] > 2 * limit and at["faint"] < limit  # 1.5 % over a 2 % element scatter is not seen
    healthy = evidence_at(strong, contrast(strong, "stiffness"), PITCH, params, 0.040, 0.015)
    assert healthy < limit
    assert math.isnan(evidence_at(strong, contrast(strong, "stiffness"), PITCH, params, 0.080, 0.015))  # never under
    # and each match carries it, found or not
    matches, _ = match_ground_truth(found_in(faint), [{"x_m": TUMOUR[0], "y_m": TUMOUR[1], "depth_m": 9e-3}], faint,
                                    PITCH, contrasts={"stiffness": contrast(faint, "stiffness")}, params=params)
    stiffness = next(m for m in matches if m.source == "stiffness")
    assert not stiffness.found and stiffness.evidence_z == pytest.approx(at["faint"])
    assert math.isnan(next(m for m in matches if m.source == "force").evidence_z)  # its contrast was not given


def test_ground_truth_is_matched_within_2_mm_and_the_rest_are_false_positives():
    def tumour(x, source="stiffness"):
        return Tumour(x, 0.015, 1e-3, 1.0, source, 5.0, 0.3, (1.0,))

    truth = [{"x_m": 0.020, "y_m": 0.015, "depth_m": 2e-3}, {"x_m": 0.050, "y_m": 0.015, "depth_m": 7e-3}]
    found = [tumour(0.0215), tumour(0.047), tumour(0.0205, "force")]
    matches, false_positives = match_ground_truth(found, truth)
    by = {(m.source, m.truth_index): m for m in matches}
    assert by[("stiffness", 0)].found and by[("stiffness", 0)].error_xy_m == pytest.approx(1.5e-3)
    assert not by[("stiffness", 1)].found  # 3 mm off is not this tumour
    assert by[("force", 0)].found and not by[("force", 1)].found
    assert false_positives == {"stiffness": 1, "force": 0}


def test_on_a_simulated_phantom_without_tumours_every_detection_is_a_false_positive(recorded, reference_recorded,
                                                                                   tmp_path):
    with open_session(reference_recorded) as ref:
        share = np.ones(ref.levels["pressure_pa"].shape)
        reference = Reference.from_levels(ref.levels, share, np.zeros(share.shape), "tumour-free", physics=False)
    path = tmp_path / "no-tumours-listed.h5"
    shutil.copy(recorded[0], path)
    with h5py.File(path, "r+") as f:  # the phantom's list says: no tumour here
        f["meta"].attrs["ground_truth_json"] = np.bytes_(b"[]")
    with open_session(path) as s:
        assert s.simulated and s.ground_truth == []
        analysis = SessionAnalysis.run(s, reference=reference)
    assert analysis.has_ground_truth and analysis.matches == []
    assert analysis.false_positives == {"stiffness": 2, "force": 2} and len(analysis.tumours) == 4


def test_the_recorded_session_shows_both_palpated_tumours_in_both_maps(recorded, reference_recorded):
    with open_session(reference_recorded) as ref:
        share = np.ones(ref.levels["pressure_pa"].shape)
        reference = Reference.from_levels(ref.levels, share, np.zeros(share.shape), "tumour-free", physics=False)
    with open_session(recorded[0]) as s:
        analysis = SessionAnalysis.run(s, reference=reference)
        levels = s.levels
    assert analysis.false_positives == {"stiffness": 0, "force": 0}
    by = {(m.source, m.truth_index): m for m in analysis.matches}
    for source in ("stiffness", "force"):
        for truth in (0, 1):  # under the first and the third area
            m = by[(source, truth)]
            assert m.found and m.palpated and m.error_xy_m < 1.5e-3 and m.score > 3.0
            assert m.first_level_N == 0.5
            assert m.depth_estimate_m == pytest.approx(levels["indentation_m"][0 if truth == 0 else 6], abs=0.3e-3)
        assert not by[(source, 2)].found and not by[(source, 2)].palpated  # x = 60 mm was never palpated
    stiffness = [t for t in analysis.tumours if t.source == "stiffness"]
    assert all(np.isfinite(t.depth_m) and t.levels_N == (0.5, 1.0, 1.5) for t in stiffness)


def test_two_tracks_the_blob_fit_puts_on_one_tumour_are_one_tumour_first_seen_at_the_earlier_level():
    from session.detect import _merged
    from session.stitch import level_groups

    levels = strip_session([1.0, 1.6, 1.6, 1.6])
    groups = level_groups(levels)
    found = found_in(levels)
    assert len(found) == 1
    lead = max(found[0].spots, key=lambda spot: spot.score)
    # the same tumour seen as two tracks, each placed a little off it, the stronger from 3 N on
    early = replace(found[0], x_m=TUMOUR[0] - 2.5e-3, first_level_N=2.0, score=6.0, contrast=0.3,
                    levels_N=(2.0, 3.0, 4.0), spots=(replace(lead, score=6.0),))
    strong = replace(found[0], x_m=TUMOUR[0] + 1.2e-3, first_level_N=3.0, score=9.0, contrast=0.5,
                     levels_N=(3.0, 4.0), spots=(replace(lead, score=9.0),))
    apart = Tumour(0.0300, 0.015, math.nan, 4.0, "stiffness", 5.0, 0.2, (4.0,))
    merged = _merged([early, strong, apart], DetectParams(), levels, contrast(levels, "stiffness"), groups, PITCH)
    assert len(merged) == 2 and merged[1] == apart
    one = merged[0]
    assert math.hypot(one.x_m - TUMOUR[0], one.y_m - TUMOUR[1]) < 1e-3  # fitted again: on the tumour
    assert (one.score, one.contrast) == (9.0, 0.5)
    assert one.first_level_N == 2.0 and one.levels_N == (2.0, 3.0, 4.0)
    over_it_at_2N = [i for i in range(len(levels)) if levels["region"][i] == 1 and levels["level"][i] == 1][0]
    assert one.depth_m == levels["indentation_m"][over_it_at_2N]


def test_a_tumour_whose_own_area_stopped_early_is_placed_by_a_level_that_saw_all_of_it():
    # Its own area (x 16-24 mm) stopped after 2 N (the pressure ceiling over a stiff tumour); at 3 and 4 N only
    # the next area's edge column sees it, and there it is strongest. Placed from that level it was put at
    # that edge, 2.5 mm off; the levels that saw all of it place it.
    tumour = (0.0215, 0.015)
    factors = (1.3, 1.3, 3.0, 3.0)
    records = [level_record(r, k, force, (x, 0.015), tumours_xy_m=(tumour,), tumour_factor=factors[k], noise=0.02,
                            seed=100 * r + k)
               for r, x in enumerate(AREAS_X) for k, force in enumerate(FORCES) if not (r == 1 and k >= 2)]
    found = found_in(levels_of(*records))
    assert len(found) == 1
    t = found[0]
    assert t.levels_N == FORCES and max(t.spots, key=lambda spot: spot.score).force_N >= 3.0
    assert math.hypot(t.x_m - tumour[0], t.y_m - tumour[1]) < 1e-3


def test_a_tumour_beside_the_palpated_tissue_is_placed_at_its_edge_not_beyond():
    # the faces span y 0-30 mm; a stiff spot past their side raises the side columns most, and a blob fitted
    # to that rise alone peaks off the tissue, where nothing was palpated
    from session.detect import _blob_centre

    levels = strip_session([1.0, 1.0, 1.0, 1.0], noise=0.0)
    offsets = np.asarray(levels["tsi_position_m"][:, None, None, :2]) + element_offsets_m(4, 15, PITCH)[None]
    rising = 0.5 * np.exp(-0.5 * (np.hypot(offsets[..., 0] - 0.020, offsets[..., 1] - 0.033) / 3e-3) ** 2)
    records = np.flatnonzero(levels["level"] == 2)
    x, y = _blob_centre(levels, rising, np.full(rising.shape, 0.02), records, [(0.020, 0.029)], PITCH,
                        DetectParams().fit_radius_m)
    assert abs(x - 0.020) < 0.5e-3
    assert 0.029 <= y <= 0.030


def test_a_contrast_shaped_like_an_uncertainty_shared_between_elements_is_not_evidence():
    # The tissue may go on beyond the palpated end: then the face's whole end half reads 5 % off together.
    # Two standard deviations of that, counted as independent per element, pass the threshold.
    shape, widths = (4, 15), DetectParams().kernel_widths_m
    limit = threshold(0.01, shape, PITCH, widths)
    mode = np.zeros(shape)
    mode[:2] = 0.05
    sigma = np.sqrt(0.02 ** 2 + mode ** 2)
    assert np.nanmax(evidence(2 * mode, sigma, PITCH, widths)) > limit
    assert np.nanmax(evidence(2 * mode, sigma, PITCH, widths, mode[None])) < 0.6 * limit
    # a tumour's blob is still one (the shared part no longer dilutes the elements it covers)
    offsets = element_offsets_m(*shape, PITCH)
    blob = 0.08 * np.exp(-0.5 * (offsets ** 2).sum(axis=-1) / 2e-3 ** 2)
    assert np.nanmax(evidence(blob, sigma, PITCH, widths, mode[None])) > limit


def test_a_weaker_tumour_beside_a_stronger_one_under_one_face_is_a_spot_of_its_own():
    # s7043-0002: a shallow tumour 8 mm across the face from a stronger one. The widest blob sums both and
    # has one maximum, on the stronger one; the narrower blob has one on each.
    shape, widths = (4, 15), DetectParams().kernel_widths_m
    limit = threshold(0.01, shape, PITCH, widths)
    offsets = element_offsets_m(*shape, PITCH)

    def blob(i, j, height, width_m=2e-3):
        return height * np.exp(-0.5 * ((offsets - offsets[i, j]) ** 2).sum(axis=-1) / width_m ** 2)

    contrast, sigma = blob(0, 5, 1.0) + blob(1, 9, 0.5), np.full(shape, 0.05)
    widest_wins = evidence(contrast, sigma, PITCH, widths)
    assert np.argwhere(significant_peaks(widest_wins, limit, contrast)).tolist() == [[0, 5]]
    by_width = evidence_by_width(contrast, sigma, PITCH, widths)
    assert np.argwhere(significant_peaks(by_width, limit, contrast)).tolist() == [[0, 5], [1, 9]]
    # and one tumour is one spot though its widths peak on neighbouring elements (a sharp peak, and a broad
    # skirt centred a row and a column over)
    one = blob(0, 7, 0.8, 1e-3) + blob(2, 8, 0.3, 4e-3)
    assert significant_peaks(evidence_by_width(one, sigma, PITCH, widths), limit, one).sum() == 1


def test_no_spot_is_centred_where_the_tissue_does_not_read_harder():
    # A strong tumour's far field rising across a face towards it (s5519-0006): the face's far row, partly
    # off a ridge, is known poorly, and its sink-in is the area's largest shared uncertainty. The widest
    # blob centred there sums the rise two rows away and peaks there, at contrast -0.21.
    shape, widths = (4, 15), DetectParams().kernel_widths_m
    limit = threshold(0.01, shape, PITCH, widths)
    rows = lambda values: np.repeat(np.array(values)[:, None], shape[1], axis=1)  # noqa: E731
    far_field = rows([0.14, 0.09, -0.04, -0.21])
    sink_in = rows([-0.04, -0.015, 0.06, 0.49])[None]
    z = evidence(far_field, rows([0.04, 0.025, 0.065, 0.49]), PITCH, widths, sink_in)
    assert np.unravel_index(np.nanargmax(z), shape)[0] == 3 and np.nanmax(z) > 2 * limit
    assert not significant_peaks(z, limit, far_field).any()
    # where the tissue does read harder, the same statistic is a spot
    assert significant_peaks(z, limit, far_field + 0.3).any()


def test_a_strong_tumours_far_field_at_the_edge_of_the_area_beyond_the_next_is_that_tumour():
    # A stiff tumour just inside the fourth area's face, at its seam with the third: both see it at their
    # edges. It also stiffens the tissue at the near edge of the second area, 8 mm beyond the third's face,
    # which rises towards that edge; that rise is its far field, not a tumour.
    from types import SimpleNamespace

    levels = strip_session([1.0, 1.0, 1.0, 1.0], noise=0.0)
    x = np.asarray(levels["tsi_position_m"][:, None, None, 0]) + element_offsets_m(4, 15, PITCH)[None][..., 0]
    y = np.asarray(levels["tsi_position_m"][:, None, None, 1]) + element_offsets_m(4, 15, PITCH)[None][..., 1]
    blob = 0.8 * np.exp(-0.5 * ((x - 0.0324) ** 2 + (y - 0.015) ** 2) / 2.5e-3 ** 2)
    far = np.where((levels["region"] == 1)[:, None, None],
                   0.15 * np.exp(-0.5 * ((x - 0.024) ** 2 + (y - 0.015) ** 2) / 2e-3 ** 2), 0.0)
    seen = SimpleNamespace(map="stiffness", contrast=blob + far, sigma=np.full(blob.shape, 0.02), modes=None)
    found = detect(levels, seen, PITCH)
    assert len(found) == 1
    assert math.hypot(found[0].x_m - 0.0324, found[0].y_m - 0.015) < 1e-3


def test_a_far_field_at_the_next_areas_edge_above_the_level_its_tumours_area_stopped_at_is_that_tumour():
    # A stiff tumour near the surface under the second area takes that area to its force limit at 2 N; the
    # third area, beside it, goes on to 4 N and its near edge shows the tumour's far field at every level.
    # Above 2 N there is no spot of the tumour's own to join, and the far field is still the same tumour.
    from types import SimpleNamespace

    levels = strip_session([1.0, 1.0, 1.0, 1.0], noise=0.0)
    levels = levels[~((levels["region"] == 1) & (levels["force_desired_N"] > 2.0))]
    x = np.asarray(levels["tsi_position_m"][:, None, None, 0]) + element_offsets_m(4, 15, PITCH)[None][..., 0]
    y = np.asarray(levels["tsi_position_m"][:, None, None, 1]) + element_offsets_m(4, 15, PITCH)[None][..., 1]
    second, third = ((levels["region"] == r)[:, None, None] for r in (1, 2))
    tumour = np.where(second, 1.5 * np.exp(-0.5 * ((x - 0.0195) ** 2 + (y - 0.015) ** 2) / 2.5e-3 ** 2), 0.0)
    far = np.where(third, 0.3 * np.exp(-0.5 * ((x - 0.0225) ** 2 + (y - 0.015) ** 2) / 2e-3 ** 2), 0.0)
    seen = SimpleNamespace(map="stiffness", contrast=tumour + far, sigma=np.full(x.shape, 0.02), modes=None)
    edge = [s for s in spots(levels, seen, PITCH, DetectParams()) if int(levels["region"][s.record]) == 2]
    assert {s.force_N for s in edge} == set(FORCES) and all(s.at_edge for s in edge)
    found = detect(levels, seen, PITCH)
    assert len(found) == 1
    assert math.hypot(found[0].x_m - 0.0195, found[0].y_m - 0.015) < 1e-3
    assert found[0].levels_N == FORCES


def test_a_tumour_at_one_edge_of_its_face_is_not_joined_to_a_stronger_spot_beyond_the_other():
    # A tumour just inside the fourth area's low edge, its elements unsure (beside a bump's flank), and a
    # weak but sure rise at the fifth area's low edge, 8 mm away: the tumour's spot reaches its face's edge
    # on the side away from that rise, so what raised it cannot lie there.
    from types import SimpleNamespace

    levels = strip_session([1.0, 1.0, 1.0, 1.0], noise=0.0)
    x = np.asarray(levels["tsi_position_m"][:, None, None, 0]) + element_offsets_m(4, 15, PITCH)[None][..., 0]
    y = np.asarray(levels["tsi_position_m"][:, None, None, 1]) + element_offsets_m(4, 15, PITCH)[None][..., 1]
    fourth, fifth = ((levels["region"] == r)[:, None, None] for r in (3, 4))
    tumour = np.where(fourth, 0.6 * np.exp(-0.5 * ((x - 0.033) ** 2 + (y - 0.015) ** 2) / 2e-3 ** 2), 0.0)
    rise = np.where(fifth, 0.1 * np.exp(-0.5 * ((x - 0.041) ** 2 + (y - 0.015) ** 2) / 2e-3 ** 2), 0.0)
    sigma = np.where(fourth, 0.15, 0.02) * np.ones(x.shape)
    seen = SimpleNamespace(map="stiffness", contrast=tumour + rise, sigma=sigma, modes=None)
    score = {int(levels["region"][s.record]): s.score for s in spots(levels, seen, PITCH, DetectParams())
             if s.force_N == 1.0}
    assert score[4] > score[3] > threshold(0.01, (4, 15), PITCH, DetectParams().kernel_widths_m)
    found = detect(levels, seen, PITCH)
    assert any(math.hypot(t.x_m - 0.033, t.y_m - 0.015) < 1.5e-3 for t in found)  # not 8 mm off, at the rise


def test_a_far_field_is_placed_by_where_its_contrast_is_largest_not_where_the_widest_blob_peaks():
    # A strong tumour 7 mm beyond the fourth area's face raises its near row most; that row is the least
    # sure, so the widest blob's statistic peaks at the far rows, 11 mm from the tumour.
    from types import SimpleNamespace

    levels = strip_session([1.0, 1.0, 1.0, 1.0], noise=0.0)
    x = np.asarray(levels["tsi_position_m"][:, None, None, 0]) + element_offsets_m(4, 15, PITCH)[None][..., 0]
    y = np.asarray(levels["tsi_position_m"][:, None, None, 1]) + element_offsets_m(4, 15, PITCH)[None][..., 1]
    blob = 0.8 * np.exp(-0.5 * ((x - 0.026) ** 2 + (y - 0.015) ** 2) / 2.5e-3 ** 2)
    fourth = (levels["region"] == 3)[:, None, None]
    rows = np.array([0.10, 0.06, 0.05, 0.045])[:, None] * np.exp(-0.5 * ((y[0] - 0.015) / 4e-3) ** 2)
    contrast = np.where(fourth, rows, blob)
    sigma = np.where(fourth & (np.arange(4) == 0)[None, :, None], 0.3, 0.02) * np.ones(blob.shape)
    seen = SimpleNamespace(map="stiffness", contrast=contrast, sigma=sigma, modes=None)
    found = detect(levels, seen, PITCH)
    assert len(found) == 1
    assert math.hypot(found[0].x_m - 0.026, found[0].y_m - 0.015) < 1e-3


def test_a_tumour_in_the_gap_between_two_areas_gets_the_rule_depth_and_counts_as_palpated():
    # Areas laid evenly along a tissue whose length is not a multiple of the face's width leave gaps of a
    # few tenths of a millimetre; a tumour there lies under both faces, and its fit may put it in the gap.
    from session.detect import _depth_at

    gap_tumour = (0.0084, 0.015)
    records = [level_record(r, k, f, (0.0042 + 0.0084 * r, 0.015), tumours_xy_m=(gap_tumour,), tumour_factor=1.6,
                            noise=0.02, seed=10 * r + k) for r in range(6) for k, f in enumerate(FORCES)]
    levels = levels_of(*records)
    first = np.flatnonzero(levels["level"] == 0)
    nearer = first[levels["region"][first] == 0][0]  # the gap is 0.2 mm from area 0, 0.2 mm from area 1
    assert _depth_at(levels, first, 0.0083, 0.015, PITCH) == levels["indentation_m"][nearer]
    assert math.isnan(_depth_at(levels, first, 0.0084, 0.032, PITCH))  # beyond the tissue's side: nobody
    found = found_in(levels)
    assert len(found) == 1 and abs(found[0].x_m - gap_tumour[0]) < 1e-3 and math.isfinite(found[0].depth_m)
    matches, _ = match_ground_truth(found, [{"x_m": gap_tumour[0], "y_m": gap_tumour[1], "depth_m": 2e-3}],
                                    levels, PITCH)
    assert all(m.palpated for m in matches) and matches[0].found


def _strong_with_far_side(second_factor=1.0, far_area=2):
    """Six areas; the third over a strong tumour at y 11 mm whose far field raises the far side's last
    three columns by 8 % (as a shallow stiff sphere does under a rigid face) in area ``far_area``, and
    over a second tumour at that far side stiffer by ``second_factor``."""
    far = np.ones((4, 15))
    far[:, 12:] = 1.08
    records = []
    for r in range(6):
        for k, f in enumerate(FORCES):
            x = 0.004 + 0.008 * r
            tumours = ((x, 0.011),) if r == 2 else ()
            record = levels_of(level_record(r, k, f, (x, 0.015), tumours_xy_m=tumours, tumour_factor=3.0,
                                            tumour_radius_m=3e-3, noise=0.01, seed=7 * r + k))
            if r == far_area:
                bump = np.where(np.hypot(element_offsets_m(4, 15, PITCH)[..., 1] + 0.015 - 0.027,
                                         element_offsets_m(4, 15, PITCH)[..., 0]) <= 3e-3, second_factor, 1.0)
                for name in ("pressure_pa", "element_force_N", "stiffness_pa"):
                    record[name][0] *= far * bump
            records.append(record)
    return np.concatenate(records), far - 1.0


def test_a_strong_tumours_far_field_in_its_own_face_is_explained_away_and_a_second_tumour_is_not():
    from session.detect import explained_away

    params = DetectParams()
    levels, far_field = _strong_with_far_side()
    c = contrast(levels, "stiffness")
    found = detect(levels, c, PITCH, params)
    ys = sorted(t.y_m for t in found)
    assert len(found) == 2 and abs(ys[0] - 0.011) < 1e-3 and ys[1] > 0.026  # the far side reads as one

    def signature(tumour, records):  # the strong sphere's own mechanics: its far field, its core as measured
        made = np.broadcast_to(far_field, (len(records), 4, 15)).copy()
        core = np.abs(element_offsets_m(4, 15, PITCH)[..., 1] + 0.015 - tumour.y_m) <= 3e-3
        made[:, core] = c.contrast[records][:, core]
        return made, 0.25 * np.abs(made)

    kept = explained_away(found, levels, c, PITCH, params, signature)
    assert len(kept) == 1 and abs(kept[0].y_m - 0.011) < 1e-3
    # a second tumour under the far side stands out of the far field, and is kept
    levels, _ = _strong_with_far_side(second_factor=1.5)
    c = contrast(levels, "stiffness")
    found = detect(levels, c, PITCH, params)
    assert len(explained_away(found, levels, c, PITCH, params, signature)) == 2
    # nothing to explain it with: kept
    assert len(explained_away(found, levels, c, PITCH, params, lambda t, records: None)) == 2


def test_a_strong_tumours_far_field_in_the_face_beside_it_is_explained_away_too():
    """The far field raises the far side of the next area, where the strong tumour itself raised no spot."""
    from session.detect import explained_away

    params = DetectParams()
    levels, far_field = _strong_with_far_side(far_area=3)
    c = contrast(levels, "stiffness")
    found = detect(levels, c, PITCH, params)
    strong, far = sorted(found, key=lambda t: -t.score)
    assert abs(strong.y_m - 0.011) < 1e-3 and far.y_m > 0.026 and abs(far.x_m - 0.028) < 2e-3
    assert not {s.record for s in strong.spots} & {s.record for s in far.spots}
    asked = []

    def signature(tumour, records):
        asked.append((round(tumour.y_m, 3), sorted(levels["region"][records])))
        near = np.abs(levels["tsi_position_m"][records, 0] - tumour.x_m) <= 12e-3
        made = np.where(near[:, None, None] & (levels["region"][records] == 3)[:, None, None], far_field, 0.0)
        return made, 0.25 * np.abs(made)

    kept = explained_away(found, levels, c, PITCH, params, signature)
    assert kept == [strong] and asked == [(0.011, [3])]




def _strong_and_weak(weak_contrast, sigma):
    """Four areas without noise: a large stiff tumour's contrast (a core and a far field) in the first, and a
    weaker one's, ``weak_contrast`` at its peak, 14 mm away in the second, every element's uncertainty
    ``sigma``. Returns the levels, the contrast as detect takes it, and each tumour's own contrast."""
    from types import SimpleNamespace

    levels = strip_session([1.0, 1.0, 1.0, 1.0], noise=0.0)
    xy = np.asarray(levels["tsi_position_m"][:, None, None, :2]) + element_offsets_m(4, 15, PITCH)[None]
    d = np.hypot(xy[..., 0] - 0.012, xy[..., 1] - 0.010)
    strong = 1.5 * np.exp(-0.5 * (d / 3e-3) ** 2) + 0.4 * np.exp(-0.5 * (d / 6e-3) ** 2)
    weak = weak_contrast * np.exp(-0.5 * np.hypot(xy[..., 0] - 0.021, xy[..., 1] - 0.020) ** 2 / 2.5e-3 ** 2)
    seen = SimpleNamespace(map="stiffness", contrast=(1.0 + strong) * (1.0 + weak) - 1.0,
                           sigma=np.full(d.shape, sigma), modes=None)
    return levels, seen, strong, weak


def test_a_weaker_tumour_is_placed_by_what_stands_out_over_a_stronger_ones_far_field():
    # A large stiff tumour in the first area, and a weaker one 14 mm away in the second: the large one's far
    # field slopes across the weaker one's blob and pulls where it peaks 2 mm towards it. Over what the large
    # one's sphere makes of those faces, the weaker one stands where it is.
    from session.detect import explained_away

    levels, seen, strong, weak = _strong_and_weak(0.5, 0.03)
    found = detect(levels, seen, PITCH)
    assert len(found) == 2
    pulled = min(found, key=lambda t: t.score)
    assert math.hypot(pulled.x_m - 0.021, pulled.y_m - 0.020) > 1.5e-3

    def signature(tumour, records):
        made = strong if tumour.score > pulled.score else weak
        return made[records], np.zeros((len(records), 4, 15))

    kept = explained_away(found, levels, seen, PITCH, DetectParams(), signature)
    placed = min(kept, key=lambda t: t.score)
    assert math.hypot(placed.x_m - 0.021, placed.y_m - 0.020) < 0.2e-3
    assert placed.depth_m == levels["indentation_m"][(levels["region"] == 1) & (levels["level"] == 0)][0]


def test_a_weaker_tumour_a_stronger_ones_far_field_tips_under_the_threshold_is_kept_where_it_makes_little_of_it(
        monkeypatch):
    """s48003-0007: a 4.9 mm-deep tumour 7 mm from a 9.9 mm-deep one read +0.26 where that one's sphere made
    +0.076, and over it fell under the threshold: a spot the stronger spheres make less than half of stays, on
    the stiffness map."""
    from types import SimpleNamespace

    import session.detect as detect_module
    from session.detect import explained_away

    levels, seen, strong, weak = _strong_and_weak(0.3, 0.18)
    found = detect(levels, seen, PITCH)
    assert len(found) == 2
    weaker = min(found, key=lambda t: t.score)

    def signature(tumour, records):
        return (weak if tumour is weaker else strong)[records], np.zeros((len(records), 4, 15))

    assert len(explained_away(found, levels, seen, PITCH, DetectParams(), signature)) == 2
    # the spheres are fitted to the stiffness contrast: the force map's share of them is not asked
    on_force_map = SimpleNamespace(**{**vars(seen), "map": "force"})
    assert len(explained_away(found, levels, on_force_map, PITCH, DetectParams(), signature)) == 1
    # over the stronger one's sphere alone it no longer passes the threshold
    monkeypatch.setattr(detect_module, "EXPLAINED_SHARE", 0.0)
    assert len(explained_away(found, levels, seen, PITCH, DetectParams(), signature)) == 1


def test_a_tumours_depth_is_read_over_the_other_tumours_spheres():
    # s7043-0002: a 1.9 mm-deep tumour 8 mm across one face from a larger one was read 10.4 mm deep, the
    # other's skirt fitted as its own broad, deep sphere. What the model of one sphere is given is each
    # face's contrast over the other's sphere, its model error added, on the faces that could hold it.
    # s5519-0006: every contrast is over its face's median, which two tumours under one face raise (a
    # 4.6 mm-deep tumour's healthy elements read -0.07); the face's scale is put back as both spheres make it.
    from session.detect import over_the_others

    levels = strip_session([1.0, 1.0, 1.0, 1.0], noise=0.0)
    xy = np.asarray(levels["tsi_position_m"][:, None, None, :2]) + element_offsets_m(4, 15, PITCH)[None]

    def over_median(ratio):  # a face's contrast: its ratio over the face's median
        return ratio / np.median(ratio.reshape(len(ratio), -1), axis=1)[:, None, None] - 1.0

    skirt = over_median(1.0 + 0.5 * np.exp(-0.5 * (np.hypot(xy[..., 0] - 0.020, xy[..., 1] - 0.010) / 5e-3) ** 2))
    own = over_median(1.0 + 0.4 * np.exp(-0.5 * (np.hypot(xy[..., 0] - 0.021, xy[..., 1] - 0.022) / 4e-3) ** 2))
    both = over_median((1.0 + skirt) * (1.0 + own))
    near = np.abs(levels["tsi_position_m"][:, 0] - 0.021) <= 8e-3
    naive = (1.0 + both) / (1.0 + skirt) - 1.0  # over the other's sphere alone
    assert np.median(naive[near] - own[near]) < -0.04  # the face's median raised: its own reads low
    seen = replace(contrast(levels, "stiffness"), contrast=both, sigma=np.full(both.shape, 0.03), modes=None)
    weak, strong = (Tumour(x, y, 2e-3, 1.0, "stiffness", score, 0.3, (1.0,))
                    for x, y, score in ((0.021, 0.022, 10.0), (0.020, 0.010, 50.0)))
    asked = []

    def signature(tumour, records):
        asked.append((tumour, tuple(records)))
        made = (skirt if tumour is strong else own)[records]
        return made, 0.1 * made

    over = over_the_others(weak, [strong], levels, seen, signature, 8e-3)
    assert asked == [(weak, tuple(np.flatnonzero(near))), (strong, tuple(np.flatnonzero(near)))]
    np.testing.assert_allclose(over.contrast[near], own[near], atol=1e-12)
    np.testing.assert_allclose(over.sigma[near], np.hypot(0.03, 0.1 * skirt[near]))
    assert np.array_equal(over.contrast[~near], both[~near]) and np.all(over.sigma[~near] == 0.03)
    alone = over_the_others(weak, [], levels, seen, signature, 8e-3)  # no other: the contrast as it is
    assert alone.contrast is not both and np.array_equal(alone.contrast, both)


def test_each_tumours_depth_is_read_over_spheres_fitted_without_its_own_contrast():
    # s5519-0016: two deep, broad tumours 5 mm apart. Each sphere fitted to the contrast as it is takes the other's
    # skirt as its own, and each tumour read over the other's sphere then loses that part twice. Fitted again
    # over the other's fit, sweep after sweep, each sphere leaves the other what is its own.
    from session.detect import over_each_other, over_the_others

    levels = strip_session([1.0, 1.0, 1.0, 1.0], noise=0.0)
    xy = np.asarray(levels["tsi_position_m"][:, None, None, :2]) + element_offsets_m(4, 15, PITCH)[None]
    places = [(0.019, 0.011), (0.023, 0.013)]  # element centres, 4.5 mm apart
    shapes = [np.exp(-0.5 * (np.hypot(xy[..., 0] - x, xy[..., 1] - y) / 4e-3) ** 2) for x, y in places]
    peak = [np.unravel_index(np.argmax(s), s.shape) for s in shapes]  # (record, row, column) of each centre

    def over_median(ratio):  # a face's contrast: its ratio over the face's median
        return ratio / np.median(ratio.reshape(len(ratio), -1), axis=1)[:, None, None] - 1.0

    def sphere(n, height):  # tumour n's contrast, ``height`` at its centre
        amplitude = height
        for _ in range(50):  # the face's median moves with it
            amplitude = (1.0 + height) * np.median(1.0 + amplitude * shapes[n][peak[n][0]]) - 1.0
        return over_median(1.0 + amplitude * shapes[n])

    own = [sphere(0, 0.25), sphere(1, 0.2)]
    both = over_median((1.0 + own[0]) * (1.0 + own[1]))
    seen = replace(contrast(levels, "stiffness"), contrast=both, sigma=np.full(both.shape, 0.03), modes=None)
    tumours = [Tumour(x, y, 2e-3, 1.0, "stiffness", score, 0.3, (1.0,)) for (x, y), score in zip(places, (30.0, 20.0))]

    def fitted(tumour, given, records):  # a sphere of the tumour's shape, as high as its centre reads
        n = tumours.index(tumour)
        made = sphere(n, given.contrast[peak[n]])[records]
        return made, np.zeros_like(made)

    def error(over):  # how far each tumour's own peak is from what it reads there, over the other
        return [abs(o.contrast[peak[n]] - own[n][peak[n]]) for n, o in enumerate(over)]

    once = error([over_the_others(t, [o for o in tumours if o is not t], levels, seen,
                                  lambda o, records: fitted(o, seen, records), 8e-3) for t in tumours])
    swept = error(over_each_other(tumours, levels, seen, fitted, 8e-3))
    assert min(once) > 0.025 and max(swept) < 0.15 * min(once)
    asked = []

    def settled(tumour, given, records):  # fits that do not move: the second sweep changes nothing, and ends it
        asked.append(tumour)
        return fitted(tumour, seen, records)

    assert error(over_each_other(tumours, levels, seen, settled, 8e-3)) == once and len(asked) == 8
    # one tumour: its contrast as it is
    alone = over_each_other(tumours[:1], levels, seen, fitted, 8e-3)
    assert len(alone) == 1 and np.array_equal(alone[0].contrast, both)


def test_two_tumours_each_pulled_towards_the_other_are_placed_over_each_other():
    # Two stiff tumours 11 mm apart, each with a far field that slopes across the other's blob: each is
    # detected pulled towards the other (the stronger one by 0.8 mm). The weaker one placed over the
    # stronger one's sphere solved where that was misplaced would be pushed away; placed over each other's
    # spheres, each solved where the other now lies, both stand where they are.
    from types import SimpleNamespace

    from session.detect import explained_away

    levels = strip_session([1.0, 1.0, 1.0, 1.0], noise=0.0)
    xy = np.asarray(levels["tsi_position_m"][:, None, None, :2]) + element_offsets_m(4, 15, PITCH)[None]
    truths = [(0.016, 0.012, 0.9, 0.4), (0.026, 0.017, 0.4, 0.3)]  # x, y, blob and far-field heights

    def field(x_m, y_m, blob, far):
        d = np.hypot(xy[..., 0] - x_m, xy[..., 1] - y_m)
        return blob * np.exp(-0.5 * (d / 2.5e-3) ** 2) + far * np.exp(-0.5 * (d / 6e-3) ** 2)

    both = np.prod([1.0 + field(*truth) for truth in truths], axis=0) - 1.0
    seen = SimpleNamespace(map="stiffness", contrast=both, sigma=np.full(both.shape, 0.03), modes=None)
    found = sorted(detect(levels, seen, PITCH), key=lambda t: -t.score)
    assert len(found) == 2
    assert math.hypot(found[0].x_m - 0.016, found[0].y_m - 0.012) > 0.6e-3

    def signature(tumour, records):  # each sphere's field, solved where the tumour now lies
        _, _, blob, far = min(truths, key=lambda truth: math.hypot(truth[0] - tumour.x_m, truth[1] - tumour.y_m))
        return field(tumour.x_m, tumour.y_m, blob, far)[records], np.zeros((len(records), 4, 15))

    kept = sorted(explained_away(found, levels, seen, PITCH, DetectParams(), signature), key=lambda t: -t.score)
    for placed, (x, y, _, _) in zip(kept, truths):
        assert math.hypot(placed.x_m - x, placed.y_m - y) < 0.2e-3
