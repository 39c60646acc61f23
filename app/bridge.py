"""The GUI's handle on the controller: a worker QThread that drives, drains and watches it.

The worker owns the driver (a :class:`~app.controller.ControllerProcess`, or a
:class:`~app.fastforward.FastForward` for GUI tests and demos), and a display-rate timer living in its
thread. Each timer tick drains the telemetry rings and the event channel and emits ONE
:class:`~control.telemetry.LiveSnapshot` with everything since the previous one, so the GUI thread does
display-rate work however fast the loop runs. Commands go the other way through a queued signal.

Signals (all delivered in the bridge's thread):

* ``started()``, ``stopped()``: the driver is running / was stopped on request;
* ``start_failed(str)``: the driver could not start (the rig did not open, ...);
* ``crashed(str)``: the driver died on its own (exit code and its last message);
* ``snapshot(LiveSnapshot)``: at display rate while running (it carries every tick row and event, but only
  the latest frame);
* ``silent(float)``: the controller process, alive, has written no tick for that many seconds (stopped, hung
  or starved of CPU), at display rate from CONTROLLER_SILENT_S on; ``answering(float)`` once it writes again,
  with how long it was silent.

Every row the controller produces (ticks, frames, events) also goes, in the worker thread itself, to the
:class:`RowSink` objects added with :meth:`ControllerBridge.add_sink`: the session recorder is fed there,
so recording never waits for the GUI thread and the GUI thread never handles rows it does not draw.
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np
from PySide6.QtCore import QCoreApplication, QObject, Qt, QThread, QTimer, Signal, Slot

from app.controller import ControllerProcess, PacingOptions
from app.fastforward import FastForward
from app.rigs import RigSpec, build_rig
from control.config import ControlConfig
from control.messages import Command, Notice
from control.telemetry import FRAME_DTYPE, TICK_DTYPE, LiveSnapshot

log = logging.getLogger(__name__)

Driver = ControllerProcess | FastForward

# A stalled display thread must not make the fast-forward driver catch up in one enormous burst.
_MAX_CATCH_UP_S = 0.25
# A controller that writes no tick for this long is not answering: it writes 1,000 a second, and this host
# stalls it 20-40 ms now and then. Checked at display rate (16 ms), so told within 80 ms: a process stopped by
# SIGSTOP was shown as force control with a green "Loop OK" for 12.5 s.
CONTROLLER_SILENT_S = 0.06
_NO_TICKS = np.empty(0, TICK_DTYPE)


def _exit_description(code: int | None) -> str:
    if code is None:
        return "exit code unknown"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


class RowSink(Protocol):
    """Takes every row the controller produces; called in the bridge's worker thread, in order."""

    def driver_started(self) -> None:
        """The driver runs; rows follow."""

    def add_rows(self, ticks: np.ndarray, frames: np.ndarray, events: list) -> None:
        """TICK_DTYPE and FRAME_DTYPE rows and control events since the previous call (any may be empty)."""

    def driver_stopped(self, failure: str | None) -> None:
        """The driver stopped, on request (``failure`` None) or on its own (``failure`` says how); the rows
        it left have been added."""


class _Pump:
    """What the worker needs from a driver: start, send, a display-rate drain, stop."""

    def __init__(self):
        self._last_tick: np.ndarray | None = None
        self._last_frame: np.ndarray | None = None
        self._held_events: list = []

    def _snapshot(self, ticks: np.ndarray, frames: np.ndarray, events: list, health) -> LiveSnapshot | None:
        if len(ticks):
            self._last_tick = ticks[-1:].copy().reshape(())
        if len(frames):
            self._last_frame = frames[-1:].copy().reshape(())
        if self._held_events:
            events = self._held_events + events
            self._held_events = []
        if self._last_tick is None:
            # Events can overtake the first tick row (different channels); a snapshot needs a tick.
            self._held_events = events
            return None
        if not (len(ticks) or events):
            return None
        return LiveSnapshot(tick=self._last_tick, frame=self._last_frame, ticks=ticks, events=events, health=health)


class _ProcessPump(_Pump):
    def __init__(self, process: ControllerProcess):
        super().__init__()
        self.process = process
        self._tick_cursor = 0
        self._frame_cursor = 0
        self._heard = None  # when the newest tick row arrived (monotonic s); None before the first

    def silence_s(self) -> float:
        """How long the controller has written no tick (0 before its first)."""
        return 0.0 if self._heard is None else time.monotonic() - self._heard

    def start(self) -> None:
        self.process.start()

    def send(self, command: Command) -> None:
        self.process.send(command)

    def pump(self) -> tuple[LiveSnapshot | None, np.ndarray, str | None]:
        proc = self.process
        alive = proc.is_alive  # before draining, so rows written just before a death are still read
        ticks, self._tick_cursor, lost = proc.ticks.read_since(self._tick_cursor)
        if len(ticks):
            self._heard = time.monotonic()
        frames, self._frame_cursor, lost_frames = proc.frames.read_since(self._frame_cursor)
        events = proc.drain_events()
        if lost or lost_frames:
            t = float(ticks[-1]["t_s"]) if len(ticks) else 0.0
            events.append(Notice(t, f"The display fell behind: {lost} tick rows and {lost_frames} sensor frames "
                                    "were overwritten before they could be read.", level="warning"))
        failure = None
        if not alive:
            failure = f"The controller process stopped unexpectedly ({_exit_description(proc.exitcode)})"
            if proc.failure:
                failure += f": {proc.failure}"
        return self._snapshot(ticks, frames, events, proc.health), frames, failure

    def stop(self) -> None:
        self.process.stop()


class _FastForwardPump(_Pump):
    def __init__(self, ff: FastForward, speed: float):
        super().__init__()
        self.ff = ff
        self.speed = speed
        self._wall = time.perf_counter()
        self._owed_s = 0.0

    def start(self) -> None:
        self._wall = time.perf_counter()

    def send(self, command: Command) -> None:
        self.ff.send(command)

    def pump(self) -> tuple[LiveSnapshot | None, np.ndarray, str | None]:
        now = time.perf_counter()
        self._owed_s += min(now - self._wall, _MAX_CATCH_UP_S) * self.speed
        self._wall = now
        period = self.ff.config.period_s
        n = int(self._owed_s / period)
        self._owed_s -= n * period
        try:
            self.ff.step(n)
        except Exception as err:  # noqa: BLE001 - the GUI must hear about it, like a crashed process
            return None, np.empty(0, FRAME_DTYPE), f"The fast-forward controller failed: {type(err).__name__}: {err}"
        ticks, frames, events = self.ff.ticks.copy(), self.ff.frames.copy(), self.ff.events
        self.ff.clear()
        return self._snapshot(ticks, frames, events, None), frames, None

    def stop(self) -> None:
        self.ff.close()


class _Worker(QObject):
    started = Signal()
    stopped = Signal()
    start_failed = Signal(str)
    crashed = Signal(str)
    snapshot = Signal(object)
    silent = Signal(float)
    answering = Signal(float)

    def __init__(self, make_driver: Callable[[], Driver], interval_ms: int, speed: float, home: QThread):
        super().__init__()
        self.sinks: list[RowSink] = []
        self._make_driver = make_driver
        self._interval_ms = interval_ms
        self._speed = speed
        self._home = home
        self._pump: _Pump | None = None
        self._timer: QTimer | None = None
        self._stopped_on_request = False
        self._silent_s = 0.0  # how long the controller was silent, while it is

    @Slot()
    def start_driver(self) -> None:
        if self._pump is not None:
            return
        try:
            driver = self._make_driver()
            if isinstance(driver, ControllerProcess):
                pump = _ProcessPump(driver)
            elif isinstance(driver, FastForward):
                pump = _FastForwardPump(driver, self._speed)
            else:
                raise TypeError(f"the driver factory returned {type(driver).__name__}, "
                                "not a ControllerProcess or FastForward")
            pump.start()
        except Exception as err:  # noqa: BLE001 - reported to the operator through start_failed
            self.start_failed.emit(f"{type(err).__name__}: {err}" if str(err) else type(err).__name__)
            return
        self._pump = pump
        self._stopped_on_request = False
        for sink in self.sinks:
            sink.driver_started()
        if self._timer is None:
            self._timer = QTimer(self)
            self._timer.setTimerType(Qt.TimerType.PreciseTimer)
            self._timer.timeout.connect(self._on_timer)
        self._timer.start(self._interval_ms)
        self.started.emit()

    @Slot()
    def stop_driver(self) -> None:
        if self._pump is None:
            return
        self._stopped_on_request = True
        self._timer.stop()
        self._on_timer()  # hand the GUI what arrived since the last display tick
        if self._pump is not None:  # the last drain may have found it dead
            self._release_pump()
            self._sinks_stopped(None)
            self.stopped.emit()

    @Slot(object)
    def send(self, command: Command) -> None:
        if self._pump is None:
            # After the operator stopped it (quitting, say), a command still in flight (a jog key's repeat)
            # has nowhere to go and nothing to tell; before a start, or after a crash, it is worth a warning.
            level = logging.DEBUG if self._stopped_on_request else logging.WARNING
            log.log(level, "controller is not running; %s was not sent", type(command).__name__)
            return
        try:
            self._pump.send(command)
        except RuntimeError as err:  # the process died between two display ticks; the next one reports it
            log.warning("%s", err)

    @Slot()
    def shutdown(self) -> None:
        self.stop_driver()
        if self._timer is not None:
            self._timer.stop()
        # Back to the bridge's thread, so this object and its timer are destroyed where they will live.
        self.moveToThread(self._home)

    @Slot()
    def _on_timer(self) -> None:
        pump = self._pump
        if pump is None:
            return
        try:
            snapshot, frames, failure = pump.pump()
        except Exception as err:  # noqa: BLE001 - a drain that fails every 16 ms must stop, and say why
            log.exception("draining the controller failed")
            snapshot, frames, failure = None, np.empty(0, FRAME_DTYPE), f"Reading the controller failed: {err}"
        if snapshot is not None or len(frames):
            ticks, events = (snapshot.ticks, snapshot.events) if snapshot is not None else (_NO_TICKS, [])
            for sink in self.sinks:
                sink.add_rows(ticks, frames, events)
        if snapshot is not None:
            self.snapshot.emit(snapshot)
        if failure is None and isinstance(pump, _ProcessPump):
            silence = pump.silence_s()
            if silence >= CONTROLLER_SILENT_S:
                self._silent_s = silence
                self.silent.emit(silence)
            elif self._silent_s:
                self.answering.emit(self._silent_s)
                self._silent_s = 0.0
        if failure is not None:
            self._timer.stop()
            self._release_pump()
            self._sinks_stopped(failure)
            self.crashed.emit(failure)

    def _sinks_stopped(self, failure: str | None) -> None:
        for sink in self.sinks:
            sink.driver_stopped(failure)

    def _release_pump(self) -> None:
        pump, self._pump = self._pump, None
        self._silent_s = 0.0
        try:
            pump.stop()
        except Exception:  # noqa: BLE001 - cleanup of a dead driver must not hide why it died
            log.exception("error while stopping the controller driver")


class ControllerBridge(QObject):
    """Create it in the GUI thread; call :meth:`shutdown` before the application quits (it also hooks
    ``aboutToQuit``). ``make_driver`` runs in the worker thread and returns an unstarted
    :class:`ControllerProcess` or a ready :class:`FastForward`."""

    snapshot = Signal(object)
    started = Signal()
    stopped = Signal()
    start_failed = Signal(str)
    crashed = Signal(str)
    silent = Signal(float)
    answering = Signal(float)

    _start_requested = Signal()
    _stop_requested = Signal()
    _command_sent = Signal(object)
    _shutdown_requested = Signal()

    def __init__(self, make_driver: Callable[[], Driver], display_hz: float = 60.0, speed: float = 1.0,
                 parent: QObject | None = None):
        super().__init__(parent)
        if not 1.0 <= display_hz <= 500.0:
            raise ValueError(f"display_hz must be within 1..500, got {display_hz}")
        if speed <= 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self._running = False
        self._shut_down = False
        self._thread = QThread()
        self._thread.setObjectName("controller-bridge")
        self._worker = _Worker(make_driver, max(1, round(1000.0 / display_hz)), speed, self.thread())
        self._worker.moveToThread(self._thread)
        self._start_requested.connect(self._worker.start_driver)
        self._stop_requested.connect(self._worker.stop_driver)
        self._command_sent.connect(self._worker.send)
        self._shutdown_requested.connect(self._worker.shutdown, Qt.ConnectionType.BlockingQueuedConnection)
        self._worker.started.connect(self._on_started)
        self._worker.stopped.connect(self._on_stopped)
        self._worker.crashed.connect(self._on_crashed)
        self._worker.start_failed.connect(self.start_failed)
        self._worker.snapshot.connect(self.snapshot)
        self._worker.silent.connect(self.silent)
        self._worker.answering.connect(self.answering)
        app = QCoreApplication.instance()
        if app is not None:
            app.aboutToQuit.connect(self.shutdown)

    @classmethod
    def for_process(cls, config: ControlConfig, rig_spec: RigSpec, options: PacingOptions | None = None,
                    **kwargs) -> ControllerBridge:
        return cls(lambda: ControllerProcess(config, rig_spec, options), **kwargs)

    @classmethod
    def for_fast_forward(cls, config: ControlConfig, rig_spec: RigSpec, speed: float = 1.0,
                         **kwargs) -> ControllerBridge:
        """``speed`` simulated seconds per wall-clock second."""
        return cls(lambda: FastForward(config, build_rig(rig_spec)), speed=speed, **kwargs)

    @property
    def running(self) -> bool:
        return self._running

    def add_sink(self, sink: RowSink) -> None:
        """Feed ``sink`` every row from now on, in the worker thread (add it before :meth:`start`)."""
        if self._thread.isRunning():
            raise RuntimeError("add sinks before the bridge starts: its worker thread reads them")
        self._worker.sinks.append(sink)

    def start(self) -> None:
        """Start the driver; ``started`` or ``start_failed`` follows."""
        if self._shut_down:
            raise RuntimeError("this ControllerBridge was shut down; create a new one")
        if not self._thread.isRunning():
            self._thread.start()
        self._start_requested.emit()

    def stop(self) -> None:
        """Stop the driver (safe hold, rig closed); ``stopped`` follows. The thread stays for a restart."""
        self._stop_requested.emit()

    def send(self, command: Command) -> None:
        """Queue a command for the controller (any thread)."""
        if not isinstance(command, Command):
            raise TypeError(f"not a control command: {command!r} (see control.messages.Command)")
        self._command_sent.emit(command)

    @Slot()
    def shutdown(self) -> None:
        """Stop the driver and the worker thread, and wait for both. Safe to call twice."""
        if self._thread.isRunning():
            if QThread.currentThread() is self._thread:
                raise RuntimeError("shutdown() must not be called from the bridge's own worker thread")
            self._shutdown_requested.emit()
            self._thread.quit()
            self._thread.wait()
        self._shut_down = True
        self._running = False

    @Slot()
    def _on_started(self) -> None:
        self._running = True
        self.started.emit()

    @Slot()
    def _on_stopped(self) -> None:
        self._running = False
        self.stopped.emit()

    @Slot(str)
    def _on_crashed(self, message: str) -> None:
        self._running = False
        self.crashed.emit(message)
