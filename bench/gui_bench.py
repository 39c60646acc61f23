"""The full console while palpating: frames per second, paint time per frame, and the loop's lateness.

Opens the operator console (:class:`widgets.live_window.LiveWindow`, 1600 x 1000, every panel in its
default place) on the controller process driving the simulated rig without a master, and lets the
autopilot palpate the phantom's areas for ``PALPATION_BENCH_SECONDS`` (default 25 s) after a warm-up.
The configuration is the shipped default (ramp 1-7 N), so the window shows what it shows in use: maps
changing at the sensor's frame rate, the force plot growing, levels being recorded, areas being done.

* a *frame* is what the window paints between two snapshots (the bridge delivers one per display
  period). Qt paints in the window's ``UpdateRequest``, all dirty widgets at once into the backing store,
  but a snapshot usually causes several: the plain widgets' at once, the pyqtgraph scenes' one event-loop
  pass later (a graphics scene reports its changes asynchronously). So the paint time of a frame is the
  sum of the ``UpdateRequest`` handling times between two snapshots;
* ``fps``: frames painted per second (snapshots whose changes reached the screen);
* ``paint_p50_ms`` / ``paint_p99_ms``: paint time per frame;
* ``update_p50_ms`` / ``update_p99_ms``: time to apply one snapshot to the widgets (before painting);
* ``loop_late_over_0_5ms_pct`` and the other loop figures: from every tick row the console received,
  with the statistics of :mod:`bench.loop_bench`.

Writes ``gui.json``. The offscreen platform paints into memory like a real one, minus the compositor.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from PySide6 import QtCore, QtWidgets

from app.bridge import ControllerBridge
from app.config import load_config
from app.controller import ControllerProcess, PacingOptions
from app.gui import console_rig
from app.rigs import plan_for_rig
from bench.loop_bench import WARMUP_S, duration_s, tick_statistics
from control.messages import FaultRaised, LevelRecorded
from widgets.live_window import LiveWindow

NAME = "gui"
WINDOW_SIZE = (1600, 1000)


def run(out_dir: Path) -> dict:
    seconds = duration_s()
    app_config = load_config()  # the shipped defaults: what `make run` opens
    config, spec = app_config.control, console_rig(app_config)
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication([])
    process = ControllerProcess(config, spec, PacingOptions(), tick_capacity=65536)
    bridge = ControllerBridge(lambda: process)
    with tempfile.TemporaryDirectory() as tmp:
        settings = QtCore.QSettings(str(Path(tmp) / "console.ini"), QtCore.QSettings.Format.IniFormat)
        probe = _Probe()
        bridge.snapshot.connect(probe.snapshot_begins)  # connected before the window: runs first
        window = LiveWindow(bridge, config=config, plan=plan_for_rig(spec, config), settings=settings)
        bridge.snapshot.connect(probe.snapshot_ends)
        window.resize(*WINDOW_SIZE)
        window.show()
        painter = _PaintTimer(window)
        window.installEventFilter(painter)
        bridge.snapshot.connect(painter.next_frame)
        problems: list[str] = []
        bridge.start_failed.connect(problems.append)
        bridge.crashed.connect(problems.append)
        try:
            waiting = QtCore.QEventLoop()
            bridge.started.connect(waiting.quit)
            bridge.start_failed.connect(waiting.quit)
            bridge.start()
            waiting.exec()
            if problems:
                raise RuntimeError(f"the controller did not start: {problems[0]}")
            window.start_autopilot(0)
            _run_for(WARMUP_S + 1.0)
            painter.reset()
            probe.reset()
            started = time.perf_counter()
            _run_for(seconds)
            elapsed = time.perf_counter() - started
            painter.next_frame()
        finally:
            window.removeEventFilter(painter)
            bridge.shutdown()
            window.close()
            window.deleteLater()
            app.processEvents()
        if problems:
            raise RuntimeError(f"the controller stopped during the run: {problems[0]}")

    if probe.faults:
        raise RuntimeError(f"the palpation faulted during the run: {probe.faults[0]}")
    if not probe.levels:
        raise RuntimeError("no level was recorded: the console was not palpating")
    ticks = np.concatenate(probe.ticks)
    loop = tick_statistics(ticks, config.period_s)
    paint_ms = np.array(painter.frames_s) * 1e3
    update_ms = np.array(probe.durations_s) * 1e3
    info = process.started_info
    result = {
        "fps": len(paint_ms) / elapsed,
        "paint_p50_ms": float(np.percentile(paint_ms, 50)),
        "paint_p99_ms": float(np.percentile(paint_ms, 99)),
        "paints_per_frame": painter.paints / max(1, len(paint_ms)),
        "update_p50_ms": float(np.percentile(update_ms, 50)),
        "update_p99_ms": float(np.percentile(update_ms, 99)),
        "snapshots_per_s": len(update_ms) / elapsed,
        "loop_late_over_0_5ms_pct": loop["late_over_0_5ms_pct"],
        "loop_late_over_1ms_pct": loop["late_over_1ms_pct"],
        "loop_p99_abs_jitter_us": loop["p99_abs_jitter_us"],
        "loop_longest_stall_ms": loop["longest_stall_ms"],
        "loop_missed_ticks": loop["missed_ticks"],
        "loop_ticks": loop["ticks"],
        "rt_priority": bool(info.rt_priority) if info else False,
        "levels_recorded": probe.levels,
        "duration_s": elapsed,
        "window": list(WINDOW_SIZE),
        "platform": app.platformName(),
        "cpus": os.cpu_count(),
    }
    print(f"gui: {result['fps']:.1f} fps, paint p50 {result['paint_p50_ms']:.2f} ms / p99 "
          f"{result['paint_p99_ms']:.2f} ms, update p50 {result['update_p50_ms']:.2f} ms, loop late > 0.5 ms "
          f"{result['loop_late_over_0_5ms_pct']:.3f} % (RT priority: {result['rt_priority']}), "
          f"{probe.levels} levels recorded")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{NAME}.json").write_text(json.dumps(result, indent=2, sort_keys=True) + "\n")
    return result


def _run_for(seconds: float) -> None:
    loop = QtCore.QEventLoop()
    QtCore.QTimer.singleShot(round(seconds * 1000.0), loop.quit)
    loop.exec()


class _PaintTimer(QtCore.QObject):
    """Times the window's UpdateRequests (where Qt paints every dirty widget of the window) and adds them
    up per frame: :meth:`next_frame` closes one, at each snapshot."""

    def __init__(self, window: QtWidgets.QWidget):
        super().__init__()
        self._window = window
        self._inside = False
        self.reset()

    def reset(self) -> None:
        self.frames_s: list[float] = []
        self.paints = 0
        self._frame_s = 0.0

    def next_frame(self, *_snapshot) -> None:
        if self._frame_s > 0.0:  # a snapshot that changed nothing on screen is no frame
            self.frames_s.append(self._frame_s)
        self._frame_s = 0.0

    def eventFilter(self, obj, event) -> bool:
        if obj is not self._window or self._inside or event.type() != QtCore.QEvent.Type.UpdateRequest:
            return False
        # Deliver it here, timed, and tell Qt it was handled.
        self._inside = True
        t0 = time.perf_counter()
        try:
            obj.event(event)
        finally:
            self._frame_s += time.perf_counter() - t0
            self.paints += 1
            self._inside = False
        return True


class _Probe:
    """Times each snapshot's trip through the window and keeps its tick rows and events."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.durations_s: list[float] = []
        self.ticks: list[np.ndarray] = []
        self.levels = 0
        self.faults: list[str] = []
        self._t0 = None

    def snapshot_begins(self, snapshot) -> None:
        self._t0 = time.perf_counter()
        self.ticks.append(snapshot.ticks)
        for event in snapshot.events:
            if isinstance(event, LevelRecorded):
                self.levels += 1
            elif isinstance(event, FaultRaised):
                self.faults.append(event.message)

    def snapshot_ends(self, snapshot) -> None:
        if self._t0 is not None:
            self.durations_s.append(time.perf_counter() - self._t0)
            self._t0 = None
