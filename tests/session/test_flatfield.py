"""The probe's own pattern taken out: a rigid face's edge rows must not read as tumours, a reference
palpation is saved and reused, and a file that is not one is refused in one line."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from session.detect import detect
from session.flatfield import FlatFieldError, Reference, contrast
from session.synthetic import level_record
from tests.session.test_hostile_files import refusal
from tests.session.test_stitch import PITCH, levels_of

AREAS_X = (0.012, 0.020, 0.028, 0.036, 0.044)
FORCES = (1.0, 2.0, 3.0)
# a rigid face on a layer: its two long edge rows carry about 2.5 times what the inner rows carry
FACE = np.array([2.5, 1.0, 1.0, 2.5])[:, None] * np.ones((4, 15))


def faced(record, tumour_xy=None):
    """A synthetic record as a rigid face would read it (the pattern, and the same force in total)."""
    levels = levels_of(record)
    pattern = FACE / FACE.mean()
    for name in ("pressure_pa", "element_force_N", "stiffness_pa"):
        levels[name] = levels[name] * pattern
    return levels


def session(tumour_area=None, noise=0.02):
    rows = [faced(level_record(r, k, f, (x, 0.015), noise=noise, seed=31 * r + k,
                               tumours_xy_m=((x, 0.015),) if r == tumour_area else (), tumour_factor=1.4))
            for r, x in enumerate(AREAS_X) for k, f in enumerate(FORCES)]
    return np.concatenate(rows)


EIGHT_AREAS_X = tuple(0.012 + 0.008 * k for k in range(8))


def eight_areas(tumour_area, alter, face=False):
    """Eight areas along x (a tumour under ``tumour_area``, if any), each record's readings changed in place
    by ``alter`` ((rows, cols) array), as a rigid face reads them if ``face``."""
    records = []
    for r, x in enumerate(EIGHT_AREAS_X):
        for k, f in enumerate(FORCES):
            record = level_record(r, k, f, (x, 0.015), noise=0.02, seed=31 * r + k,
                                  tumours_xy_m=((x, 0.015),) if r == tumour_area else (), tumour_factor=1.4)
            levels = faced(record) if face else levels_of(record)
            change = np.ones((4, 15))
            alter(change)
            for name in ("pressure_pa", "element_force_N", "stiffness_pa"):
                levels[name][0] *= change
            records.append(levels)
    return np.concatenate(records)


def test_the_face_pattern_is_not_a_tumour_and_a_tumour_still_is():
    healthy = session()
    c = contrast(healthy, "force")
    assert np.nanmax(np.abs(c.contrast)) < 0.15  # the 2.5x edge rows are gone
    assert detect(healthy, c, PITCH) == []
    with_tumour = session(tumour_area=2)
    found = detect(with_tumour, contrast(with_tumour, "force"), PITCH)
    assert len(found) == 1 and abs(found[0].x_m - AREAS_X[2]) < 1e-3


def test_without_the_flat_field_the_face_edges_would_read_as_hard():
    healthy = session()
    edge, inner = healthy["pressure_pa"][:, 0, :].mean(), healthy["pressure_pa"][:, 1, :].mean()
    assert edge / inner > 2.0  # what the raw map shows, and why the raw map cannot be thresholded


def test_a_reference_palpation_round_trips_and_is_used(tmp_path):
    healthy = session()
    share = np.ones(healthy["pressure_pa"].shape)
    reference = Reference.from_levels(healthy, share, np.zeros(share.shape), "five healthy areas", physics=False)
    path = tmp_path / "reference.json"
    reference.save(path)
    again = Reference.load(path, (4, 15))
    assert again.forces_N == FORCES and again.areas == len(AREAS_X)
    np.testing.assert_allclose(again.baseline, reference.baseline)
    with_tumour = session(tumour_area=2)
    c = contrast(with_tumour, "force", reference=again)
    assert c.source == "reference" and "five healthy areas" in c.description
    found = detect(with_tumour, c, PITCH)
    assert len(found) == 1 and abs(found[0].x_m - AREAS_X[2]) < 1e-3


@pytest.mark.parametrize("content, message", [
    ("not json", "cannot read the reference palpation"),
    (json.dumps({"format": "something else"}), "not a Palpation Console reference palpation"),
    (json.dumps({"format": "palpation-console-reference", "forces_N": [1.0], "baseline": [[1.0]],
                 "scatter": [[0.0]]}), "made for another array"),
    (json.dumps({"format": "palpation-console-reference", "forces_N": [float("nan")],
                 "baseline": np.ones((1, 4, 15)).tolist(), "scatter": np.zeros((1, 4, 15)).tolist()}),
     "finite and positive"),
])
def test_a_file_that_is_not_a_reference_is_refused_in_one_line(tmp_path, content, message):
    path = tmp_path / "ref.json"
    path.write_text(content)
    with pytest.raises(FlatFieldError) as info:
        Reference.load(path, (4, 15))
    assert message in str(info.value) and "\n" not in str(info.value)


def test_a_fifo_a_device_or_a_huge_file_is_refused_without_waiting_on_it_or_reading_it(tmp_path):
    """Each in a child process (tests/session/open_child.py): a FIFO's open would wait for ever, /dev/zero
    never ends, and reading a file of gigabytes would take them (the child's memory is capped)."""
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    for path in (fifo, "/dev/zero", tmp_path):
        assert refusal(path, "reference") == f"{path}: not a regular file: not a reference palpation"
    huge = tmp_path / "huge.json"
    with open(huge, "wb") as f:
        f.truncate(5 * 2**30)  # 5 GB of zeros, sparse: no room on the disk
    assert refusal(huge, "reference") == (f"{huge}: larger than 4 MB: not a reference palpation (one is well under "
                                          "1 MB)")


def test_the_side_columns_the_physics_knows_less_well_do_not_raise_spots():
    # Where the face meets the tissue's free sides the expected pattern is least sure: there healthy tissue
    # departs from it by several times what it does under the rest of the face, from one area to the next.
    rng = np.random.default_rng(7)

    def scatter_sides(reading):
        reading[:, [0, -1]] *= 1.0 + 0.12 * rng.standard_normal((4, 2))

    def areas(tumour_area=None):
        return eight_areas(tumour_area, scatter_sides, face=True)

    healthy = areas()
    c = contrast(healthy, "force")
    side, inside = c.sigma[:, 1:3, [0, -1]], c.sigma[:, 1:3, 1:-1]
    assert np.nanmedian(side) > 2.5 * np.nanmedian(inside)
    assert detect(healthy, c, PITCH) == []
    with_tumour = areas(tumour_area=3)
    found = detect(with_tumour, contrast(with_tumour, "force"), PITCH)
    assert len(found) == 1 and abs(found[0].x_m - EIGHT_AREAS_X[3]) < 1e-3


def test_an_element_too_few_areas_vouch_for_takes_its_part_of_the_face_not_one():
    # The physics misses how much faster the face's edge rows stiffen (10 % here). Elements of the first
    # three columns are surely modelled in three areas only (a bump under the others), so leaving one out
    # leaves two to vouch for them: too few. Given a baseline of one they read 10 % harder than healthy.
    def stiffer_edge_rows(reading):
        reading[[0, -1]] *= 1.10

    def areas(tumour_area=None):
        return eight_areas(tumour_area, stiffer_edge_rows)

    def analysed(levels):
        share = np.ones(levels["pressure_pa"].shape)
        share_sigma = np.full(share.shape, 0.005)
        share_sigma[levels["region"] >= 3, :, :3] = 0.2
        return contrast(levels, "force", share, share_sigma)

    healthy = areas()
    c = analysed(healthy)
    vouched_by_two = c.contrast[healthy["region"] < 3][:, [0, -1], 1:3]
    assert np.nanmax(np.abs(vouched_by_two)) < 0.06
    assert detect(healthy, c, PITCH) == []
    with_tumour = areas(tumour_area=1)
    found = detect(with_tumour, analysed(with_tumour), PITCH)
    assert len(found) == 1 and abs(found[0].x_m - EIGHT_AREAS_X[1]) < 1e-3


def test_an_element_beyond_the_baselines_range_of_one_is_within_it_of_its_part_of_the_face():
    # The physics misses the edge rows by 20 % in every area (they stiffen faster at finite strain), and one
    # of their elements is 12 % more sensitive than the others: its baseline is 1.22 (the face's median
    # between the edge rows' and the inner rows' levels is one), beyond what a baseline may correct of one,
    # but within it of its part's level. Bounded about one, it read 6 % harder than healthy tissue in every
    # area (a false tumour on a held-out phantom of the study).
    def stiffer_edge_rows(reading):
        reading[[0, -1]] *= 1.20
        reading[0, 7] *= 1.12

    healthy = eight_areas(None, stiffer_edge_rows)
    c = contrast(healthy, "force", np.ones(healthy["pressure_pa"].shape), np.full(healthy["pressure_pa"].shape, 0.005))
    assert abs(np.nanmean(c.contrast[:, 0, 7])) < 0.02  # noise: 2 % per element and record
    assert detect(healthy, c, PITCH) == []


def test_three_areas_over_one_large_tumour_do_not_paint_its_mirror_image_on_the_healthy_ones():
    # A large or deep tumour changes the load of the whole face in the areas either side of it too: their
    # middle columns carry more, their side columns less. The median of the other seven areas, three of them
    # over it, then expects too much in the middle of every healthy area and too little at its sides.
    records = []
    for r, x in enumerate(EIGHT_AREAS_X):
        for k, f in enumerate(FORCES):
            levels = levels_of(level_record(r, k, f, (x, 0.015), noise=0.02, seed=31 * r + k))
            if r in (2, 3, 4):
                change = np.ones((4, 15))
                change[:, 4:11] = 1.25 if r == 3 else 1.15
                change[:, :4] = change[:, 11:] = 0.90
                for name in ("pressure_pa", "element_force_N", "stiffness_pa"):
                    levels[name][0] *= change
            records.append(levels)
    levels = np.concatenate(records)
    c = contrast(levels, "force")
    healthy = np.isin(levels["region"], (0, 1, 5, 6, 7))
    middle, sides = c.contrast[healthy][:, :, 4:11], c.contrast[healthy][:, :, np.r_[0:4, 11:15]]
    assert abs(np.nanmean(middle)) < 0.01 and abs(np.nanmean(sides)) < 0.01
    found = detect(levels, c, PITCH)
    assert found and all(EIGHT_AREAS_X[2] - 0.004 <= t.x_m <= EIGHT_AREAS_X[4] + 0.004 for t in found)
    assert any(abs(t.x_m - EIGHT_AREAS_X[3]) < 1e-3 for t in found)
    assert "3 of them not homogeneous tissue at some level" in c.description


def test_areas_on_a_bump_keep_voting_for_each_other_and_a_tumours_do_not():
    from session.flatfield import MIN_VOUCHING, _voters

    # the physics' error on a bump (departures 1-4) is shared by the other areas on it, whose votes correct it
    assert _voters(np.array([0.4, 3.5, 2.8, 0.5, 0.3, 3.9, 0.6, 0.4])).all()
    assert list(_voters(np.array([0.4, 0.5, 9.0, 40.0, 0.3, 0.6, 0.4, 0.5]))) == [1, 1, 0, 0, 1, 1, 1, 1]
    # a level where every area departs alike (the physics off everywhere) sets none aside
    assert _voters(np.array([9.0, 12.0, 10.0, 11.0, 9.5])).all()
    # and at least MIN_VOUCHING + 1 always vote, the least departing
    assert list(_voters(np.array([50.0, 0.5, 0.4, 60.0, 0.6]))) == [1, 1, 1, 0, 1] and MIN_VOUCHING + 1 == 4
