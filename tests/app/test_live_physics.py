"""The live maps' physics computed beside the console: the paper's flat phantom palpated by the simulated rig
(its continuum tissue), its first eight areas of nine judged as the console judges them live."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.config import load_config
from app.live_physics import LivePhysics
from app.recording import record_simulation, session_info
from hardware.interfaces import TactileConstraints
from session.live import LiveMaps
from session.reader import open_session

FLAT_EXTENT_M = (0.0, 0.072, 0.0, 0.030)  # the autopilot plan's (tissue/phantoms/flat.toml)
TUMOURS_XY_M = ((0.012, 0.015), (0.036, 0.015), (0.060, 0.015))


@pytest.fixture(scope="module")
def flat_session(tmp_path_factory):
    """(the first eight areas' levels, what the console's session says of itself)."""
    config = load_config(None, {})
    path = tmp_path_factory.mktemp("flat") / "flat.h5"
    record_simulation(path, config)
    levels = open_session(path).levels
    return levels[levels["region"] < 8], session_info(config)


def _maps(levels) -> LiveMaps:
    maps = LiveMaps(TactileConstraints(), min_indentation_m=0.2e-3)
    for row in levels:  # kept as add() keeps a LevelRecord, from the recorded rows
        maps._rows.append(tuple(row))
        maps._regions.add(int(row["region"]))
    maps._dirty = True
    return maps


def _stiffness_spots(maps: LiveMaps) -> list[tuple[float, float]]:
    return [(t.x_m, t.y_m) for t in maps.tumours() if t.source == "stiffness"]


def _judged(levels, records, patterns, description) -> list[tuple[float, float]]:
    """The stiffness map's spots once the physics answered for ``records`` of ``levels``."""
    maps = _maps(levels)
    maps.physics_expected = True
    maps.set_physics(records, patterns, description)
    return _stiffness_spots(maps)


def _answer(qtbot, physics: LivePhysics, levels, signal: str = "ready") -> tuple:
    """What ``physics`` says to ``levels`` (its ``signal``'s arguments); its worker is closed after."""
    try:
        with qtbot.waitSignal(getattr(physics, signal), timeout=120_000) as answered:
            physics.request(levels)
    finally:
        physics.close()
    return answered.args


def _near_a_tumour(xy) -> bool:
    return min(math.dist(xy, t) for t in TUMOURS_XY_M) < 2e-3


def test_with_the_physics_computed_aside_the_live_maps_find_the_tumours_and_not_the_tissues_ends(
        qtbot, flat_session):
    levels, info = flat_session
    without = _stiffness_spots(_maps(levels))
    assert sum(not _near_a_tumour(xy) for xy in without) >= 2  # the other areas' pattern fails at the ends

    physics = LivePhysics(info, extent_m=FLAT_EXTENT_M)
    try:
        with qtbot.waitSignal(physics.ready, timeout=120_000) as answered:
            physics.request(levels)
            physics.request(levels[:7])  # asked while busy: only the latest is computed next
        assert physics.busy
        physics.close()
    finally:
        physics.close()
    records, patterns, description = answered.args
    assert records == len(levels) and "rebuilt from the session" in description
    found = _judged(levels, records, patterns, description)
    assert all(_near_a_tumour(xy) for xy in found)
    assert all(any(math.dist(xy, t) < 2e-3 for xy in found) for t in TUMOURS_XY_M)


def test_without_a_plan_the_newest_areas_far_edge_is_not_read_as_a_tumour(qtbot, flat_session):
    # A real rig has no plan: where the tissue ends is not known. Taken to end where the areas palpated so far
    # do, after six areas the sixth's far edge (x = 48 mm) read as two tumours, z 6.5 and 7.1.
    levels, info = flat_session
    levels = levels[levels["region"] < 6]
    records, patterns, description = _answer(qtbot, LivePhysics(info), levels)
    assert "where the tissue ends not known" in description
    found = _judged(levels, records, patterns, description)
    assert all(_near_a_tumour(xy) for xy in found)
    assert all(any(math.dist(xy, t) < 2e-3 for xy in found) for t in TUMOURS_XY_M[:2])


def test_areas_that_cannot_be_modelled_are_said_so_and_nothing_is_left_running(qtbot, flat_session):
    levels, info = flat_session
    unmodelled = levels[:3].copy()
    unmodelled["onset_height_m"] = np.nan  # no element ever touched
    physics = LivePhysics(info)
    reason, = _answer(qtbot, physics, unmodelled, "failed")
    assert "no element of this session ever touched the tissue" in reason
    assert not physics.busy


def test_a_held_worker_is_sent_nothing_and_one_killed_under_way_is_said_so(qtbot, flat_session):
    levels, info = flat_session
    unmodelled = levels[:3].copy()
    unmodelled["onset_height_m"] = np.nan  # answered at once, with a reason
    physics = LivePhysics(info)
    try:
        physics.hold(True)
        physics.request(unmodelled)
        assert not physics.busy  # kept until the loop leaves force control
        physics.hold(False)
        assert physics.busy
        process = physics._worker[0]
        process.kill()
        process.join()
        physics.hold(True)
        physics.request(unmodelled)  # kept for later
        with qtbot.waitSignal(physics.failed, timeout=60_000) as answered:
            physics.hold(False)
        assert "ended without an answer" in answered.args[0]
        assert not physics.busy
        with qtbot.waitSignal(physics.failed, timeout=60_000) as answered:
            physics.request(unmodelled)  # another worker
        assert "no element of this session ever touched the tissue" in answered.args[0]
    finally:
        physics.close()
