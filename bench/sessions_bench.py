"""Session recording and review: how much faster than real time the recorder writes, whether the console's
pipeline loses rows, how fast the reviewer shows a 1-hour session, how fast 9 regions x 7 levels stitch.

* ``logging_headroom_x``: tick rows written per second of wall time over 1000 (the stream's rate), for one
  hour of a real simulated session (tiled from ``BASE_S`` seconds recorded with the fast-forward driver:
  ticks, frames, events and levels as the console makes them), fed to the recorder in one-second pieces,
  everything on disk at the end. Goal >= 100.
* ``rows_lost``: the console's path end to end for ``PALPATION_BENCH_SECONDS`` (at most 10 s): the controller
  process, its ring, the bridge's worker thread, snapshots to the GUI thread, the recorder. Rows missing from
  the file (gaps in the tick index, rows the recorder dropped). Goal 0.
* ``review_open_1h_s``: from ``ReviewWindow.open_file`` on that hour to its first map painted (median of 3;
  the first, with cold imports and caches, is ``review_open_1h_first_s``). Goal <= 1 s. The analysis runs in the
  reviewer's worker meanwhile; ``review_findings_1h_s`` is from ``open_file`` to its findings shown (median).
* ``review_open_first_s``: a session never analysed (``BASE_S`` seconds of the simulated session, with a cold
  tissue-model cache, so its flat-field physics is a finite-element solve), from constructing the reviewer with
  the ``review`` command's physics and depth model to its first map painted. Goal <= 3 s.
* ``stitch_9x7_s``: the paper's protocol, 9 areas x 7 levels (1-7 N) over the flat phantom: open the file,
  stitch at 1 mm, detect in both maps (median of 5). Goal <= 0.5 s.
"""

from __future__ import annotations

import dataclasses
import json
import os
import statistics
import threading
import time
from pathlib import Path

import numpy as np

from app.config import load_config
from app.fastforward import FastForward
from app.recording import session_info
from app.rigs import RigSpec, build_rig
from control.config import ControlConfig, RampSettings
from control.messages import LevelRecorded
from hardware.interfaces import TactileConstraints
from session.analysis import AnalysisParams, SessionAnalysis
from session.info import SessionInfo, calibration_of
from session.reader import open_session
from session.stitch import StitchParams
from session.synthetic import level_record
from session.writer import SessionRecorder

NAME = "sessions"
BASE_S = 30.0  # simulated seconds recorded once and tiled to an hour
HOUR_S = 3600.0
RAMP = RampSettings(force_min_N=0.5, force_max_N=2.0, force_step_N=0.5)
FLAT_TUMOURS_XY_M = ((0.012, 0.015), (0.036, 0.015), (0.060, 0.015))


def _shifted(event, dt_s: float, region_offset: int):
    changes = {"t_s": event.t_s + dt_s}
    if isinstance(event, LevelRecorded):
        record = event.record
        changes["record"] = dataclasses.replace(record, t_s=record.t_s + dt_s, region=record.region + region_offset)
    elif hasattr(event, "region"):
        changes["region"] = event.region + region_offset
    return dataclasses.replace(event, **changes)


def record_base() -> tuple[np.ndarray, np.ndarray, list, SessionInfo]:
    config = load_config(None, {"control": {"ramp": RAMP.to_mapping()}})
    rig = build_rig(config.rig)
    info = session_info(config, rig)
    with FastForward(config.control, rig) as ff:
        ff.run_for(BASE_S)
        return ff.ticks.copy(), ff.frames.copy(), list(ff.events), info


def write_hour(path: Path, base: tuple, seconds: float = HOUR_S) -> dict:
    ticks, frames, events, info = base
    n_ticks, period = len(ticks), 1e-3
    regions = 1 + max((e.record.region for e in events if isinstance(e, LevelRecorded)), default=0)
    copies = int(np.ceil(seconds / (n_ticks * period)))
    started = time.perf_counter()
    recorder = SessionRecorder(path, info)
    for k in range(copies):
        dt = k * n_ticks * period
        t = ticks.copy()
        t["tick"] += k * n_ticks
        t["t_s"] += dt
        f = frames.copy()
        f["tick"] += k * n_ticks
        f["t_s"] += dt
        f["sensor_seq"] += k * (int(frames["sensor_seq"][-1]) + 1)
        shifted = [_shifted(e, dt, k * regions) for e in events]
        for second in range(0, n_ticks, 1000):  # one-second pieces, as a display-rate drain delivers them
            piece = t[second:second + 1000]
            recorder.add_ticks(piece)
            recorder.add_frames(f[(f["t_s"] >= piece["t_s"][0]) & (f["t_s"] <= piece["t_s"][-1])])
            recorder.add_events([e for e in shifted if piece["t_s"][0] <= e.t_s <= piece["t_s"][-1]])
        recorder.flush(300.0)  # bounds the queue; the writer never waits for the producer
    status = recorder.close(600.0)
    elapsed = time.perf_counter() - started
    if status.problem:
        raise RuntimeError(status.problem)
    return {
        "logging_headroom_x": status.ticks_written / elapsed / 1000.0,
        "logging_ticks_written": status.ticks_written,
        "logging_frames_written": status.frames_written,
        "logging_levels_written": status.levels_written,
        "logging_wall_s": elapsed,
        "file_mb_per_hour": status.bytes_on_disk / 2**20 * HOUR_S / (status.ticks_written * period),
    }


def time_review_open(path: Path, repeats: int = 3) -> dict:
    from PySide6 import QtCore, QtWidgets

    from widgets.review import ReviewWindow
    from widgets.tactile_map import TactileMapWidget

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication([])
    settings = QtCore.QSettings(str(path.with_suffix(".ini")), QtCore.QSettings.Format.IniFormat)
    times, findings = [], []
    for _ in range(repeats):
        window = ReviewWindow(settings=settings)
        window.resize(1400, 900)
        window.show()
        app.processEvents()
        done = QtCore.QEventLoop()
        window.analysing_changed.connect(lambda busy, done=done: busy or done.quit())
        started = time.perf_counter()
        if not window.open_file(path):
            raise RuntimeError(f"the reviewer could not open {path}")
        window.findChild(TactileMapWidget, "pressureMap").grab()  # painted, not merely scheduled
        app.processEvents()
        times.append(time.perf_counter() - started)
        if window.analysing:
            done.exec()  # the next repeat's first map is not timed against this one's analysis
        if window.analysis is None:
            raise RuntimeError(f"the reviewer could not analyse {path}")
        findings.append(time.perf_counter() - started)
        regions = len(window.session.regions())
        window.close()
        window.deleteLater()
        app.processEvents()
    return {"review_open_1h_s": statistics.median(times), "review_open_1h_first_s": times[0],
            "review_findings_1h_s": statistics.median(findings), "review_1h_regions": regions}


def time_review_first(path: Path) -> dict:
    """The reviewer on a session it has never analysed, its tissue model not in the cache: the physics the
    ``review`` command offers is a finite-element solve, which no longer stands between the window and its map."""
    import tempfile

    from PySide6 import QtCore, QtWidgets

    from app.session_commands import physics_options
    from session.depth import DepthModel
    from tissue.mechanics.cache import ENV_VAR
    from widgets.review import ReviewWindow
    from widgets.review.analysis_worker import THREAD_NAME
    from widgets.tactile_map import TactileMapWidget

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication([])
    settings = QtCore.QSettings(str(path.with_suffix(".ini")), QtCore.QSettings.Format.IniFormat)
    before = os.environ.get(ENV_VAR)
    with tempfile.TemporaryDirectory(prefix="palpation-cold-cache-") as cold:
        os.environ[ENV_VAR] = cold
        try:
            started = time.perf_counter()
            window = ReviewWindow(path, settings=settings, physics=physics_options(),
                                  depth_model=DepthModel.for_session)
            window.resize(1400, 900)
            window.show()
            window.findChild(TactileMapWidget, "pressureMap").grab()
            app.processEvents()
            elapsed = time.perf_counter() - started
            if window.session is None:
                raise RuntimeError(f"the reviewer could not open {path}")
            window.close()  # stops the solve at its next progress report
            window.deleteLater()
            app.processEvents()
            for thread in threading.enumerate():
                if thread.name == THREAD_NAME:
                    thread.join()
        finally:
            if before is None:
                os.environ.pop(ENV_VAR)
            else:
                os.environ[ENV_VAR] = before
    return {"review_open_first_s": elapsed}


def write_9x7(path: Path) -> None:
    sensor = TactileConstraints()
    info = SessionInfo(config={"control": ControlConfig().to_mapping()}, calibration=calibration_of(sensor, 0.0),
                       rig={"backend": "synthetic"})
    with SessionRecorder(path, info) as recorder:
        for region in range(9):
            for level in range(7):
                t = region * 13.0 + level
                record = level_record(region, level, 1.0 + level, (0.004 + 0.008 * region, 0.015),
                                      tumours_xy_m=FLAT_TUMOURS_XY_M, noise=0.03, seed=region * 7 + level, t_s=t)
                recorder.add_events([LevelRecorded(t, record)])


def time_stitch_9x7(path: Path, repeats: int = 5) -> dict:
    times, found = [], 0
    for _ in range(repeats):
        started = time.perf_counter()
        with open_session(path) as session:
            found = len(SessionAnalysis.run(session, AnalysisParams(StitchParams(cell_m=1e-3))).tumours)
        times.append(time.perf_counter() - started)
    return {"stitch_9x7_s": statistics.median(times), "stitch_9x7_tumours_found": found}


class _RecorderFeed:
    """The console's way of feeding a recorder: every row, in the bridge's worker thread."""

    def __init__(self, recorder: SessionRecorder):
        self.recorder = recorder

    def driver_started(self) -> None:
        pass

    def add_rows(self, ticks, frames, events) -> None:
        self.recorder.add_ticks(ticks)
        self.recorder.add_frames(frames)
        self.recorder.add_events(events)

    def driver_stopped(self, failure) -> None:
        pass


def measure_rows_lost(path: Path, seconds: float) -> dict:
    from PySide6 import QtCore, QtWidgets

    from app.bridge import ControllerBridge

    _app = QtWidgets.QApplication.instance() or QtWidgets.QApplication([])  # signals need an application
    config = load_config(None, {"control": {"ramp": RAMP.to_mapping()}})
    recorder = SessionRecorder(path, session_info(config))
    bridge = ControllerBridge.for_process(config.control, RigSpec())
    bridge.add_sink(_RecorderFeed(recorder))
    problems: list[str] = []
    bridge.start_failed.connect(problems.append)
    bridge.crashed.connect(problems.append)
    loop = QtCore.QEventLoop()
    bridge.started.connect(loop.quit)
    bridge.start_failed.connect(loop.quit)
    bridge.start()
    loop.exec()
    if not problems:
        QtCore.QTimer.singleShot(round(seconds * 1000), loop.quit)
        loop.exec()
    bridge.shutdown()  # the last rows reach the recorder in the bridge's thread before this returns
    status = recorder.close()
    if problems:
        raise RuntimeError(problems[0])
    with open_session(path) as session:
        ticks = session.tick_rows(0, session.n_ticks, ["tick"])["tick"]
    missing = int(ticks[-1] + 1 - len(ticks)) if len(ticks) else 0
    return {"rows_lost": missing + status.rows_dropped, "rows_lost_run_s": seconds,
            "rows_lost_ticks_recorded": int(len(ticks))}


def run(out_dir: Path) -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    work = out_dir / "sessions-work"
    work.mkdir(exist_ok=True)
    for old in work.glob("*.h5"):
        old.unlink()
    seconds = min(10.0, float(os.environ.get("PALPATION_BENCH_SECONDS", "10")))
    results: dict = {}
    print(f"sessions: recording {BASE_S:g} s of a simulated session to tile into an hour ...", flush=True)
    base = record_base()
    print("sessions: writing one hour ...", flush=True)
    hour = work / "hour.h5"
    results.update(write_hour(hour, base))
    print("sessions: opening it in the reviewer ...", flush=True)
    results.update(time_review_open(hour))
    print("sessions: opening a session never analysed in the reviewer ...", flush=True)
    first = work / "first.h5"
    write_hour(first, base, BASE_S)
    results.update(time_review_first(first))
    print("sessions: stitching 9 x 7 ...", flush=True)
    nine = work / "nine_by_seven.h5"
    write_9x7(nine)
    results.update(time_stitch_9x7(nine))
    print(f"sessions: the console's pipeline for {seconds:g} s ...", flush=True)
    results.update(measure_rows_lost(work / "pipeline.h5", seconds))
    hour.unlink()  # a gigabyte-class file has no business staying in build/
    print("  ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in sorted(results.items())))
    (out_dir / f"{NAME}.json").write_text(json.dumps(results, indent=2, sort_keys=True) + "\n")
    return results
