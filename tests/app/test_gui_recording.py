"""The console records every controller run to a session file and opens recorded sessions.

The console is the real window on the fast-forward bridge (the real control loop on the simulated rig),
wired to a :class:`app.gui.SessionRecording` as ``run_gui`` wires it. Waits are conditions, never sleeps.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from PySide6 import QtCore, QtGui, QtWidgets

from app.bridge import ControllerBridge
from app.config import AppConfig
from app.gui import wire_depth_model, wire_recording
from app.recording import SessionRecording, session_info
from app.rigs import RigSpec, plan_for_rig
from control.config import ControlConfig, MasterMapping, RampSettings
from session.format import EventKind
from session.info import sessions_dir
from session.reader import SessionFileError, open_session
from widgets.live_window import LiveWindow
from widgets.review import RecentSessions, ReviewWindow
from widgets.sz_switch import SzSwitch

RAMP = RampSettings(force_min_N=0.5, force_max_N=2.0, force_step_N=0.5)
CONFIG = ControlConfig(ramp=RAMP, master=MasterMapping(jog_speed_m_s=0.04))
# the TSI starts 1.5 mm above the flat phantom, as an operator starts force control: a seek that touches nothing
# goes no deeper than 2.4 mm (control.safety.blind_seek_depth_m)
SPEC = RigSpec(master="none", sim={"robot": {"home_m": (0.036, 0.015, 0.0265)}})
SPEED = 8.0
WAIT_MS = 30_000


@pytest.fixture
def info():
    return session_info(AppConfig(control=CONFIG, rig=SPEC), spec=SPEC)


@pytest.fixture
def bridge():
    made = ControllerBridge.for_fast_forward(CONFIG, SPEC, speed=SPEED)
    yield made
    made.shutdown()


@pytest.fixture
def recent(tmp_path):
    return RecentSessions(QtCore.QSettings(str(tmp_path / "recent.ini"), QtCore.QSettings.Format.IniFormat))


def make_console(qtbot, tmp_path, bridge, recent):
    settings = QtCore.QSettings(str(tmp_path / "console.ini"), QtCore.QSettings.Format.IniFormat)
    window = LiveWindow(bridge, config=CONFIG, plan=plan_for_rig(SPEC, CONFIG), settings=settings,
                        sessions_folder=sessions_dir(), recent=recent)
    qtbot.addWidget(window)
    window.show()
    qtbot.waitExposed(window)
    return window


def start(qtbot, window, bridge, recording):
    with qtbot.waitSignal(recording.recording_started, timeout=WAIT_MS) as started:
        bridge.start()
    qtbot.waitUntil(lambda: window.findChild(SzSwitch, "szSwitch").state() is not None, timeout=WAIT_MS)
    return started.args[0]


def logged(window, fragment: str) -> bool:
    return any(fragment in line for line in window.messages().lines())


def test_a_region_run_in_the_console_is_recorded_with_its_levels_and_a_note(qtbot, tmp_path, bridge, recent,
                                                                             info):
    window = make_console(qtbot, tmp_path, bridge, recent)
    recording = SessionRecording(bridge, info)
    wire_recording(window, recording)
    path = start(qtbot, window, bridge, recording)
    panel = window.session_panel()
    assert path.startswith(str(sessions_dir())) and path.endswith(".h5")
    assert panel.state() == "recording" and panel.path_text() == path
    assert logged(window, f"Recording the session to {path}")

    note = window.findChild(QtWidgets.QLineEdit, "noteEdit")
    qtbot.keyClicks(note, "stiff spot near the lower edge")
    qtbot.mouseClick(window.findChild(QtWidgets.QPushButton, "addNoteButton"), QtCore.Qt.MouseButton.LeftButton)
    assert note.text() == "" and logged(window, "Note: stiff spot near the lower edge")
    # issue 50: what the console tells the surgeon is in the session too, stamped when it was told
    window.findings_told.emit("Area 1: stiffness map: tumour at x 12.0 mm, y 15.0 mm, first at 1 N")

    qtbot.mouseClick(window.findChild(QtWidgets.QPushButton, "szForce"), QtCore.Qt.MouseButton.LeftButton)
    done = window.findChild(QtWidgets.QLabel, "regionDone")
    qtbot.waitUntil(lambda: done.property("done") is True, timeout=WAIT_MS)
    with qtbot.waitSignal(recording.recording_stopped, timeout=WAIT_MS) as stopped:
        bridge.stop()
    assert stopped.args[0] == path and "4 force levels" in stopped.args[1]
    assert recording.recorder is None and panel.state() == "stopped"
    assert not panel.findChild(QtWidgets.QLineEdit, "noteEdit").isEnabled()  # nothing to attach a note to
    assert recent.paths() == [Path(path).resolve()]

    with open_session(path) as session:
        assert session.closed_cleanly and not session.recovered
        levels = session.levels
        assert len(levels) == 4
        np.testing.assert_allclose(levels["force_desired_N"], [0.5, 1.0, 1.5, 2.0])
        assert np.all(levels["region"] == 0)
        assert np.all(np.isfinite(levels["indentation_m"]))
        kinds = [e["kind"] for e in session.event_dicts()]
        assert kinds.count(EventKind.LEVEL) == 4 and EventKind.REGION_DONE in kinds
        assert kinds[-1] == EventKind.CLOSED
        notes = [e for e in session.event_dicts() if e["kind"] == EventKind.NOTE]
        assert [n["text"] for n in notes] == [
            "stiff spot near the lower edge",
            "Console told the surgeon: Area 1: stiffness map: tumour at x 12.0 mm, y 15.0 mm, first at 1 N"]
        t0, t1 = session.time_span_s()
        assert t0 <= notes[0]["t_s"] <= t1  # stamped with the loop's clock
        ticks = session.tick_rows(0, 10**9, ["tick"])
        assert len(ticks) > 1000
        np.testing.assert_array_equal(ticks["tick"], np.arange(ticks["tick"][0], ticks["tick"][0] + len(ticks)))
        assert len(session.frames()) > 0

    review = window.open_session(path)
    assert isinstance(review, ReviewWindow) and review.session is not None
    told = review.findChild(QtWidgets.QLabel, "findingsTold").text()  # beside the reviewer's own analysis
    assert told.startswith("What the console told the surgeon:\nt = ")
    assert told.endswith("s: Area 1: stiffness map: tumour at x 12.0 mm, y 15.0 mm, first at 1 N")
    assert window.review_windows() == [review]
    review.close()
    qtbot.waitUntil(lambda: window.review_windows() == [], timeout=WAIT_MS)


def test_each_controller_run_gets_its_own_file(qtbot, tmp_path, bridge, recent, info):
    window = make_console(qtbot, tmp_path, bridge, recent)
    recording = SessionRecording(bridge, info)
    wire_recording(window, recording)
    first = start(qtbot, window, bridge, recording)
    with qtbot.waitSignal(recording.recording_stopped, timeout=WAIT_MS):
        bridge.stop()
    second = start(qtbot, window, bridge, recording)
    assert second != first
    with qtbot.waitSignal(recording.recording_stopped, timeout=WAIT_MS):
        bridge.stop()
    for path in (first, second):
        with open_session(path) as session:
            assert session.event_dicts()[-1]["kind"] == EventKind.CLOSED


def test_a_recorder_that_cannot_start_is_shown_and_control_goes_on(qtbot, tmp_path, bridge, recent, info):
    window = make_console(qtbot, tmp_path, bridge, recent)
    recording = SessionRecording(bridge, info, recorder_options={"min_free_bytes": 2**62})
    wire_recording(window, recording)
    with qtbot.waitSignal(recording.problem, timeout=WAIT_MS) as problem:
        bridge.start()
    assert "NOT being recorded" in problem.args[0] and "MB free" in problem.args[0]
    panel = window.session_panel()
    assert panel.state() == "problem" and "NOT being recorded" in panel.state_text()
    assert logged(window, "NOT being recorded")
    # the controller runs on: the console keeps getting readings
    qtbot.waitUntil(lambda: window.latest_tick() is not None and float(window.latest_tick()["t_s"]) > 0.5,
                    timeout=WAIT_MS)
    assert recording.recorder is None and not any(sessions_dir().glob("*.h5"))


def test_a_disk_filling_up_stops_recording_visibly_while_control_goes_on(qtbot, tmp_path, bridge, recent, info,
                                                                         monkeypatch):
    window = make_console(qtbot, tmp_path, bridge, recent)
    recording = SessionRecording(bridge, info, recorder_options={"min_free_bytes": 2**20})
    wire_recording(window, recording)
    path = start(qtbot, window, bridge, recording)
    real_usage = shutil.disk_usage

    def nearly_full(where):
        return real_usage(where)._replace(free=2**19)

    # the writer checks the free space after every flush; from now on the disk looks nearly full
    monkeypatch.setattr(shutil, "disk_usage", nearly_full)
    with qtbot.waitSignal(recording.problem, timeout=WAIT_MS) as problem:
        pass
    assert problem.args[0].startswith("Recording stopped: only 0 MB left")
    assert window.session_panel().state() == "problem" and logged(window, "Recording stopped")
    t_then = float(window.latest_tick()["t_s"])
    qtbot.waitUntil(lambda: float(window.latest_tick()["t_s"]) > t_then + 0.5, timeout=WAIT_MS)
    monkeypatch.undo()
    with qtbot.waitSignal(recording.recording_stopped, timeout=WAIT_MS):
        bridge.stop()
    assert window.session_panel().state() == "problem"  # the problem stays in view after the stop
    with open_session(path) as session:
        kinds = [e["kind"] for e in session.event_dicts()]
        assert EventKind.RECORDER in kinds


def test_the_file_menu_opens_sessions_and_lists_recent_ones(qtbot, tmp_path, bridge, recent, monkeypatch):
    window = make_console(qtbot, tmp_path, bridge, recent)
    open_action = window.findChild(QtGui.QAction, "openSessionAction")
    recent_action = window.findChild(QtGui.QAction, "recentSessionsMenu")
    assert open_action is not None and recent_action is not None and recent_action.menu() is not None
    assert open_action.shortcut() == QtGui.QKeySequence(QtGui.QKeySequence.StandardKey.Open)

    # a file that is not a session: the reason goes to the messages pane, no reviewer opens
    bogus = tmp_path / "not-a-session.h5"
    bogus.write_bytes(b"definitely not HDF5")
    chosen = []
    monkeypatch.setattr(QtWidgets.QFileDialog, "getOpenFileName",
                        lambda *args, **kwargs: (chosen.append(args[2]) or str(bogus), "Palpation sessions (*.h5)"))
    open_action.trigger()
    assert chosen == [str(sessions_dir())]
    assert window.review_windows() == []
    assert logged(window, "Cannot open the session") and logged(window, "not-a-session.h5")
    with pytest.raises(SessionFileError):
        open_session(bogus)

    # the recent list fills its menu when it is about to show
    menu = recent_action.menu()
    menu.aboutToShow.emit()
    assert [a.text() for a in menu.actions()] == ["No recent sessions"]


def test_a_controller_crash_closes_the_file_cleanly(qtbot, tmp_path, bridge, recent, info, monkeypatch):
    from app.fastforward import FastForward

    window = make_console(qtbot, tmp_path, bridge, recent)
    recording = SessionRecording(bridge, info)
    wire_recording(window, recording)
    path = start(qtbot, window, bridge, recording)

    def broken(self, n):
        raise RuntimeError("simulated loop failure")

    monkeypatch.setattr(FastForward, "step", broken)
    with qtbot.waitSignal(recording.recording_stopped, timeout=WAIT_MS) as stopped:
        pass
    assert stopped.args[0] == path and recording.recorder is None
    # The worker closes the file before it reports the crash, and the two reach the window as separate
    # queued signals: the crash line may come an event later than the file's.
    qtbot.waitUntil(lambda: logged(window, "CONTROLLER STOPPED"), timeout=WAIT_MS)
    assert logged(window, f"Session saved to {path}")
    with open_session(path) as session:
        assert session.closed_cleanly and session.n_ticks > 0
        lost = [e for e in session.event_dicts() if e["kind"] == "controller_lost"]
        assert len(lost) == 1 and "simulated loop failure" in lost[0]["text"]
        assert any("controller stopped on its own" in w and "simulated loop failure" in w for w in session.warnings)


def test_the_console_gets_the_model_based_depth_or_says_why_not(qtbot, tmp_path, bridge, recent, info):
    window = LiveWindow(bridge, sessions_folder=tmp_path, recent=recent)
    qtbot.addWidget(window)
    wire_depth_model(window, info)
    assert not any("Model-based depth" in line for line in window.messages().lines())
    wire_depth_model(window, info, tmp_path / "missing.npz")
    assert window.messages().lines()[-1].endswith(
        f"Model-based depth unavailable: depth model library {tmp_path / 'missing.npz'}: cannot be read "
        f"([Errno 2] No such file or directory: '{tmp_path / 'missing.npz'}')")
