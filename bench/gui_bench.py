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

Then what a user waits for:

* ``first_window_s``: from starting ``palpation-console run`` (a new process, an empty tissue cache: the first
  run) to its first window on screen, the tissue model's progress dialog (issue 50's goal: 3 s);
* ``findings_after_region_done_s``: the console wired as ``run`` wires it (its live physics and model-based
  depth) lets the autopilot palpate every area of the shipped phantom; for each area from the
  (``MIN_VOUCHING`` + 1)-th on, the first whose findings can come at once, the time from its "region done" to
  its findings told; the median over them (``findings_after_region_done_max_s``: the longest; issue 50's goal
  for the median: 5 s). The first areas' findings wait for that one's.

Writes ``gui.json``. The offscreen platform paints into memory like a real one, minus the compositor.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
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
from control.messages import FaultRaised, LevelRecorded, RegionDone
from session.flatfield import MIN_VOUCHING
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
    result["first_window_s"] = first_window_s()
    waits = findings_after_region_done_s(app_config)
    result["findings_after_region_done_s"] = float(np.median(waits))
    result["findings_after_region_done_max_s"] = float(np.max(waits))
    print(f"gui: first window after {result['first_window_s']:.1f} s; findings "
          f"{result['findings_after_region_done_s']:.1f} s after region done (median of {len(waits)} areas, "
          f"longest {result['findings_after_region_done_max_s']:.1f} s)")
    print(f"gui: {result['fps']:.1f} fps, paint p50 {result['paint_p50_ms']:.2f} ms / p99 "
          f"{result['paint_p99_ms']:.2f} ms, update p50 {result['update_p50_ms']:.2f} ms, loop late > 0.5 ms "
          f"{result['loop_late_over_0_5ms_pct']:.3f} % (RT priority: {result['rt_priority']}), "
          f"{probe.levels} levels recorded")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{NAME}.json").write_text(json.dumps(result, indent=2, sort_keys=True) + "\n")
    return result


# the child: the time its first window is shown, then out (the first run's tissue model is not waited for)
FIRST_WINDOW = """
import os, sys, time
from PySide6 import QtCore, QtWidgets
class Shown(QtCore.QObject):
    def eventFilter(self, obj, event):
        if event.type() == QtCore.QEvent.Type.Expose and isinstance(obj, QtCore.QObject) and obj.isWindowType():
            print("shown", time.time(), flush=True)
            os._exit(0)
        return False
app = QtWidgets.QApplication(sys.argv[:1])
shown = Shown()
app.installEventFilter(shown)
from app.cli import main
sys.exit(main(["run"]))
"""
FIRST_WINDOW_TIMEOUT_S = 120.0


def first_window_s() -> float:
    """Seconds from starting the console's process on the first run (an empty tissue cache and settings) to
    its first window exposed on screen."""
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, PALPATION_CACHE_DIR=str(Path(tmp) / "cache"), PALPATION_DATA_DIR=str(Path(tmp) / "data"),
                   XDG_CONFIG_HOME=str(Path(tmp) / "config"))
        started = time.time()
        child = subprocess.run([sys.executable, "-c", FIRST_WINDOW], env=env, capture_output=True, text=True,
                               timeout=FIRST_WINDOW_TIMEOUT_S, cwd=Path(__file__).resolve().parents[1])
    shown = [line.split() for line in child.stdout.splitlines() if line.startswith("shown ")]
    if not shown:
        raise RuntimeError(f"the console showed no window (exit {child.returncode}): {child.stderr.strip()[-500:]}")
    return float(shown[0][1]) - started


FINDINGS_TIMEOUT_S = 900.0  # nine areas of the flat phantom take 160 s; the findings of a loaded machine, more


def findings_after_region_done_s(app_config) -> list[float]:
    """Seconds from "region done" to the area's findings told, for each area from the (MIN_VOUCHING + 1)-th on
    of an autopilot run over the shipped phantom (module docstring)."""
    from app.gui import wire_depth_model
    from app.live_physics import LivePhysics
    from app.recording import session_info

    config, spec = app_config.control, console_rig(app_config)
    plan = plan_for_rig(spec, config)
    info = session_info(app_config, spec=spec)
    process = ControllerProcess(config, spec, PacingOptions(), tick_capacity=65536)
    bridge = ControllerBridge(lambda: process)
    done_at: dict[int, float] = {}
    told_at: dict[int, float] = {}
    finished = QtCore.QEventLoop()

    def region_done(snapshot) -> None:
        for event in snapshot.events:
            if isinstance(event, RegionDone):
                done_at.setdefault(event.region, time.perf_counter())

    def told(text: str) -> None:
        area = int(text.split()[1].rstrip(":,")) - 1  # "Area 5: ..." or "Area 5, with the areas palpated since: ..."
        told_at.setdefault(area, time.perf_counter())
        if len(told_at) == len(plan.areas):
            finished.quit()

    with tempfile.TemporaryDirectory() as tmp:
        settings = QtCore.QSettings(str(Path(tmp) / "console.ini"), QtCore.QSettings.Format.IniFormat)
        bridge.snapshot.connect(region_done)  # before the window: the time the console learns of it
        window = LiveWindow(bridge, config=config, plan=plan, settings=settings)
        wire_depth_model(window, info)
        physics = LivePhysics(info, window, plan.phantom_extent_m)
        window.set_live_physics(physics)
        window.findings_told.connect(told)
        problems: list[str] = []
        bridge.start_failed.connect(problems.append)
        bridge.crashed.connect(problems.append)
        bridge.start_failed.connect(finished.quit)
        bridge.crashed.connect(finished.quit)
        bridge.started.connect(lambda: window.start_autopilot(0))
        QtCore.QTimer.singleShot(round(FINDINGS_TIMEOUT_S * 1000), finished.quit)
        try:
            window.show()
            bridge.start()
            finished.exec()
        finally:
            physics.close()
            bridge.shutdown()
            window.close()
            window.deleteLater()
            QtWidgets.QApplication.processEvents()
    if problems:
        raise RuntimeError(f"the controller stopped during the findings run: {problems[0]}")
    waited = [told_at[a] - done_at[a] for a in range(MIN_VOUCHING, len(plan.areas)) if a in told_at and a in done_at]
    if len(waited) < len(plan.areas) - MIN_VOUCHING:
        raise RuntimeError(f"findings told for areas {sorted(a + 1 for a in told_at)} of {len(plan.areas)} within "
                           f"{FINDINGS_TIMEOUT_S:.0f} s")
    return waited


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
