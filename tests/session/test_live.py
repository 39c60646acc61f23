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
