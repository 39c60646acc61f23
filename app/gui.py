"""The console's composition root: a QApplication, the controller bridge, the console window and the
session recording.

Every controller run (from ``started`` to ``stopped``, ``crashed`` or quitting) is recorded to one new
session file in :func:`session.info.sessions_dir` by :class:`app.recording.SessionRecording`, fed from the
bridge's thread; the console's session panel shows where, and the messages pane says so when recording
stops early (full disk...), while control goes on.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable
from pathlib import Path

from app.config import AppConfig
from app.recording import SessionRecording, session_info
from session.depth import LIBRARY_PATH, DepthModel, DepthModelError
from session.format import FINDINGS_TOLD
from session.info import sessions_dir
from tissue.mechanics.progress import Progress


def console_rig(config: AppConfig):
    """The rig the interactive console drives: a simulated rig without its scripted operator, so the TSI is
    moved by the console's jog and autopilot (real rigs are taken as configured)."""
    if config.rig.backend == "sim":
        return dataclasses.replace(config.rig, master="none")
    return config.rig


def wire_recording(window, recording: SessionRecording) -> None:
    """Show ``recording`` in the console ``window`` (a :class:`widgets.live_window.LiveWindow`) and let its
    operator notes, and the findings it tells the surgeon, reach the session file."""
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
        if not recording.add_note(text):
            messages.add("The note was not recorded: no session is being recorded (or nothing recorded yet "
                         "to take the loop's time from).", Severity.WARNING)
            return
        panel.note_added(text)
        messages.add(f"Note: {text}")

    recording.recording_started.connect(started)
    recording.recording_stopped.connect(stopped)
    recording.problem.connect(problem)
    panel.note_submitted.connect(note)
    # what the surgeon was told, and when, so the reviewer can show it beside its own analysis (issue 50)
    window.findings_told.connect(lambda text: recording.add_note(f"{FINDINGS_TOLD} {text}"))


def wire_bus(window, bridge, rig):
    """Publish the palpation on the ROS 2 bus when ``rig`` is a CRTK rig that publishes
    (:func:`app.rigs.bus_publisher`): the publisher becomes one of ``bridge``'s row sinks, and a bus that fails is
    told in the console ``window`` as a recording that fails is. Returns the publisher (None: nothing published)."""
    from PySide6 import QtCore

    from app.rigs import bus_publisher
    from widgets.messages import Severity

    publisher = bus_publisher(rig)
    if publisher is None:
        return None

    class Relay(QtCore.QObject):
        failed = QtCore.Signal(str)

    def failed(message: str) -> None:
        window.messages().add(message, Severity.ERROR)
        window.statusBar().showMessage(message)

    # made in the window's thread, so what the publisher tells in the bridge's thread is queued to the window's
    relay = Relay(window)
    relay.failed.connect(failed)
    publisher.on_problem = relay.failed.emit
    bridge.add_sink(publisher)
    return publisher


def prepare_in_console(prepare: Callable[[Progress], None], title: str, terminal: Progress | None = None) -> None:
    """Run ``prepare(progress)`` (the first use of a phantom: its tissue model, tens of seconds) off the GUI
    thread while a progress dialog shows how far it is, so a new user sees the wait in the console, not
    only on a terminal they may not be looking at; ``terminal`` hears the same. An exception in
    ``prepare`` is raised here. Returns at once, without a dialog, when it takes less than half a second
    (a cached model)."""
    import threading

    from PySide6 import QtCore, QtWidgets

    class Relay(QtCore.QObject):
        moved = QtCore.Signal(float, str)
        finished = QtCore.Signal()

    relay = Relay()
    dialog = QtWidgets.QProgressDialog(title, "", 0, 1000)
    dialog.setObjectName("prepareProgress")
    dialog.setWindowTitle("Palpation Console")
    dialog.setCancelButton(None)  # the model is needed; quitting the console is the way out
    dialog.setMinimumDuration(2**31 - 1)  # shown by the timer below, not by its own guess of what is left
    dialog.setMinimumWidth(480)

    def moved(fraction: float, message: str) -> None:
        dialog.setLabelText(f"{title}\n{message}")
        dialog.setValue(int(round(1000 * min(1.0, max(0.0, fraction)))))

    relay.moved.connect(moved)
    loop = QtCore.QEventLoop()
    relay.finished.connect(loop.quit)
    failure: list[BaseException] = []

    def report(fraction: float, message: str) -> None:  # on the worker thread: queued to the GUI's
        relay.moved.emit(fraction, message)
        if terminal is not None:
            terminal(fraction, message)

    def work() -> None:
        try:
            prepare(report)
        except BaseException as err:  # noqa: BLE001 - handed to the GUI thread and raised there
            failure.append(err)
        finally:
            relay.finished.emit()

    worker = threading.Thread(target=work, name="prepare-rig", daemon=True)
    worker.start()
    QtCore.QTimer.singleShot(500, lambda: worker.is_alive() and dialog.show())
    loop.exec()
    worker.join()
    dialog.close()
    dialog.deleteLater()
    if failure:
        raise failure[0]


def run_gui(config: AppConfig, argv: list[str] | None = None, screenshot: str | None = None,
            screenshot_after_s: float = 10.0, autopilot: bool | None = None) -> int:
    """Run the console until its window closes. With ``screenshot``, save the window to that PNG after
    ``screenshot_after_s`` seconds and quit (for docs and for looking at the GUI on a headless machine).
    ``autopilot`` starts the autopilot with the controller; by default it does so only for a screenshot,
    so the picture shows a palpation under way. The layout and last settings are kept in the user's
    configuration directory (:func:`widgets.live_window.console_settings`)."""
    from PySide6 import QtCore, QtWidgets

    from app.bridge import ControllerBridge
    from app.live_physics import LivePhysics
    from app.rigs import plan_for_rig, prepare_rig
    from tissue.mechanics.progress import TextProgressBar
    from widgets.live_window import LiveWindow

    rig = console_rig(config)
    plan = plan_for_rig(rig, config.control)  # first: a bad phantom is a configuration error, not a crash
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(argv or sys.argv[:1])
    app.setApplicationName("Palpation Console")
    app.setOrganizationName("palpation-console")
    # the first use of a phantom: its tissue model, before the controller process starts, and before anything
    # else builds the rig (the session's description did, for 36 s of black window and a silent terminal)
    prepare_in_console(lambda progress: prepare_rig(rig, progress),
                       f"Preparing the tissue model of {rig.phantom!r} (once per phantom; cached after)",
                       terminal=TextProgressBar())
    info = session_info(config, spec=rig)
    bridge = ControllerBridge.for_process(config.control, rig)
    window = LiveWindow(bridge, config=config.control, plan=plan, sessions_folder=sessions_dir())
    recording = SessionRecording(bridge, info)
    wire_recording(window, recording)
    wire_bus(window, bridge, rig)
    wire_depth_model(window, info)
    physics = LivePhysics(info, window, plan.phantom_extent_m if plan is not None else None)
    window.set_live_physics(physics)
    wire_findings_progress(physics, TextProgressBar)
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
        physics.close()
        bridge.shutdown()  # drains the controller's last rows into the recording and closes its file
        recording.close()  # in case the driver never started


def wire_findings_progress(physics, bar) -> None:
    """The terminal shows the live findings' tissue model being computed, as the console does: a progress
    line per answer (``bar()`` makes one, :class:`tissue.mechanics.progress.TextProgressBar`), closed with
    how long it took."""
    under_way: list = []  # (its line, when it started) while an answer is computed

    def moved(records: int, fraction: float, what: str) -> None:
        if not under_way:
            under_way.append((bar(), time.monotonic()))
        under_way[0][0](min(fraction, 0.99), f"findings ({records} levels): {what}")

    def finished(text: str) -> None:
        if under_way:
            line, started = under_way.pop()
            line(1.0, text.format(s=time.monotonic() - started))

    physics.progress.connect(moved)
    physics.ready.connect(lambda records, *_: finished(f"findings ({records} levels) in {{s:.1f}} s"))
    physics.failed.connect(lambda reason: finished(f"no findings' tissue model after {{s:.1f}} s: {reason}"))


def wire_depth_model(window, info, library: Path = LIBRARY_PATH) -> None:
    """The model-based depth for the findings told at "region done", where the library of solves fits this
    array; the messages say why not otherwise (the paper's rule is then the only depth)."""
    from widgets.messages import Severity

    try:
        window.set_depth_model(DepthModel.for_info(info, library))
    except DepthModelError as err:
        window.messages().add(f"Model-based depth unavailable: {err}", Severity.WARNING)


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
