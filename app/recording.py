"""Sessions recorded by the application: the console's recording of every controller run, the description a
session file carries, and whole simulated sessions recorded headlessly on a virtual clock."""

from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from PySide6 import QtCore

from app.config import AppConfig
from app.fastforward import FastForward, FastForwardTimeout
from app.realtime import read_clocks
from app.rigs import RigSpec, build_rig
from control.messages import ClearFault, FaultCleared, FaultRaised
from hardware.array_calibration import CalibratedSensor
from hardware.rig import Rig
from hardware.settings import ConfigError
from session.format import CLOCK_INTERVAL_S
from session.info import SessionInfo, calibration_of, new_session_path, sessions_dir, software_version
from session.writer import RecorderError, RecorderStatus, SessionRecorder


def session_info(config: AppConfig, rig: Rig | None = None, spec: RigSpec | None = None) -> SessionInfo:
    """What the session files of a console driving ``rig`` (built from ``spec``, ``config.rig`` by default)
    describe themselves with. Without ``rig`` the rig is built for its sensor geometry, description and
    ground truth, but never opened: the controller opens its own."""
    spec = spec if spec is not None else config.rig
    rig = rig if rig is not None else build_rig(spec)
    phantom = None
    if spec.backend == "sim":
        from tissue.phantom import load_phantom

        phantom = load_phantom(spec.phantom).source
    full_config = {
        "control": config.control.to_mapping(),
        "rig": {k: v for k, v in dataclasses.asdict(spec).items() if k != "sim"},
        "sim": dict(spec.sim),
        "sources": list(config.sources),
    }
    calibration = calibration_of(rig.sensor.constraints, config.control.contact.table_height_m)
    if isinstance(rig.sensor, CalibratedSensor):
        calibration["elements"] = rig.sensor.calibration.to_mapping()
    return SessionInfo(
        config=full_config,
        calibration=calibration,
        rig=dict(rig.description),
        phantom=phantom,
        ground_truth=list(rig.ground_truth),
        software_version=software_version(),
    )


def recording_summary(status: RecorderStatus) -> str:
    """One line on a closed recording, for the operator."""
    text = (f"{status.levels_written} force levels, {status.ticks_written} control periods, "
            f"{status.frames_written} frames, {status.bytes_on_disk / 2**20:.1f} MB")
    lost = status.rows_lost + status.rows_dropped
    return text + (f" ({lost} rows missing)" if lost else "")


class SessionRecording(QtCore.QObject):
    """Records each run of ``controller`` (a :class:`app.bridge.ControllerBridge`) to a file of its own.

    It is one of the bridge's row sinks (:class:`app.bridge.RowSink`): in the bridge's worker thread, a
    recorder is created when the driver starts and closed when it stops or dies (and by :meth:`close` when
    the console quits), and every tick, frame and event goes into it as the bridge drains them. Operator
    notes (:meth:`add_note`, any thread) are stamped with the loop's clock: the time of the newest tick
    row recorded. Create it in the GUI thread, before the controller starts.

    The controller's loop runs on ``time.monotonic()`` (app/controller.py), one clock for every process of
    the machine, so this process reads it beside UTC to pair the two: when a recording begins, every
    CLOCK_INTERVAL_S while rows come, and when it closes.

    Signals: ``recording_started(path)``, ``recording_stopped(path, summary)``, ``problem(message)``
    (recording could not start, or stopped early); receivers in the GUI thread get them there.
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
        self._lock = threading.Lock()  # start/close in the bridge's thread, close once more when quitting
        self._loop_time_s: float | None = None  # of the newest tick row recorded
        self._paired_at_s = -float("inf")  # the loop's clock at the newest pairing with UTC
        self.last_status: RecorderStatus | None = None
        # queued: the writer thread reports through this, the GUI thread shows it
        self._writer_problem.connect(self.problem, QtCore.Qt.ConnectionType.QueuedConnection)
        controller.add_sink(self)

    @property
    def recorder(self) -> SessionRecorder | None:
        """The recorder of the run under way; None between runs."""
        return self._recorder

    def start(self) -> None:
        """Begin a new session file (closing any still open); a failure is reported through ``problem``."""
        self.close()
        folder = self._folder if self._folder is not None else sessions_dir()
        path = new_session_path(folder)
        try:
            recorder = SessionRecorder(path, self._info, on_problem=self._writer_problem.emit, **self._options)
        except RecorderError as err:
            self.problem.emit(f"This session is NOT being recorded: {err}. The controller is unaffected.")
            return
        self._pair_clocks(recorder)
        with self._lock:
            self._recorder, self._loop_time_s = recorder, None
        self.recording_started.emit(str(path))

    def close(self) -> RecorderStatus | None:
        """Close the current session file cleanly (writes what is queued); None if none was open."""
        with self._lock:
            recorder, self._recorder = self._recorder, None
        if recorder is None:
            return None
        self._pair_clocks(recorder)
        status = recorder.close()
        self.last_status = status
        self.recording_stopped.emit(str(status.path), recording_summary(status))
        return status

    def add_note(self, text: str) -> bool:
        """Record an operator's note at the loop's time now; False if no session is being recorded (or no
        tick has been recorded yet to take the time from)."""
        recorder, t_s = self._recorder, self._loop_time_s
        if recorder is None or not recorder.recording or t_s is None:
            return False
        recorder.add_note(text, t_s)
        return True

    # ---- the bridge's row sink (its worker thread) -------------------------------------------------------

    def driver_started(self) -> None:
        self.start()

    def add_rows(self, ticks: np.ndarray, frames: np.ndarray, events: list) -> None:
        recorder = self._recorder
        if recorder is None:
            return
        if len(ticks):
            recorder.add_ticks(ticks)
            self._loop_time_s = float(ticks[-1]["t_s"])
        recorder.add_frames(frames)
        recorder.add_events(events)
        self._pair_clocks(recorder, every=CLOCK_INTERVAL_S)

    def _pair_clocks(self, recorder: SessionRecorder, every: float = 0.0) -> None:
        """Pair the clocks, if ``every`` seconds have passed since the last pairing."""
        loop_s, utc_ns = read_clocks()
        if loop_s - self._paired_at_s >= every:
            self._paired_at_s = loop_s
            recorder.add_clock(loop_s, utc_ns)

    def driver_stopped(self, failure: str | None) -> None:
        recorder = self._recorder
        if failure is not None and recorder is not None:
            recorder.add_controller_lost(failure)
        self.close()


class NominalClock:
    """The pairs of clocks of a session simulated on ``ff``'s virtual clock (app.fastforward.FastForward).

    The virtual clock runs faster than the wall's, so no instant of UTC belongs to a simulated one: UTC here
    is a nominal time line, the moment recording began plus the simulated time since
    (session.format.CLOCK_NOTES). Pairs the clocks at once; then call :meth:`every_interval` as the
    simulation goes on and :meth:`pair` at its end."""

    def __init__(self, recorder: SessionRecorder, ff: FastForward):
        self._recorder, self._ff = recorder, ff
        self._began_ns, self._began_s = time.time_ns(), ff.now_s
        self._paired_at_s: float | None = None
        self.pair()

    def pair(self) -> None:
        now_s = self._ff.now_s
        if now_s != self._paired_at_s:  # the end of a run may fall on a pairing already made
            self._recorder.add_clock(now_s, self._began_ns + round((now_s - self._began_s) * 1e9))
            self._paired_at_s = now_s

    def every_interval(self) -> None:
        """Pair the clocks if CLOCK_INTERVAL_S of simulated time have passed since the last pairing."""
        if self._ff.now_s - self._paired_at_s >= CLOCK_INTERVAL_S:
            self.pair()


OPERATOR_CLEARS_S = 2.0  # a scripted operator's time to read a fault and clear it


def record_simulation(path: str | Path, config: AppConfig, *, rig: Rig | None = None, max_time_s: float = 900.0,
                      chunk_s: float = 0.1, **recorder_options) -> RecorderStatus:
    """Palpate every area of the configured phantom and record it to ``path``; returns the recorder's status.

    ``rig``: a simulated rig built for ``config`` (to choose its tissue model, say); built from the config
    when not given. Raises ConfigError if the rig has no scripted operator, FastForwardTimeout if the operator
    has not finished after ``max_time_s`` of simulated time (the file is still closed cleanly).

    A fault (a ceiling reached on a bump's crest, say) ends the area it happened in, as at the console; the
    operator reads it and clears it ``OPERATOR_CLEARS_S`` later (again as often, while the loop still refuses,
    the probe not yet lifted clear), and goes on with the next area, so one fault does not leave the rest of
    the tissue unpalpated.
    """
    if chunk_s <= 0:
        raise ValueError(f"chunk_s must be > 0, got {chunk_s!r}")
    rig = rig if rig is not None else build_rig(config.rig)
    operator = rig.master
    if operator is None or not hasattr(operator, "finished"):
        raise ConfigError("rig.backend", "recording a simulation needs the simulated rig's scripted operator")
    recorder = SessionRecorder(path, session_info(config, rig), **recorder_options)
    try:
        with FastForward(config.control, rig) as ff:
            clock = NominalClock(recorder, ff)
            clear_at = None
            while not operator.finished:
                if ff.now_s > max_time_s:
                    raise FastForwardTimeout(f"the scripted operator had not finished after {max_time_s:g} s of "
                                             f"simulated time ({len(operator.outcomes)} areas done)")
                if clear_at is not None and ff.now_s >= clear_at:
                    ff.send(ClearFault())
                    clear_at = ff.now_s + OPERATOR_CLEARS_S
                ff.run_for(chunk_s)
                for event in ff.events:
                    if isinstance(event, FaultRaised):
                        clear_at = event.t_s + OPERATOR_CLEARS_S
                    elif isinstance(event, FaultCleared):
                        clear_at = None
                recorder.add_ticks(ff.ticks)
                recorder.add_frames(ff.frames)
                recorder.add_events(ff.events)
                ff.clear()
                clock.every_interval()
            clock.pair()
    finally:
        status = recorder.close()
    return status
