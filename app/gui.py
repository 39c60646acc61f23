"""The console's composition root: a QApplication, the controller bridge and the live window."""

from __future__ import annotations

import sys

from app.config import AppConfig


def run_gui(config: AppConfig, argv: list[str] | None = None, screenshot: str | None = None,
            screenshot_after_s: float = 10.0) -> int:
    """Run the console until its window closes. With ``screenshot``, save the window to that PNG after
    ``screenshot_after_s`` seconds and quit (for docs and for looking at the GUI on a headless machine)."""
    from PySide6 import QtCore, QtWidgets

    from app.bridge import ControllerBridge
    from widgets.live_window import LiveWindow

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(argv or sys.argv[:1])
    app.setApplicationName("Palpation Console")
    app.setOrganizationName("palpation-console")
    bridge = ControllerBridge.for_process(config.control, config.rig)
    window = LiveWindow(bridge, ramp=config.control.ramp)
    window.setWindowTitle(f"Palpation Console — {config.rig.backend} rig, phantom {config.rig.phantom}")

    def failed(message: str) -> None:
        QtWidgets.QMessageBox.critical(window, "The controller could not start", message)
        app.quit()

    def crashed(message: str) -> None:
        QtWidgets.QMessageBox.critical(
            window, "The controller stopped",
            f"{message}\n\nThe robot was left holding (or was never commanded). Restart the console to go on.")

    bridge.start_failed.connect(failed)
    bridge.crashed.connect(crashed)
    window.resize(1280, 720)
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
