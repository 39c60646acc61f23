"""The reviewer never blocks (issue 50): its analysis runs in a worker while the window answers, an older request's
result is never shown, and a closed window leaves no thread behind."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from PySide6 import QtCore, QtWidgets

from session.analysis import SessionAnalysis
from session.depth import DepthModel
from tests.session.test_model_depth import _reference
from tests.session.test_review import _analysis_worker_ended, child  # noqa: F401 - the fixture, for this module
from widgets.review import ReviewWindow, analysis_worker
from widgets.review.analysis_worker import THREAD_NAME
from widgets.tactile_map import TactileMapWidget

WAIT_MS = 20000


class SlowPhysics:
    """A physics factory that reports a quarter done, then waits for :attr:`release` (a finite-element build the
    test controls) and gives no physics."""

    def __init__(self):
        self.entered = threading.Event()
        self.release = threading.Event()
        self.builds = 0

    def __call__(self, session, progress):
        self.builds += 1
        progress(0.25, "condensing the tissue onto its surface")
        self.entered.set()
        assert self.release.wait(WAIT_MS / 1000)
        return None


@pytest.fixture
def slow():
    physics = SlowPhysics()
    yield physics
    physics.release.set()  # a failed test never leaves the worker waiting


def reviewer(qtbot, tmp_path, physics, depth_model=None) -> ReviewWindow:
    settings = QtCore.QSettings(str(tmp_path / "review.ini"), QtCore.QSettings.Format.IniFormat)
    w = ReviewWindow(settings=settings, physics=physics, depth_model=depth_model)
    qtbot.addWidget(w)
    w.resize(1200, 800)
    w.show()
    return w


def counted(signal) -> list:
    seen = []
    signal.connect(lambda *args: seen.append(args))
    return seen


def worker_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == THREAD_NAME]


def test_the_window_answers_while_the_physics_is_built_and_lands_on_the_findings(qtbot, tmp_path, recorded, slow):
    w = reviewer(qtbot, tmp_path, {"slow model": slow})
    assert w.open_file(recorded[0])
    qtbot.waitUntil(slow.entered.is_set, timeout=WAIT_MS)
    # the session's table, timeline and maps, while the worker is in the middle of the build
    table = child(w, QtWidgets.QTableWidget, "regionTable")
    assert (table.rowCount(), table.columnCount()) == (3, 3)
    assert w.findChild(QtWidgets.QWidget, "timeline").points_drawn() > 0
    pressure = child(w, TactileMapWidget, "pressureMap")
    levels = w.session.levels
    assert np.allclose(pressure.data_pa(), levels["pressure_pa"][0], rtol=1e-6) and not pressure.contrast_view()
    table.setCurrentCell(2, 1)
    assert np.allclose(pressure.data_pa(), levels["pressure_pa"][7], rtol=1e-6)
    state = child(w, QtWidgets.QLabel, "analysisState")
    progress = child(w, QtWidgets.QProgressBar, "analysisProgress")
    qtbot.waitUntil(lambda: progress.maximum() == 100 and progress.value() == 25)
    assert state.isVisible() and state.text() == ("Analysing… (the flat field's tissue model: condensing the "
                                                  "tissue onto its surface)")
    tabs = child(w, QtWidgets.QTabWidget, "tabs")
    assert tabs.currentIndex() == 0 and tabs.tabText(1) == "Whole tissue (analysing…)"
    assert w.analysing and w.analysis is None and child(w, QtWidgets.QTableWidget, "tumourTable").rowCount() == 0
    stitched = w.findChild(QtWidgets.QWidget, "stitchedMap")
    assert not np.isfinite(stitched.values()).any()

    with qtbot.waitSignal(w.analysis_done, timeout=WAIT_MS):
        slow.release.set()
    assert not w.analysing and not state.isVisible() and not progress.isVisible()
    assert tabs.currentIndex() == 1 and tabs.tabText(1) == "Whole tissue"  # opens on the findings
    assert child(w, QtWidgets.QLabel, "analysisSummary").text().startswith("0 tumour(s) in the stiffness map")
    assert np.isfinite(stitched.values()).any()
    assert pressure.contrast_view()  # the record maps turn to the contrast once there is one


def test_a_reviewer_who_went_elsewhere_meanwhile_is_left_there(qtbot, tmp_path, recorded, slow):
    w = reviewer(qtbot, tmp_path, {"slow model": slow})
    assert w.open_file(recorded[0])
    qtbot.waitUntil(slow.entered.is_set, timeout=WAIT_MS)
    table = child(w, QtWidgets.QTableWidget, "regionTable")
    cell = table.visualItemRect(table.item(1, 2)).center()
    qtbot.mouseClick(table.viewport(), QtCore.Qt.MouseButton.LeftButton, pos=cell)
    assert "Region 2, level 3" in child(w, QtWidgets.QLabel, "recordInfo").text()
    stiffness = child(w, TactileMapWidget, "stiffnessMap")
    child(stiffness, QtWidgets.QCheckBox, "contrastView").click()  # asked for the contrast before there is one
    child(stiffness, QtWidgets.QCheckBox, "contrastView").click()  # ... and back to the reading
    with qtbot.waitSignal(w.analysis_done, timeout=WAIT_MS):
        slow.release.set()
    assert child(w, QtWidgets.QTabWidget, "tabs").currentIndex() == 0
    assert "Region 2, level 3" in child(w, QtWidgets.QLabel, "recordInfo").text()
    assert not stiffness.contrast_view()


def test_a_result_for_an_older_request_is_never_shown(qtbot, tmp_path, recorded, monkeypatch):
    """An analysis overtaken before it tells any progress (here, before it starts) is dropped."""
    entered, release = threading.Event(), threading.Event()
    run = SessionAnalysis.run.__func__

    class FirstRunWaits(SessionAnalysis):
        @classmethod
        def run(cls, *args, **kwargs):
            if not entered.is_set():
                entered.set()
                assert release.wait(WAIT_MS / 1000)
            return run(SessionAnalysis, *args, **kwargs)

    monkeypatch.setattr(analysis_worker, "SessionAnalysis", FirstRunWaits)
    w = reviewer(qtbot, tmp_path, {})
    shown = counted(w.analysis_done)
    assert w.open_file(recorded[0])
    qtbot.waitUntil(entered.is_set, timeout=WAIT_MS)
    child(w, QtWidgets.QDoubleSpinBox, "accuracySpin").setValue(50.0)  # healthy tissue this scattered: no tumour
    w.reanalyse()
    release.set()
    qtbot.waitUntil(lambda: not w.analysing, timeout=WAIT_MS)
    qtbot.waitUntil(lambda: not worker_threads(), timeout=WAIT_MS)
    assert len(shown) == 1 and w.analysis.params.detect.accuracy == pytest.approx(0.5)
    assert w.tumours == [] and child(w, QtWidgets.QTableWidget, "tumourTable").rowCount() == 0


def test_a_session_opened_while_another_is_analysed_shows_only_its_own(qtbot, tmp_path, recorded, reference_recorded,
                                                                       slow):
    w = reviewer(qtbot, tmp_path, {"slow model": slow})
    shown = counted(w.analysis_done)
    assert w.open_file(recorded[0])
    qtbot.waitUntil(slow.entered.is_set, timeout=WAIT_MS)
    assert w.open_file(reference_recorded)  # the first session's build cannot be interrupted: it ends, unseen
    with qtbot.waitSignal(w.analysis_done, timeout=WAIT_MS):
        slow.release.set()
    qtbot.waitUntil(lambda: not worker_threads(), timeout=WAIT_MS)
    assert len(shown) == 1 and w.analysis.session is w.session and w.session.path == reference_recorded


def test_new_options_for_the_same_physics_wait_for_its_build_rather_than_start_again(qtbot, tmp_path, recorded,
                                                                                     slow):
    w = reviewer(qtbot, tmp_path, {"slow model": slow})
    shown = counted(w.analysis_done)
    assert w.open_file(recorded[0])
    qtbot.waitUntil(slow.entered.is_set, timeout=WAIT_MS)
    child(w, QtWidgets.QDoubleSpinBox, "accuracySpin").setValue(50.0)
    w.reanalyse()
    with qtbot.waitSignal(w.analysis_done, timeout=WAIT_MS):
        slow.release.set()
    assert slow.builds == 1 and len(shown) == 1 and w.analysis.params.detect.accuracy == pytest.approx(0.5)


class EndlessPhysics:
    """A build that reports progress as it works, and would never end by itself."""

    def __init__(self):
        self.stopped = threading.Event()

    def __call__(self, session, progress):
        rng = np.random.default_rng(0)
        try:
            while True:
                progress(0.5, "condensing the tissue onto its surface")
                np.linalg.inv(rng.random((60, 60)) + 60 * np.eye(60))
        finally:
            self.stopped.set()


def test_choosing_other_physics_stops_the_build_no_request_needs(qtbot, tmp_path, recorded):
    endless = EndlessPhysics()
    w = reviewer(qtbot, tmp_path, {"endless": endless})
    assert w.open_file(recorded[0])
    qtbot.waitUntil(lambda: child(w, QtWidgets.QProgressBar, "analysisProgress").value() == 50, timeout=WAIT_MS)
    combo = child(w, QtWidgets.QComboBox, "physicsCombo")
    with qtbot.waitSignal(w.analysis_done, timeout=WAIT_MS):
        combo.setCurrentText("none (session baseline only)")
    assert endless.stopped.is_set() and "no physics" in w.analysis.flat_field


def test_closing_while_the_physics_is_built_stops_it_and_leaves_no_thread(qtbot, tmp_path, recorded):
    endless = EndlessPhysics()
    w = reviewer(qtbot, tmp_path, {"endless": endless})
    shown = counted(w.analysis_done)
    assert w.open_file(recorded[0])
    qtbot.waitUntil(lambda: child(w, QtWidgets.QProgressBar, "analysisProgress").value() == 50, timeout=WAIT_MS)
    w.close()
    qtbot.waitUntil(lambda: endless.stopped.is_set() and not worker_threads(), timeout=WAIT_MS)
    assert shown == [] and w.analysis is None


def test_closing_while_a_build_that_cannot_be_interrupted_runs_returns_at_once(qtbot, tmp_path, recorded, slow):
    w = reviewer(qtbot, tmp_path, {"slow model": slow})
    shown = counted(w.analysis_done)
    assert w.open_file(recorded[0])
    qtbot.waitUntil(slow.entered.is_set, timeout=WAIT_MS)
    w.close()  # returns while the build still waits
    assert worker_threads() and not w.analysing
    slow.release.set()
    qtbot.waitUntil(lambda: not worker_threads(), timeout=WAIT_MS)
    assert shown == [] and w.analysis is None


def depth_reviewer(qtbot, tmp_path, reference_recorded) -> ReviewWindow:
    """A reviewer with the depth model and, for the Winkler recording to show its tumours, a reference palpation."""
    w = reviewer(qtbot, tmp_path, {}, DepthModel.for_session)
    _reference(reference_recorded).save(tmp_path / "reference.json")
    assert w.set_reference(tmp_path / "reference.json")
    return w


def test_the_reviewer_tells_each_finite_element_solve_of_the_depth_model(qtbot, tmp_path, recorded,
                                                                         reference_recorded, solves):
    solves.go.clear()
    w = depth_reviewer(qtbot, tmp_path, reference_recorded)
    assert w.open_file(recorded[0])
    qtbot.waitUntil(solves.entered.is_set, timeout=WAIT_MS)
    state = child(w, QtWidgets.QLabel, "analysisState")
    progress = child(w, QtWidgets.QProgressBar, "analysisProgress")
    qtbot.waitUntil(lambda: state.text().startswith("Analysing… (finite-element solve 1: sphere "), timeout=WAIT_MS)
    assert " mm deep; depth model, stiffness map: " in state.text()
    assert progress.maximum() == 100 and 0 < progress.value() < 100
    with qtbot.waitSignal(w.analysis_done, timeout=WAIT_MS):
        solves.go.set()
    assert w.analysis.tumours and solves.started > 1


def test_closing_while_the_depth_model_solves_stops_the_analysis_at_its_next_solve(qtbot, tmp_path, recorded,
                                                                                  reference_recorded, solves):
    solves.go.clear()
    w = depth_reviewer(qtbot, tmp_path, reference_recorded)
    shown = counted(w.analysis_done)
    assert w.open_file(recorded[0])
    qtbot.waitUntil(solves.entered.is_set, timeout=WAIT_MS)
    w.close()
    assert not w.analysing
    solves.go.set()  # the solve under way ends; the analysis needs more, and starts none
    qtbot.waitUntil(lambda: not worker_threads(), timeout=WAIT_MS)
    assert solves.started == 1 and shown == [] and w.analysis is None
