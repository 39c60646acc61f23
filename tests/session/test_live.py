"""The live maps' flat field of a single frame (session/live.py): the face's own pattern is taken out, a
stiffer spot under the face is marked where it is, and healthy tissue raises none."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hardware.interfaces import TactileConstraints
from session.live import LiveMaps
from session.synthetic import level_record

SENSOR = TactileConstraints()
FORCES = (1.0, 2.0, 3.0)
# the rigid face's own pattern: its two edge rows loaded harder than the inner ones
FACE = np.array([2.2, 1.0, 1.0, 2.2])[:, None] * np.ones(SENSOR.shape)


def _with_face(record):
    return dataclasses.replace(record, pressure_pa=record.pressure_pa * FACE, stiffness_pa=record.stiffness_pa * FACE,
                               element_force_N=record.element_force_N * FACE)


def _area(region: int, x: float, tumour: bool = False):
    return [_with_face(level_record(region, k, f, (x, 0.015), noise=0.02, seed=11 * region + k,
                                    tumours_xy_m=((x, 0.015),) if tumour else (), tumour_factor=1.5))
            for k, f in enumerate(FORCES)]


@pytest.fixture
def maps():
    live = LiveMaps(SENSOR, min_indentation_m=0.2e-3)
    for region, x in enumerate((0.012, 0.020, 0.028)):
        for record in _area(region, x):
            live.add(record)
    return live


def test_a_frame_is_flat_fielded_once_enough_areas_vouch_for_the_pattern(maps):
    healthy = _area(7, 0.060)[1]
    assert maps.frame_contrast(healthy.pressure_pa, "force", 2.0) is None  # three areas: none may vouch
    for record in _area(3, 0.036):
        maps.add(record)
    for name, values in (("force", healthy.pressure_pa), ("stiffness", healthy.stiffness_pa)):
        frame = maps.frame_contrast(values * 1.3, name, 2.1)  # a frame between levels, pressed harder
        assert frame is not None and frame.level_N == 2.0
        assert np.nanmax(np.abs(frame.contrast)) < 0.1 < np.ptp(values / values.mean())  # the face's edges are gone
        assert frame.spots == ()
    for values, force in ((np.zeros(SENSOR.shape), 2.0), (healthy.pressure_pa, float("nan"))):  # no contact
        frame = maps.frame_contrast(values, "force", force)
        assert np.isnan(frame.contrast).all() and frame.spots == ()


def test_a_stiffer_spot_under_the_face_is_marked_where_it_is(maps):
    for record in _area(3, 0.036):
        maps.add(record)
    over = _area(8, 0.044, tumour=True)[2]
    for name, values in (("force", over.pressure_pa), ("stiffness", over.stiffness_pa)):
        frame = maps.frame_contrast(values, name, 3.0)
        assert len(frame.spots) == 1
        (i, j), = frame.spots
        offset = SENSOR.element_offsets_m()[i, j]
        assert np.hypot(*offset) < 2.5e-3  # the tumour lies under the face's centre
        assert frame.contrast[i, j] > 0.3 and frame.z[i, j] > 5


def _physics(levels, face=FACE):
    """What the composition root computes (app.live_physics): the face's pattern on every record, exactly."""
    share = np.broadcast_to(face / face.mean(), levels["pressure_pa"].shape).copy()
    pattern = dataclasses.make_dataclass("Pattern", ["share", "sigma", "modes"])(share, 0.0 * share, None)
    return {"stiffness": pattern, "force": pattern}


def test_where_physics_is_expected_the_records_it_covers_are_judged_and_the_later_ones_wait(maps):
    maps.physics_expected = True
    for record in _area(3, 0.036, tumour=True):
        maps.add(record)
    assert not maps.flat_field_ready() and maps.tumours() == [] and maps.pending(0) and maps.pending(3)
    three = maps.levels()[:9]
    maps.set_physics(9, _physics(three), "three areas' block")
    assert not maps.flat_field_ready()  # three areas cannot vouch for each other, physics or not
    maps.set_physics(12, _physics(maps.levels()), "four areas' block")
    assert maps.flat_field_ready() and not maps.pending(3)
    assert [round(t.x_m * 1e3) for t in maps.tumours() if t.source == "stiffness"] == [36]
    for record in _area(4, 0.044, tumour=True):
        maps.add(record)
    assert maps.pending(4) and not maps.pending(3)
    assert len(maps.tumours()) == 2  # the fifth area's tumour waits for its physics
    top = maps.stitched().levels[-1]
    waiting = np.isfinite(top.pressure_pa).sum() - np.isfinite(top.extra["stiffness_contrast"]).sum()
    assert waiting == 8 * 30  # its 8 x 30 mm has no contrast yet (1 mm cells)
    maps.set_physics(15, _physics(maps.levels()), "five areas' block")
    assert sorted({round(t.x_m * 1e3) for t in maps.tumours()}) == [36, 44] and not maps.pending(4)
    top = maps.stitched().levels[-1]
    assert np.isfinite(top.pressure_pa).sum() == np.isfinite(top.extra["stiffness_contrast"]).sum()
    with pytest.raises(ValueError, match="physics for 16 records of 15"):
        maps.set_physics(16, _physics(maps.levels()), "")
    with pytest.raises(ValueError, match="do not cover"):
        maps.set_physics(12, _physics(maps.levels()), "")
    maps.drop_physics()
    assert not maps.physics_expected and not maps.pending(4) and len(maps.tumours()) == 4


def test_the_physics_pattern_is_what_the_contrast_divides_out(maps):
    for record in _area(3, 0.036):
        maps.add(record)
    maps.physics_expected = True
    wrong = np.ones(SENSOR.shape)
    wrong[:, 7] = 0.5  # a physics that expects half the load under one column
    maps.set_physics(12, _physics(maps.levels(), FACE * wrong), "a wrong block")
    # the baseline is estimated over the physics and stays within BASELINE_RANGE of it: the column reads hard
    assert {(round(t.y_m * 1e3)) for t in maps.tumours()} == {15}
