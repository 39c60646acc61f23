"""The live maps' physics computed beside the console: a 40 mm block of the paper's flat phantom, with two of its
tumours, palpated by the simulated rig (its continuum tissue), judged as the console judges it live. (Shorter
than the paper's 72 mm: the rebuilt block's solve grows with the cube of its extent, and on a busy two-core
machine the whole phantom took past the suite's two minutes.)"""

from __future__ import annotations

import math

import numpy as np
import pytest
import tomli_w

from app import live_physics
from app.config import load_config
from app.fastforward import FastForward
from app.live_physics import LivePhysics
from app.recording import session_info
from app.rigs import build_rig
from control.messages import FaultRaised, LevelRecorded
from hardware.interfaces import TactileConstraints
from hardware.settings import read_toml
from session.format import LEVEL_DTYPE, level_row
from session.live import LiveMaps
from tissue.phantom import PHANTOM_DIR

EXTENT_M = (0.0, 0.040, 0.0, 0.030)  # the block's, as an autopilot plan gives it
TUMOURS_XY_M = ((0.012, 0.015), (0.028, 0.015))


@pytest.fixture(scope="module")
def flat_session(tmp_path_factory):
    """(the five areas' levels as the console receives them, what the console's session says of itself). Its
    levels come straight from the loop's events: writing the session's ticks and frames to a file first took
    most of this module's time on a busy machine."""
    folder = tmp_path_factory.mktemp("flat")
    data = read_toml(PHANTOM_DIR / "flat.toml", "phantom file")
    block = data["phantom"]
    block.update(name="flat-40", length_m=EXTENT_M[1])
    block["inclusions"] = block["inclusions"][:2]
    block["inclusions"][1].update(centre_xy_m=list(TUMOURS_XY_M[1]), depth_m=0.004)  # shows by 5 N
    (folder / "flat-40.toml").write_text(tomli_w.dumps(data), encoding="utf-8")
    # the scripted operator moves between areas 3.5 mm over their approach height, not at the default 45 mm:
    # climbing there and back was a fifth of the palpation's time, and what is judged here is the levels
    config = load_config(None, {"rig": {"phantom": str(folder / "flat-40.toml")},
                                "control": {"ramp": {"force_max_N": 5.0}},
                                "sim": {"operator": {"travel_height_m": 0.030}}})
    rig = build_rig(config.rig)
    info = session_info(config, rig)
    rows = []
    with FastForward(config.control, rig) as palpating:
        while not rig.master.finished:
            assert palpating.now_s < 600.0, "the scripted operator did not finish"
            palpating.run_for(0.5)
            for event in palpating.events:
                assert not isinstance(event, FaultRaised), event
                if isinstance(event, LevelRecorded):
                    rows.append(level_row(event.record))
            palpating.clear()
    return np.array(rows, dtype=LEVEL_DTYPE), info


@pytest.fixture(autouse=True)
def at_the_tests_priority(monkeypatch):
    """The workers at the suite's own priority: the console's lower ones yield to the suite's other tests run
    beside them, and on a loaded machine took the end-to-end test past the suite's timeout."""
    monkeypatch.setattr(live_physics, "NICENESS", 0)
    monkeypatch.setattr(live_physics, "FULL_NICENESS", 0)


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

    physics = LivePhysics(info, extent_m=EXTENT_M)
    try:
        with qtbot.waitSignal(physics.ready, timeout=120_000) as answered:
            physics.request(levels)
            physics.request(levels[levels["region"] < 4])  # asked while busy: only the latest is computed next
        assert physics.busy
        physics.close()
    finally:
        physics.close()
    records, patterns, description = answered.args
    assert records == len(levels) and "rebuilt from the session" in description
    assert "meshed on" not in description  # solved in full
    found = _judged(levels, records, patterns, description)
    assert all(_near_a_tumour(xy) for xy in found)
    assert all(any(math.dist(xy, t) < 2e-3 for xy in found) for t in TUMOURS_XY_M)


def test_a_quick_answer_is_followed_by_the_full_solve_of_the_same_levels(qtbot, flat_session):
    # one area's block (8 x 30 mm) keeps the three solves to seconds
    levels, info = flat_session
    first = levels[levels["region"] == 0]
    lower = first.copy()
    lower["onset_height_m"] -= 0.5e-3  # another surface over the same extent: a quick answer, then a full one
    x0, y0 = (float(v) for v in first["tsi_position_m"][0, :2])
    physics = LivePhysics(info, extent_m=(x0 - 0.004, x0 + 0.004, y0 - 0.015, y0 + 0.015))
    answers = []
    physics.ready.connect(lambda records, patterns, description: answers.append(description))
    try:
        with qtbot.waitSignal(physics.ready, timeout=60_000):
            physics.request(first)
        physics.request(lower)
        qtbot.waitUntil(lambda: len(answers) == 3, timeout=90_000)
    finally:
        physics.close()
    assert ["meshed on" in description for description in answers] == [False, True, False]


def test_without_a_plan_the_newest_areas_far_edge_is_not_read_as_a_tumour(qtbot, flat_session):
    # A real rig has no plan: where the tissue ends is not known. Taken to end where the areas palpated so far
    # do, after six areas of the 72 mm phantom the sixth's far edge (x = 48 mm) read as two tumours, z 6.5 and 7.1.
    # Here four areas of five: the tissue goes on 8 mm beyond the fourth's far edge (x = 32 mm).
    levels, info = flat_session
    levels = levels[levels["region"] < 4]
    records, patterns, description = _answer(qtbot, LivePhysics(info), levels)
    assert "where the tissue ends not known" in description
    found = _judged(levels, records, patterns, description)
    # the newest area's own tumour is drawn up to 2.2 mm towards the end not known (measured: 30.2 for 28 mm)
    assert all(min(math.dist(xy, t) for t in TUMOURS_XY_M) < 2.5e-3 for xy in found)
    assert any(math.dist(xy, TUMOURS_XY_M[0]) < 2e-3 for xy in found)


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
        process = physics._quick.process
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


def test_the_terminal_shows_the_findings_being_computed_and_how_long_they_took(qapp):
    from PySide6 import QtCore

    from app.gui import wire_findings_progress

    class Physics(QtCore.QObject):
        ready = QtCore.Signal(int, object, str)
        failed = QtCore.Signal(str)
        progress = QtCore.Signal(int, float, str)

    lines: list[list[tuple[float, str]]] = []
    physics = Physics()

    def bar():
        lines.append([])
        return lambda fraction, text: lines[-1].append((fraction, text))

    wire_findings_progress(physics, bar)
    physics.progress.emit(28, 0.0, "starting")
    physics.progress.emit(28, 1.0, "the face's contact on record 28 of 28")
    physics.ready.emit(28, {}, "")
    physics.ready.emit(28, {}, "")  # the full solve behind it: no line of its own
    physics.progress.emit(35, 0.5, "condensing the tissue onto its surface")
    physics.failed.emit("no element touched")
    assert [[(f, text.split(" in ")[0].split(" after ")[0]) for f, text in line] for line in lines] == [
        [(0.0, "findings (28 levels): starting"), (0.99, "findings (28 levels): the face's contact on record 28 of 28"),
         (1.0, "findings (28 levels)")],
        [(0.5, "findings (35 levels): condensing the tissue onto its surface"),
         (1.0, "no findings' tissue model")]]
