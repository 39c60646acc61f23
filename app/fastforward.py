"""Fast-forward driver: the real tick on a virtual clock, as fast as the CPU allows.

Tick ``k`` runs at exactly ``start_s + k * period`` (no accumulated rounding), with the same
:func:`app.runtime.run_tick` the controller process uses, so tests and batch runs see the loop the robot
sees, minus the scheduler. The rig must be one whose devices follow the ``now_s`` they are polled with
(the simulated rig does); a real device on a virtual clock would look stale to the safety supervisor.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import numpy as np

from app.runtime import make_loop, run_tick
from control.config import ControlConfig
from control.loop import StepResult
from control.messages import Command
from control.telemetry import FRAME_DTYPE, TICK_DTYPE
from hardware.interfaces import Phase
from hardware.rig import Rig


class FastForwardTimeout(TimeoutError):
    """run_until's condition did not come true within its (simulated) time budget."""


class _RowLog:
    """Rows appended one at a time into a preallocated array that grows a block at a time."""

    def __init__(self, dtype: np.dtype, block_rows: int):
        self._block = block_rows
        self._rows = np.empty(block_rows, dtype=dtype)
        self.n = 0

    def append(self, row: np.ndarray) -> None:
        if self.n == len(self._rows):
            grown = np.empty(len(self._rows) + self._block, dtype=self._rows.dtype)
            grown[: self.n] = self._rows
            self._rows = grown
        self._rows[self.n] = row
        self.n += 1

    def view(self) -> np.ndarray:
        return self._rows[: self.n]

    def clear(self) -> None:
        self.n = 0


class FastForward:
    """Owns the rig from construction (opens it) to :meth:`close`; use it as a context manager.

    ``ticks``/``frames`` keep every row since the start or the last :meth:`clear`; ``events`` likewise.
    """

    def __init__(self, config: ControlConfig, rig: Rig, start_s: float = 0.0, block_rows: int = 65536):
        if block_rows < 1:
            raise ValueError(f"block_rows must be >= 1, got {block_rows}")
        self.config = config
        self.rig = rig
        self.loop = make_loop(config, rig)
        self._period_s = config.period_s
        self._start_s = float(start_s)
        self._k = 0
        self._ticks = _RowLog(TICK_DTYPE, block_rows)
        self._frames = _RowLog(FRAME_DTYPE, max(1, block_rows // 8))
        self.events: list = []
        self._commands: deque = deque()  # deque.append/popleft are atomic: send() may come from any thread
        self._closed = False
        self.last_result: StepResult | None = None  # what the newest tick returned
        rig.open()

    # -- clock

    @property
    def now_s(self) -> float:
        """Virtual time of the next tick."""
        return self._start_s + self._k * self._period_s

    @property
    def tick_count(self) -> int:
        """Ticks run since the start (not reset by :meth:`clear`)."""
        return self._k

    # -- commands and data

    def send(self, command: Command) -> None:
        """Queue a command for the next tick (thread-safe)."""
        if not isinstance(command, Command):
            raise TypeError(f"not a control command: {command!r} (see control.messages.Command)")
        self._commands.append(command)

    @property
    def ticks(self) -> np.ndarray:
        """TICK_DTYPE rows kept so far (a view: copy it to keep it past the next run)."""
        return self._ticks.view()

    @property
    def frames(self) -> np.ndarray:
        return self._frames.view()

    def clear(self) -> None:
        """Forget the kept rows and events (the clock, the loop and the rig carry on)."""
        self._ticks.clear()
        self._frames.clear()
        self.events = []

    # -- running

    def step(self, n: int = 1) -> None:
        if self._closed:
            raise RuntimeError("this FastForward is closed")
        loop, rig, commands = self.loop, self.rig, self._commands
        period, start = self._period_s, self._start_s
        tick_row = loop.tick
        for _ in range(n):
            now = start + self._k * period
            pending = [commands.popleft() for _ in range(len(commands))]
            result = self.last_result = run_tick(loop, rig, now, pending)
            tick_row["late_s"] = 0.0  # a virtual clock is never late
            tick_row["missed_ticks"] = 0
            self._ticks.append(tick_row)
            if result.new_frame:
                self._frames.append(loop.frame)
            if result.events:
                self.events.extend(result.events)
            self._k += 1

    def run_for(self, seconds: float) -> int:
        """Run ``seconds`` of virtual time (rounded to whole periods); returns the ticks run."""
        if seconds < 0:
            raise ValueError(f"seconds must be >= 0, got {seconds}")
        n = int(round(seconds / self._period_s))
        self.step(n)
        return n

    def run_until(self, predicate: Callable[[FastForward], bool], timeout_s: float) -> float:
        """Tick until ``predicate(self)`` is true (checked after every tick); returns the virtual time taken.

        Raises :class:`FastForwardTimeout` after ``timeout_s`` of virtual time, so it always returns.
        """
        if predicate(self):
            return 0.0
        limit = int(round(timeout_s / self._period_s))
        for n in range(1, limit + 1):
            self.step(1)
            if predicate(self):
                return n * self._period_s
        name = getattr(predicate, "__name__", repr(predicate))
        tick = self.loop.tick
        raise FastForwardTimeout(
            f"{name} did not come true within {timeout_s:g} s of simulated time "
            f"(now t = {self.now_s:.3f} s, phase {Phase(int(tick['phase'])).name}, "
            f"force {float(tick['force_measured_N']):.2f} N, {len(self.events)} events kept)"
        )

    # -- lifetime

    def close(self) -> None:
        """Hold the slave and close the rig; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        try:
            self.rig.slave.hold(self.now_s)
        finally:
            self.rig.close()

    def __enter__(self) -> FastForward:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
