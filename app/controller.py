"""The controller process: the 1 kHz loop in a process of its own, and the parent-side handle to it.

Why a process: PySide releases and retakes the GIL around nearly every Qt call, so a control thread in
the GUI process misses its period whenever pyqtgraph paints (measured in docs/performance.md, "The 1 kHz
loop's real time").

Channels between the two sides:

* commands, parent -> child: a ``multiprocessing.Queue`` of the typed dataclasses of
  :mod:`control.messages` (plus :class:`Shutdown`), and beside it a shared-memory count of the commands
  sent. The child compares that count with the number it has received at the start of every tick and
  reads the queue only when they differ: finding a queue empty costs a system call and an exception
  (about 40 us with cold caches, measured), reading a shared integer well under 1 us. A command whose
  bytes have not reached the pipe yet is read on a later tick: the count never lets one be forgotten;
* telemetry, child -> parent: two :class:`~app.ring.SharedRing` (tick rows, frame rows) the parent creates
  and owns, so they are released even if the child is killed;
* events, child -> parent: a one-way pipe fed by a sender thread in the child, carrying the loop's events,
  :class:`~control.telemetry.LoopHealth` reports and this module's :class:`ControllerStarted`,
  :class:`ControllerFailed` and :class:`ControllerStopped`. The parent holds only the read end, so a dead
  child shows up as end-of-file instead of a read that waits forever for half a message.

Pacing: tick ``k`` is due at the absolute deadline ``t0 + k * period``; the child sleeps until
``spin_s`` before it and spins the rest (see :class:`PacingOptions` for why it spins most of the period
when it runs with SCHED_FIFO). A tick that starts more than one period late does not cause
the missed ticks to be replayed back to back: they are counted (``missed_ticks``), the deadline grid
moves on to the current period, and the loop clamps its integration step (``ControlConfig.max_step_s``).
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import logging
import multiprocessing as mp
import os
import queue
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from app.realtime import claim_realtime
from app.rigs import RigSpec, build_rig, prepare_rig
from app.ring import RingHandle, SharedRing
from app.runtime import make_loop, run_tick
from control.config import ControlConfig
from control.messages import Command
from control.telemetry import FRAME_DTYPE, TICK_DTYPE, LoopHealth

log = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_ORPHANED = 3  # the parent died: the child held the slave and left

# SCHED_FIFO priority: below the kernel's threaded interrupt handlers (50), so the serial/USB devices the
# loop talks to are still serviced while it runs.
DEFAULT_RT_PRIORITY = 40


# ---- messages that only exist between the driver and its parent --------------------------------------


@dataclass(frozen=True, slots=True)
class Shutdown:
    """Parent -> child: hold the slave, close the rig and exit."""


@dataclass(frozen=True, slots=True)
class ControllerStarted:
    pid: int
    rt_priority: bool
    cpu: int | None
    warning: str


@dataclass(frozen=True, slots=True)
class ControllerFailed:
    """The child hit an exception (or lost its parent) and is exiting non-zero."""

    message: str
    details: str = ""  # the traceback, for the log


@dataclass(frozen=True, slots=True)
class ControllerStopped:
    ticks: int
    missed_ticks: int


class ControllerStartError(RuntimeError):
    """The controller process could not start (rig failed to open, bad settings, ...)."""


@dataclass(frozen=True)
class PacingOptions:
    """How the child waits for its deadlines.

    It sleeps until ``spin_s`` before a deadline and spins the rest. Without SCHED_FIFO the spin is short
    (``spin_s``): sleeps overshoot by ~65 us median here, and a process that spins longer loses out to the
    scheduler. With SCHED_FIFO it spins most of the period (``rt_spin_s``): a CPU that halts between
    ticks comes back with cold caches, and the same tick then costs 2-2.5x as much (measured: 48 us hot,
    105-125 us after a 0.8 ms sleep, 70-80 us after 50-100 us). It still sleeps ``min_sleep_s`` each
    period when the tick left that much time: the kernel throttles SCHED_FIFO tasks for 50 ms once they
    have run 95 % of a second (sched_rt_runtime_us), and spinning whole periods ran into exactly that.
    """

    realtime: bool = True  # ask for SCHED_FIFO
    pin_cpu: bool = True  # pin the loop to the last CPU and move the parent's threads off it
    rt_priority: int = DEFAULT_RT_PRIORITY
    spin_s: float = 150e-6
    rt_spin_s: float = 10e-3  # longer than a period: with SCHED_FIFO, sleep only min_sleep_s
    min_sleep_s: float = 100e-6
    health_interval_s: float = 0.5

    def __post_init__(self):
        if not 1 <= self.rt_priority <= 99:
            raise ValueError(f"rt_priority must be within 1..99, got {self.rt_priority}")
        for name in ("spin_s", "rt_spin_s"):
            if not 0 <= getattr(self, name) <= 0.01:
                raise ValueError(f"{name} must be within [0, 0.01] s, got {getattr(self, name)}")
        if not 0 <= self.min_sleep_s < 1e-3:
            raise ValueError(f"min_sleep_s must be within [0, 1) ms, got {self.min_sleep_s}")
        if self.health_interval_s <= 0:
            raise ValueError(f"health_interval_s must be > 0, got {self.health_interval_s}")


# ---- parent side --------------------------------------------------------------------------------------


class ControllerProcess:
    """Parent-side handle: start, command, watch and stop the controller process.

    Not thread-safe apart from :meth:`send`; one thread (the GUI's bridge worker, a script, a test) drives it.
    """

    def __init__(
        self,
        config: ControlConfig,
        rig_spec: RigSpec,
        options: PacingOptions | None = None,
        tick_capacity: int = 16384,
        frame_capacity: int = 1024,
        progress: Callable[[float, str], None] | None = None,
    ):
        if not isinstance(config, ControlConfig):
            raise TypeError(f"config must be a ControlConfig, got {type(config).__name__}")
        if not isinstance(rig_spec, RigSpec):
            raise TypeError(f"rig_spec must be a RigSpec, got {type(rig_spec).__name__}")
        self.config = config
        self._progress = progress  # reports of the rig's one-off preparation (tissue precompute)
        self.rig_spec = rig_spec
        self.options = options or PacingOptions()
        self._capacities = (tick_capacity, frame_capacity)
        self.ticks: SharedRing | None = None
        self.frames: SharedRing | None = None
        self.health: LoopHealth | None = None
        self.started_info: ControllerStarted | None = None
        self.failure: str | None = None  # the child's last ControllerFailed message
        self.stopped_info: ControllerStopped | None = None  # set after a clean stop
        self._process: mp.process.BaseProcess | None = None
        self._commands: mp.queues.Queue | None = None
        self._sent = None  # shared count of the commands put on the queue (see the module docstring)
        self._send_lock = threading.Lock()
        self._events: Connection | None = None
        self._pending: list = []
        self._cpu_reservation: _CpuReservation | None = None
        self._started = False

    # -- lifetime

    def start(self, timeout_s: float = 30.0) -> None:
        """Spawn the child and wait until its loop runs; raise ControllerStartError with its message if not."""
        if self._started:
            raise RuntimeError("this ControllerProcess was already started; create a new one")
        self._started = True
        try:
            prepare_rig(self.rig_spec, self._progress)
        except Exception as err:  # noqa: BLE001 - reported like any other start-up failure
            raise ControllerStartError(f"could not prepare the rig: {_describe(err)}") from err
        ctx = mp.get_context("spawn")
        child_end = None
        try:
            self.ticks = SharedRing.create(TICK_DTYPE, self._capacities[0])
            self.frames = SharedRing.create(FRAME_DTYPE, self._capacities[1])
            self._commands = ctx.Queue()
            self._sent = ctx.RawValue(ctypes.c_uint64, 0)
            self._events, child_end = ctx.Pipe(duplex=False)
            process = ctx.Process(
                target=_child_main,
                args=(self.config, self.rig_spec, self.options, self.ticks.handle, self.frames.handle,
                      _CommandInbox(self._commands, self._sent), child_end),
                name="palpation-controller",
                daemon=True,  # a parent that exits without stop() still takes the child down (SIGTERM: hold)
            )
            process.start()
            self._process = process
        except BaseException:
            self._release()
            raise
        finally:
            if child_end is not None:
                child_end.close()  # the child holds the only write end now: its death reads as end-of-file
        try:
            error = self._wait_until_started(timeout_s)
        except BaseException:  # Ctrl-C while waiting: never leave a half-started controller behind
            self.stop(timeout_s=2.0)
            raise
        if error is not None:
            self.stop(timeout_s=2.0)
            raise ControllerStartError(error)
        if self.options.pin_cpu and self.started_info.cpu is not None:
            self._cpu_reservation = _CpuReservation.claim(self.started_info.cpu)

    def _wait_until_started(self, timeout_s: float) -> str | None:
        deadline = time.monotonic() + timeout_s
        while self.started_info is None:
            left = deadline - time.monotonic()
            if left <= 0:
                return f"the controller process did not start within {timeout_s:g} s"
            if self._events.poll(min(left, 0.1)) and not self._receive():
                # End of file: the child is exiting; let it finish so its exit code is known.
                self._process.join(min(left, 2.0))
                return self.failure or (f"the controller process exited with code {self._process.exitcode} while "
                                        "starting (its error output says why)")
            if self.failure is not None:
                return self.failure
        return None

    def stop(self, timeout_s: float = 3.0) -> int | None:
        """Ask the child to hold the slave and exit; escalate to SIGTERM, then SIGKILL. Returns the exit code.

        Always releases the shared memory and queues; safe to call twice and after a crash.
        """
        process = self._process
        if process is None:
            self._release()
            return None
        if process.is_alive():
            with contextlib.suppress(ValueError, OSError, AttributeError):  # the queue is closed already
                self._put(Shutdown())
            deadline = time.monotonic() + timeout_s
            # Keep reading while waiting: a child blocked on a full event pipe could not finish otherwise.
            while process.is_alive() and time.monotonic() < deadline:
                self._receive()
                process.join(0.02)
            if process.is_alive():
                log.warning("controller process did not stop within %.1f s; terminating it", timeout_s)
                process.terminate()
                process.join(1.0)
            if process.is_alive():
                process.kill()
                process.join()
        else:
            process.join()
        self._receive()
        self._release()
        return process.exitcode

    def _release(self) -> None:
        if self._cpu_reservation is not None:
            self._cpu_reservation.release()
            self._cpu_reservation = None
        if self._commands is not None:
            self._commands.close()
            # Commands the dead child never read must not keep this process from exiting.
            self._commands.cancel_join_thread()
            self._commands = None
        if self._events is not None:
            self._events.close()
            self._events = None
        for ring in (self.ticks, self.frames):
            if ring is not None:
                ring.unlink()

    def __enter__(self) -> ControllerProcess:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- state

    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    @property
    def is_alive(self) -> bool:
        return self._process is not None and self._process.is_alive()

    @property
    def exitcode(self) -> int | None:
        return self._process.exitcode if self._process is not None else None

    # -- commands and events

    def send(self, command: Command) -> None:
        """Queue a command for the next tick (thread-safe)."""
        if not isinstance(command, Command):
            raise TypeError(f"not a control command: {command!r} (see control.messages.Command)")
        if self._commands is None or not self.is_alive:
            raise RuntimeError(f"the controller process is not running; {type(command).__name__} was not sent")
        self._put(command)

    def _put(self, command) -> None:
        # Under one lock, so the count never runs ahead of a command another thread has yet to put.
        with self._send_lock:
            self._commands.put(command)
            self._sent.value += 1

    def drain_events(self) -> list:
        """The loop's events (control.messages) received since the last call, oldest first.

        Also updates :attr:`health`, :attr:`failure` and :attr:`started_info` from the driver's own messages.
        """
        self._receive()
        events, self._pending = self._pending, []
        return events

    def _receive(self) -> bool:
        """Read everything the child sent so far; False once the channel is closed (the child ended)."""
        conn = self._events
        if conn is None:
            return False
        try:
            while conn.poll():
                self._dispatch(conn.recv())
        except (EOFError, OSError):
            return False
        return True

    def _dispatch(self, message) -> None:
        if isinstance(message, LoopHealth):
            self.health = message
        elif isinstance(message, ControllerStarted):
            self.started_info = message
        elif isinstance(message, ControllerFailed):
            self.failure = message.message
            if message.details:
                log.error("controller process failed: %s\n%s", message.message, message.details)
        elif isinstance(message, ControllerStopped):
            self.stopped_info = message
        else:
            self._pending.append(message)


class _CpuReservation:
    """Moves every thread of this process off the controller's CPU, and back when released."""

    def __init__(self, saved: dict[int, set[int]], fallback: set[int]):
        self._saved = saved
        self._fallback = fallback

    @classmethod
    def claim(cls, cpu: int) -> _CpuReservation | None:
        if not hasattr(os, "sched_setaffinity"):
            return None
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{os.getpid()}/task")]
            fallback = os.sched_getaffinity(os.getpid())
        except OSError:
            return None
        saved: dict[int, set[int]] = {}
        for tid in tids:
            try:
                mask = os.sched_getaffinity(tid)
                if cpu in mask and len(mask) > 1:
                    os.sched_setaffinity(tid, mask - {cpu})
                    saved[tid] = mask
            except OSError as err:  # thread ended meanwhile, or not permitted
                log.debug("could not move thread %d off CPU %d: %s", tid, cpu, err)
        return cls(saved, fallback)

    def release(self) -> None:
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{os.getpid()}/task")]
        except OSError:
            return
        for tid in tids:
            # Threads started meanwhile inherited the narrowed mask: give them the process's original one.
            try:
                os.sched_setaffinity(tid, self._saved.get(tid, self._fallback))
            except OSError as err:
                log.debug("could not restore the CPU mask of thread %d: %s", tid, err)


# ---- child side ---------------------------------------------------------------------------------------


class _Terminated(BaseException):
    """SIGTERM in the child: unwind to the safe-hold path."""


class _EventSender:
    """Sends events to the parent from a thread of its own, so a slow reader never blocks a tick.

    Start it only once the loop thread has its scheduling policy and CPU: the thread inherits both. A
    sender left at normal priority on the GUI's CPU would take the GIL while the loop sleeps, be preempted
    there, and hold the loop up for milliseconds (measured: 5-25 ms stalls under load).
    """

    def __init__(self, conn: Connection):
        self._conn = conn
        self._queue: queue.SimpleQueue = queue.SimpleQueue()  # buffers messages put before start()
        self._thread = threading.Thread(target=self._run, name="controller-events", daemon=True)

    def start(self) -> None:
        if self._thread.ident is None:
            self._thread.start()

    def put(self, message) -> None:
        self._queue.put(message)

    def _run(self) -> None:
        while (message := self._queue.get()) is not None:
            try:
                self._conn.send(message)
            except (BrokenPipeError, ConnectionResetError, OSError):
                return  # the parent is gone; the loop notices through its parent check

    def close(self, timeout_s: float = 2.0) -> None:
        self.start()  # a start-up failure is reported before the loop ever ran
        self._queue.put(None)
        self._thread.join(timeout_s)
        self._conn.close()


class _Stats:
    """Timing statistics for LoopHealth: since start, and over the current report window."""

    def __init__(self, period_s: float, window_s: float):
        self.period_s = period_s
        self.ticks = 0
        self.late_over_0_5ms = 0
        self.missed = 0
        self.longest_stall_s = 0.0
        self._intervals = np.empty(int(window_s / period_s * 4) + 16)
        self._n = 0
        self._window_ticks = 0
        self._window_start = None
        self._prev_start = None

    def add(self, start_s: float, late_s: float, missed: int) -> None:
        self.ticks += 1
        self.missed = missed
        self._window_ticks += 1
        if late_s > 0.5e-3:
            self.late_over_0_5ms += 1
        self.longest_stall_s = max(self.longest_stall_s, late_s)
        if self._prev_start is not None and self._n < len(self._intervals):
            self._intervals[self._n] = start_s - self._prev_start
            self._n += 1
        if self._window_start is None:
            self._window_start = start_s
        self._prev_start = start_s

    def report(self, now_s: float, rt: bool, cpu: int | None, warning: str) -> LoopHealth:
        elapsed = now_s - self._window_start if self._window_start is not None else 0.0
        jitter = np.abs(self._intervals[: self._n] - self.period_s)
        health = LoopHealth(
            rate_hz=self._window_ticks / elapsed if elapsed > 0 else 0.0,
            late_over_0_5ms_pct=100.0 * self.late_over_0_5ms / self.ticks if self.ticks else 0.0,
            p99_abs_jitter_us=float(np.percentile(jitter, 99)) * 1e6 if self._n else 0.0,
            missed_ticks=self.missed,
            longest_stall_ms=self.longest_stall_s * 1e3,
            rt_priority=rt,
            cpu=cpu,
            warning=warning,
        )
        self._n = 0
        self._window_ticks = 0
        self._window_start = now_s
        return health


class _CommandInbox:
    """The child's end of the command channel: the queue, read only when the shared count says so."""

    def __init__(self, commands: mp.queues.Queue, sent):
        self._commands = commands
        self._sent = sent
        self._received = 0

    def take(self) -> Sequence:
        """The commands that have arrived, oldest first (usually none, at the cost of one shared read)."""
        if self._sent.value == self._received:
            return ()
        out = []
        while self._received < self._sent.value:
            try:
                out.append(self._commands.get_nowait())
            except queue.Empty:
                break  # counted, but its bytes are still on their way: the next tick reads it
            self._received += 1
        return out


def _child_main(config, rig_spec, options, tick_handle: RingHandle, frame_handle: RingHandle,
                commands: _CommandInbox, events_conn):
    """Entry point of the controller process."""
    sys.exit(_ControllerChild(config, rig_spec, options, tick_handle, frame_handle, commands, events_conn).run())


class _ControllerChild:
    def __init__(self, config: ControlConfig, rig_spec: RigSpec, options: PacingOptions, tick_handle: RingHandle,
                 frame_handle: RingHandle, commands: _CommandInbox, events_conn: Connection):
        self.config = config
        self.rig_spec = rig_spec
        self.options = options
        self.handles = (tick_handle, frame_handle)
        self.commands = commands
        self.sender = _EventSender(events_conn)
        self.parent_pid = os.getppid()
        self.rings: list[SharedRing] = []
        self.rig = None
        self.opened = False
        self.stats = _Stats(config.period_s, options.health_interval_s)

    def run(self) -> int:
        # Ctrl-C in a terminal reaches the whole process group; the parent decides how the child stops.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, _raise_terminated)
        code = EXIT_OK
        try:
            self._set_up()
            code = self._pace()
            self.sender.put(ControllerStopped(self.stats.ticks, self.stats.missed))
        except _Terminated:
            code = EXIT_OK
        except BaseException as err:  # noqa: BLE001 - everything must reach the operator, then exit non-zero
            code = EXIT_FAILED
            self.sender.put(ControllerFailed(_describe(err), traceback.format_exc()))
        finally:
            signal.signal(signal.SIGTERM, signal.SIG_IGN)  # the safe-hold path must run to the end
            if self.opened:
                problem = _hold_and_close(self.rig)
                if problem:
                    code = EXIT_FAILED
                    self.sender.put(ControllerFailed(problem))
            for ring in self.rings:
                ring.close()
            self.sender.close()
        return code

    def _set_up(self) -> None:
        for handle in self.handles:
            self.rings.append(handle.attach())
        self.rig = build_rig(self.rig_spec)
        self.loop = make_loop(self.config, self.rig)
        self.rig.open()  # closes whatever it opened if one device fails
        self.opened = True
        claim = claim_realtime(self.options.realtime, self.options.rt_priority, self.options.pin_cpu)
        self.rt_info = (claim.realtime, claim.cpu, claim.warning)
        self.sender.start()
        # numpy's percentile costs ~10 ms on its first call (lazy imports): pay it before the first tick.
        np.percentile(np.zeros(8), 99)
        gc.freeze()  # everything allocated so far is long-lived: keep it out of every later collection
        self.sender.put(ControllerStarted(os.getpid(), *self.rt_info))

    def _pace(self) -> int:
        """Tick on absolute deadlines until told to stop or orphaned; returns the exit code."""
        loop, rig, sender, stats, commands = self.loop, self.rig, self.sender, self.stats, self.commands
        ticks, frames = self.rings
        period_s = self.config.period_s
        spin_s = self.options.rt_spin_s if self.rt_info[0] else self.options.spin_s
        min_sleep_s = self.options.min_sleep_s
        health_interval_s = self.options.health_interval_s
        tick_row = loop.tick
        t0 = time.monotonic()
        k = 0
        missed = 0
        next_health = t0 + health_interval_s
        while True:
            deadline = t0 + k * period_s
            now = wait_until(deadline, spin_s, min_sleep_s)
            late = now - deadline
            if late >= period_s:
                # A stall: skip the periods it swallowed instead of running them back to back, and move
                # the deadline grid on. The loop clamps its integration step (max_step_s) by itself.
                skipped = int(late / period_s)
                missed += skipped
                k += skipped
            pending = commands.take()
            if any(isinstance(command, Shutdown) for command in pending):
                return EXIT_OK  # run() holds the slave; commands queued with the shutdown are moot
            result = run_tick(loop, rig, now, pending)

            tick_row["late_s"] = late
            tick_row["missed_ticks"] = missed
            ticks.write(tick_row)
            if result.new_frame:
                frames.write(loop.frame)
            for event in result.events:
                sender.put(event)
            stats.add(now, late, missed)
            if now >= next_health:
                sender.put(stats.report(now, *self.rt_info))
                next_health = now + health_interval_s
            if os.getppid() != self.parent_pid:
                sender.put(ControllerFailed("the console process died; the slave was held and the controller "
                                            "stopped"))
                return EXIT_ORPHANED
            k += 1


def wait_until(deadline: float, spin_s: float, min_sleep_s: float) -> float:
    """Sleep until ``spin_s`` before ``deadline`` (monotonic clock), then spin; returns when it returned.

    It sleeps at least ``min_sleep_s``, less when under twice that is left, so that the wake-up still
    comes before the deadline (see :class:`PacingOptions`).
    """
    remaining = deadline - time.monotonic()
    pause = max(remaining - spin_s, min(min_sleep_s, remaining - min_sleep_s))
    if pause > 0:
        time.sleep(pause)
    now = time.monotonic()
    while now < deadline:
        now = time.monotonic()
    return now


@dataclass(frozen=True)
class PacingFloor:
    """Empty ticks paced like the controller's: when each started and how late (monotonic clock, s)."""

    started_s: np.ndarray
    late_s: np.ndarray
    rt_priority: bool
    cpu: int | None
    pid: int


def pacing_floor(options: PacingOptions, period_s: float, seconds: float) -> PacingFloor:
    """Pace empty ticks exactly as the controller paces its own, with the same priority and CPU. No tick
    does any work, so their lateness is what this machine's scheduler and hypervisor add: the best the
    loop can do here. Meant for a process of its own (it changes the calling thread's scheduling)."""
    claim = claim_realtime(options.realtime, options.rt_priority, options.pin_cpu)
    rt, cpu = claim.realtime, claim.cpu
    spin_s = options.rt_spin_s if rt else options.spin_s
    n = max(1, round(seconds / period_s))
    started, late = np.empty(n), np.empty(n)
    t0 = time.monotonic()
    k = 0
    for i in range(n):
        deadline = t0 + k * period_s
        started[i] = wait_until(deadline, spin_s, options.min_sleep_s)
        late[i] = started[i] - deadline
        k += 1 + int(late[i] / period_s)  # the controller's stall policy: skip, do not replay
    return PacingFloor(started, late, rt, cpu, os.getpid())


def _raise_terminated(signum, frame):
    raise _Terminated()


def _hold_and_close(rig) -> str:
    problems = []
    try:
        rig.slave.hold(time.monotonic())
    except BaseException as err:  # noqa: BLE001 - still close the rig, then report
        problems.append(f"could not hold the slave: {_describe(err)}")
    try:
        rig.close()
    except BaseException as err:  # noqa: BLE001
        problems.append(f"could not close the rig: {_describe(err)}")
    return "; ".join(problems)


def _describe(err: BaseException) -> str:
    text = str(err)
    return f"{type(err).__name__}: {text}" if text else type(err).__name__
