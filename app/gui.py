"""The console's composition root: a QApplication, the controller bridge and the console window."""

from __future__ import annotations

import dataclasses
import sys

from app.config import AppConfig


def console_rig(config: AppConfig):
    """The rig the interactive console drives: a simulated rig without its scripted operator, so the TSI is
    moved by the console's jog and autopilot (real rigs are taken as configured)."""
    if config.rig.backend == "sim":
        return dataclasses.replace(config.rig, master="none")
    return config.rig


def run_gui(config: AppConfig, argv: list[str] | None = None, screenshot: str | None = None,
            screenshot_after_s: float = 10.0, autopilot: bool | None = None) -> int:
    """Run the console until its window closes. With ``screenshot``, save the window to that PNG after
    ``screenshot_after_s`` seconds and quit (for docs and for looking at the GUI on a headless machine).
    ``autopilot`` starts the autopilot with the controller; by default it does so only for a screenshot,
    so the picture shows a palpation under way. The layout and last settings are kept in the user's
    configuration directory (:func:`widgets.live_window.console_settings`)."""
    from PySide6 import QtCore, QtWidgets

    from app.autopilot import plan_for_rig
    from app.bridge import ControllerBridge
    from widgets.live_window import LiveWindow

    rig = console_rig(config)
    plan = plan_for_rig(rig, config.control)  # first: a bad phantom is a configuration error, not a crash
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(argv or sys.argv[:1])
    app.setApplicationName("Palpation Console")
    app.setOrganizationName("palpation-console")
    bridge = ControllerBridge.for_process(config.control, rig)
    window = LiveWindow(bridge, config=config.control, plan=plan)
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
