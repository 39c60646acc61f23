"""The console's composition root: a QApplication, the controller bridge, the console window and the
session recorder.

Every controller run (from ``started`` to ``stopped``, ``crashed`` or quitting) is recorded to one new
session file in :func:`app.session.recorder.sessions_dir`; the console's session panel shows where, and
the messages pane says so when recording stops early (full disk...), while control goes on.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any

from PySide6 import QtCore

from app.config import AppConfig
from app.session.recorder import (RecorderError, RecorderStatus, SessionInfo, SessionRecorder, new_session_path,
                                  sessions_dir)


def console_rig(config: AppConfig):
    """The rig the interactive console drives: a simulated rig without its scripted operator, so the TSI is
    moved by the console's jog and autopilot (real rigs are taken as configured)."""
    if config.rig.backend == "sim":
        return dataclasses.replace(config.rig, master="none")
    return config.rig


def recording_summary(status: RecorderStatus) -> str:
    """One line on a closed recording, for the operator."""
    text = (f"{status.levels_written} force levels, {status.ticks_written} control periods, "
            f"{status.frames_written} frames, {status.bytes_on_disk / 2**20:.1f} MB")
    lost = status.rows_lost + status.rows_dropped
    return text + (f" ({lost} rows missing)" if lost else "")


class SessionRecording(QtCore.QObject):
    """Records each run of ``controller`` (a :class:`app.bridge.ControllerBridge`) to a file of its own.

    A recorder is created on ``started`` and closed on ``stopped`` or ``crashed`` (and by :meth:`close`
    when the console quits); ``snapshot`` ticks and events and ``frames`` rows go into it as they arrive.
    Create it in the GUI thread, before the controller starts.

    Signals: ``recording_started(path)``, ``recording_stopped(path, summary)``, ``problem(message)``
    (recording could not start, or stopped early; delivered in the GUI thread even when the writer thread
    finds it).
    """

    recording_started = QtCore.Signal(str)
    recording_stopped = QtCore.Signal(str, str)
    problem = QtCore.Signal(str)
    _writer_problem = QtCore.Signal(str)

    def __init__(self, controller, info: SessionInfo, folder: str | Path | None = None,
                 recorder_options: dict[str, Any] | None = None, parent: QtCore.QObject | None = None):
        super().__init__(parent)
        self._info = info
        self._folder = Path(folder) if folder is not None else None
        self._options = dict(recorder_options or {})
        self._recorder: SessionRecorder | None = None
        self.last_status: RecorderStatus | None = None
        # queued: the writer thread reports through this, the GUI thread shows it
        self._writer_problem.connect(self.problem, QtCore.Qt.ConnectionType.QueuedConnection)
        controller.started.connect(self.start)
        controller.stopped.connect(self.close)
        controller.crashed.connect(self.close)
        controller.snapshot.connect(self._add_snapshot)
        controller.frames.connect(self._add_frames)

    @property
    def recorder(self) -> SessionRecorder | None:
        """The recorder of the run under way; None between runs."""
        return self._recorder

    @QtCore.Slot()
    def start(self) -> None:
        """Begin a new session file (closing any still open); a failure is reported through ``problem``."""
        self.close()
        folder = self._folder if self._folder is not None else sessions_dir()
        path = new_session_path(folder)
        try:
            self._recorder = SessionRecorder(path, self._info, on_problem=self._writer_problem.emit,
                                             **self._options)
        except RecorderError as err:
            self.problem.emit(f"This session is NOT being recorded: {err}. The controller is unaffected.")
            return
        self.recording_started.emit(str(path))

    @QtCore.Slot()
    def close(self) -> RecorderStatus | None:
        """Close the current session file cleanly (writes what is queued); None if none was open."""
        recorder, self._recorder = self._recorder, None
        if recorder is None:
            return None
        status = recorder.close()
        self.last_status = status
        self.recording_stopped.emit(str(status.path), recording_summary(status))
        return status

    def add_note(self, text: str, t_s: float) -> bool:
        """Record an operator's note at loop time ``t_s``; False if no session is being recorded."""
        recorder = self._recorder
        if recorder is None or not recorder.recording:
            return False
        recorder.add_note(text, t_s)
        return True

    @QtCore.Slot(object)
    def _add_snapshot(self, snapshot) -> None:
        if self._recorder is not None:
            self._recorder.add_ticks(snapshot.ticks)
            self._recorder.add_events(snapshot.events)

    @QtCore.Slot(object)
    def _add_frames(self, frames) -> None:
        if self._recorder is not None:
            self._recorder.add_frames(frames)


def wire_recording(window, recording: SessionRecording) -> None:
    """Show ``recording`` in the console ``window`` (a :class:`widgets.live_window.LiveWindow`) and let its
    operator notes reach the session file."""
    from widgets.messages import Severity

    panel = window.session_panel()
    messages = window.messages()

    def started(path: str) -> None:
        panel.show_recording(path)
        messages.add(f"Recording the session to {path}")

    def stopped(path: str, summary: str) -> None:
        panel.show_stopped(path, summary)
        window.recent_sessions().add(path)
        messages.add(f"Session saved to {path}: {summary}")

    def problem(message: str) -> None:
        panel.show_problem(message)
        messages.add(message, Severity.ERROR)
        window.statusBar().showMessage(message)

    def note(text: str) -> None:
        tick = window.latest_tick()
        if tick is None:
            messages.add("The note was not recorded: no reading from the controller yet.", Severity.WARNING)
            return
        if not recording.add_note(text, float(tick["t_s"])):
            messages.add("The note was not recorded: no session is being recorded.", Severity.WARNING)
            return
        panel.note_added(text)
        messages.add(f"Note: {text}")

    recording.recording_started.connect(started)
    recording.recording_stopped.connect(stopped)
    recording.problem.connect(problem)
    panel.note_submitted.connect(note)


def session_info(config: AppConfig, spec) -> SessionInfo:
    """What the session files of a console driving the rig ``spec`` describe themselves with. The rig is
    built (for its sensor geometry, description and ground truth) but never opened: the controller opens
    its own."""
    from app.rigs import build_rig

    return SessionInfo.from_rig(config, build_rig(spec), spec)


def run_gui(config: AppConfig, argv: list[str] | None = None, screenshot: str | None = None,
            screenshot_after_s: float = 10.0, autopilot: bool | None = None) -> int:
    """Run the console until its window closes. With ``screenshot``, save the window to that PNG after
    ``screenshot_after_s`` seconds and quit (for docs and for looking at the GUI on a headless machine).
    ``autopilot`` starts the autopilot with the controller; by default it does so only for a screenshot,
    so the picture shows a palpation under way. The layout and last settings are kept in the user's
    configuration directory (:func:`widgets.live_window.console_settings`)."""
    from PySide6 import QtCore, QtWidgets

    from app.rigs import plan_for_rig
    from app.bridge import ControllerBridge
    from widgets.live_window import LiveWindow

    rig = console_rig(config)
    plan = plan_for_rig(rig, config.control)  # first: a bad phantom is a configuration error, not a crash
    info = session_info(config, rig)
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(argv or sys.argv[:1])
    app.setApplicationName("Palpation Console")
    app.setOrganizationName("palpation-console")
    bridge = ControllerBridge.for_process(config.control, rig)
    window = LiveWindow(bridge, config=config.control, plan=plan, sessions_folder=sessions_dir())
    recording = SessionRecording(bridge, info)
    wire_recording(window, recording)
    window.setWindowTitle(f"Palpation Console — {rig.backend} rig, phantom {rig.phantom}")
    if autopilot is None:
        autopilot = screenshot is not None
    if autopilot and plan is not None:
        bridge.started.connect(lambda: window.start_autopilot(0))

    def failed(message: str) -> None:
        QtWidgets.QMessageBox.critical(window, "The controller could not start", message)
        app.quit()

    bridge.start_failed.connect(failed)
    window.show()
    _quit_on_signals(app)
    if screenshot:
        def grab() -> None:
            window.grab().save(screenshot)
            app.quit()

        QtCore.QTimer.singleShot(int(screenshot_after_s * 1000), grab)
    bridge.start()
    try:
        return app.exec()
    finally:
        window.save_settings()  # quitting does not close the window, so its closeEvent never saved them
        bridge.shutdown()
        # The controller's last rows and its "stopped" were queued while the event loop was ending:
        # deliver them, so they reach the file and the recorder closes it in the usual way.
        QtCore.QCoreApplication.sendPostedEvents()
        recording.close()


def _quit_on_signals(app) -> None:
    """SIGINT/SIGTERM quit through Qt, so the controller is stopped and shared memory released."""
    import signal

    from PySide6 import QtCore

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: app.quit())
    # Python runs signal handlers only between bytecodes: give the interpreter a chance while Qt idles
    timer = QtCore.QTimer(app)
    timer.timeout.connect(lambda: None)
    timer.start(200)
