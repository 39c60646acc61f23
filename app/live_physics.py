"""The live maps' physics (:mod:`session.live`): homogeneous tissue rebuilt from the areas palpated so far, as
the reviewer's analysis rebuilds it from the whole session (:meth:`session.physics.BlockResponse.from_levels`).

Its finite elements take 14-20 s a time on this project's 2-core machine (on the paper's flat phantom, 72 mm:
a third meshing and condensing the block onto its surface, a third its finite-strain factor, the rest the face's
contact on each record), longer than an area takes to palpate, and mostly in Python, which would hold the GUI's
interpreter: they run in worker processes, at a lower priority than the console and off the 1 kHz loop's CPU.

Where the tissue's extent is known (the autopilot's plan) the block is the same after every area but for the
surface the onsets measured, which hardly changes the tissue's response. So each area is answered in seconds
by a *quick* worker: the contact on the surface measured so far, on the finite elements of the last block
solved in full (:meth:`session.physics.BlockResponse.on_surface_of`). A *full* worker, at a lower priority
still, solves the latest block in full behind it: its finite elements serve the next areas, and its answer
replaces the quick one when no area came since. On the flat phantom (a recorded session, areas 4-9 each
answered on the previous area's block, against the full solve of the same areas): the same tumours, within
0.2 mm of where the full solve put them; scores within 8 %; most contrasts within 0.01, but the shallow
tumour's largest (the maximum over its records) by up to 0.4 (+1.18 against +1.58 after the 9th area); each
element's expected share within 1.3 %, the 9th area's within 7 %.
Without a plan the block grows with every area and each answer is a full solve. Finite elements are shared
between the workers through a temporary tissue cache, deleted with them: each area's block is new, so
nothing of it belongs in the tissue cache the reviewer keeps.

Even so, on this project's 2-core machine (a virtual one) the solves stall the loop on its own CPU: over
100 s of the autopilot on the flat phantom, 175-288 ticks missed and stalls of 17-24 ms, against 2-7 and
2.4 ms without them, and 15 and 4.9 ms beside an unrelated process as busy with the CPU but not with memory.
The console therefore holds the workers (:meth:`LivePhysics.hold`) while the loop controls force: 61 ticks
missed and 7 ms, and the findings come between areas or after the last one. Between areas, with the TSI in
the air, a solve still cost the loop stalls of 25-36 ms; most of that was the kernel's work on the huge pages
numpy asks for, which the console no longer asks for (``app/process.py``): over 140 s, 22-27 ticks missed
and stalls of 12-15 ms.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import shutil
import signal
import tempfile
import time

import numpy as np
from PySide6 import QtCore

from app.realtime import loop_cpu
from session.analysis import expected_patterns
from session.info import SessionInfo
from session.physics import BlockResponse
from tissue.mechanics.progress import stage

Extent = tuple[float, float, float, float]  # (x0, x1, y0, y1) in m
POLL_MS = 100  # how often the console looks for answers: a tenth of a second on seconds is little
# Below the console, so the operator's display never waits for the tissue model, but above other work of the
# computer's: at +10, on this project's machine busy with other sessions' work (a load of 12-14), the worker had
# 11 s of CPU in the 8 minutes of an autopilot run, and no area's findings came
NICENESS = 5
FULL_NICENESS = 15  # below the quick worker: the next area's answer never waits for a full solve
PROGRESS_EVERY_S = 0.2  # the workers' progress, at most this often (the condensation reports each of its boxes)


def patterns_of(levels: np.ndarray, info: SessionInfo, extent_m: Extent | None = None, cache_dir=None,
                base: BlockResponse | None = None, progress=None) -> tuple[dict, str]:
    """({map: its pattern on every record of ``levels``} as the reviewer's analysis takes them, how the tissue
    was obtained) for the tissue that reaches over ``extent_m`` and the palpated areas, and ends
    there; without ``extent_m``, over the areas palpated so far, where it ends not known. With ``base``, a block
    of the same extent solved before, on its finite elements (:meth:`BlockResponse.on_surface_of`). Raises
    ValueError where the areas cannot be modelled."""
    tissue = None
    if base is not None:
        try:
            tissue = base.on_surface_of(levels, extent_m)
        except ValueError:  # the areas went beyond the block known (off the plan): its finite elements anew
            tissue = None
    solved = tissue is None
    if solved:
        with contextlib.ExitStack() as scratch:
            folder = cache_dir or scratch.enter_context(tempfile.TemporaryDirectory(prefix="palpation-live-"))
            tissue = BlockResponse.from_levels(levels, info, folder, stage(progress, 0.0, 0.7), extent_m=extent_m,
                                               ends_known=extent_m is not None)
    return expected_patterns(tissue, levels, stage(progress, 0.7 if solved else 0.0, 1.0)), tissue.description


def _serve(connection, info: SessionInfo, extent_m: Extent | None, cache_dir: str | None, niceness: int) -> None:
    """A worker: the physics of every (levels, base levels) received, until the console's end of the pipe
    closes. With base levels, the answer is on their block's finite elements (found in ``cache_dir``)."""
    if hasattr(os, "nice"):
        os.nice(niceness)
    busy = loop_cpu()
    if busy is not None:
        os.sched_setaffinity(0, os.sched_getaffinity(0) - {busy})
    known: tuple[int, BlockResponse] | None = None  # the newest base: the records it was solved for, its block
    last = [0.0]

    def progress(fraction: float, message: str) -> None:
        now = time.monotonic()
        if now - last[0] >= PROGRESS_EVERY_S:
            last[0] = now
            connection.send(("progress", fraction, message))

    while True:
        try:
            levels, base_levels = connection.recv()
        except (EOFError, OSError):
            return
        try:
            base = None
            if base_levels is not None:
                if known is None or known[0] != len(base_levels):
                    known = len(base_levels), BlockResponse.from_levels(base_levels, info, cache_dir, extent_m=extent_m)
                base = known[1]
            answer = ("ok", *patterns_of(levels, info, extent_m, cache_dir, base, progress))
        except (ValueError, MemoryError, OSError, np.linalg.LinAlgError) as err:
            answer = ("error", str(err) or type(err).__name__)
        connection.send(answer)


class _Worker:
    """One worker process and the console's end of its pipe; what it was asked and not yet answered."""

    def __init__(self, context, name: str, args: tuple):
        pipe, theirs = context.Pipe()
        self.process = context.Process(target=_serve, args=(theirs, *args), name=name)
        self.process.start()
        theirs.close()  # the worker holds the only other end: its death reads as the end of the pipe
        self.pipe = pipe
        self.levels: np.ndarray | None = None  # under way
        self.progress = (0.0, "")

    def kill(self) -> None:
        self.process.kill()
        self.process.join()
        self.pipe.close()

    def signal(self, number: int) -> None:
        try:
            os.kill(self.process.pid, number)
        except ProcessLookupError:
            pass  # it ended: the next poll or request says so

    def answer(self) -> tuple | None:
        """Its answer once it has one (its progress is kept meanwhile), else None."""
        try:
            while self.pipe.poll():
                message = self.pipe.recv()
                if message[0] != "progress":
                    return message
                self.progress = message[1:]
        except (EOFError, OSError):
            return "error", f"its process ended without an answer (exit code {self.process.exitcode})"
        return None


class LivePhysics(QtCore.QObject):
    """:meth:`request` the physics of the levels recorded so far; ``ready(records, patterns, description)``
    answers for the first ``records`` of them (``session.live.LiveMaps.set_physics``), ``failed(reason)`` says
    why it cannot be had, ``progress(records, fraction, what)`` how far the answer for ``records`` has got.
    Worker processes serve every request of the session (module docstring); :meth:`close` stops them, a
    computation under way or not (the console closing). ``extent_m``: where the tissue is known to reach (the
    autopilot's plan), else it is taken to end where the areas do."""

    ready = QtCore.Signal(int, object, str)
    failed = QtCore.Signal(str)
    progress = QtCore.Signal(int, float, str)

    def __init__(self, info: SessionInfo, parent: QtCore.QObject | None = None, extent_m: Extent | None = None):
        super().__init__(parent)
        self._info = info
        self._extent_m = extent_m
        self._context = multiprocessing.get_context("spawn")  # a fork of the GUI would copy Qt's threads' state
        self._quick: _Worker | None = None
        self._full: _Worker | None = None  # only where the extent is known: else every answer is full
        self._cache: str | None = None  # the finite elements the workers share (module docstring)
        self._wanted: np.ndarray | None = None  # levels asked for while an answer was under way, or held
        self._full_wanted: np.ndarray | None = None  # the same, for the full worker
        self._solved: np.ndarray | None = None  # the newest levels whose block's finite elements are in the cache
        self._answered = 0  # records of the newest answer
        self._held = False
        self._timer = QtCore.QTimer(self)
        self._timer.setInterval(POLL_MS)
        self._timer.timeout.connect(self._poll)

    @property
    def busy(self) -> bool:
        """An answer is under way (the full worker's solves behind the answers are not counted)."""
        return self._quick is not None and self._quick.levels is not None

    @property
    def ends_known(self) -> bool:
        """Whether the tissue is known to end where the plan says (else it may go on beyond the areas)."""
        return self._extent_m is not None

    def hold(self, held: bool) -> None:
        """Stop the workers where they are (``held``) or let them go on: the console holds them while the loop
        controls force, for their solves stalled the loop's ticks (module docstring). Nothing is sent to a held
        worker nor read from it: the console would wait on a pipe that only a running worker empties or fills,
        and only the console can let it run again."""
        if held == self._held or not hasattr(signal, "SIGSTOP"):
            return
        self._held = held
        for worker in (self._quick, self._full):
            if worker is not None:
                worker.signal(signal.SIGSTOP if held else signal.SIGCONT)
        if not held:
            if not self.busy and self._wanted is not None:
                levels, self._wanted = self._wanted, None
                self._send(levels)
            self._send_full()

    def request(self, levels: np.ndarray) -> None:
        if not len(levels):
            return
        if self.busy or self._held:
            self._wanted = levels
            return
        self._send(levels)

    def close(self) -> None:
        self._timer.stop()
        self._wanted = self._full_wanted = self._solved = None
        for worker in (self._quick, self._full):
            if worker is not None:
                if self._held:
                    worker.signal(signal.SIGCONT)  # a stopped process is killed all the same; this is tidier
                worker.kill()
        self._quick = self._full = None
        if self._cache is not None:
            shutil.rmtree(self._cache, ignore_errors=True)
            self._cache = None

    def _worker(self, full: bool) -> _Worker:
        if self._cache is None and self._extent_m is not None:
            self._cache = tempfile.mkdtemp(prefix="palpation-live-")
        args = (self._info, self._extent_m, self._cache)
        if full:
            if self._full is None:
                self._full = _Worker(self._context, "live-physics-full", (*args, FULL_NICENESS))
            return self._full
        if self._quick is None:
            self._quick = _Worker(self._context, "live-physics", (*args, NICENESS))
        return self._quick

    def _send(self, levels: np.ndarray) -> None:
        worker = self._worker(full=False)
        try:
            worker.pipe.send((levels, self._solved))
        except OSError as err:  # it ended since its last answer (killed for memory, say)
            self.close()
            self.failed.emit(f"its process could not be reached ({err})")
            return
        worker.levels, worker.progress = levels, (0.0, "")
        self.progress.emit(len(levels), 0.0, "starting")
        self._timer.start()

    def _send_full(self) -> None:
        """Solve the newest levels answered in full, behind the answers, if no full solve is under way."""
        if self._held or self._full_wanted is None or (self._full is not None and self._full.levels is not None):
            return
        levels, self._full_wanted = self._full_wanted, None
        worker = self._worker(full=True)
        try:
            worker.pipe.send((levels, None))
        except OSError:  # the answers go on from the finite elements known
            self._full.kill()
            self._full = None
            return
        worker.levels = levels
        self._timer.start()

    def _poll(self) -> None:
        if self._held:
            return
        if self.busy:
            self._poll_quick()
        if self._full is not None and self._full.levels is not None:
            self._poll_full()
        if not self.busy and (self._full is None or self._full.levels is None):
            self._timer.stop()

    def _poll_quick(self) -> None:
        worker = self._quick
        before = worker.progress
        answer = worker.answer()
        if answer is None:
            if worker.progress != before:
                self.progress.emit(len(worker.levels), *worker.progress)
            return
        levels, worker.levels = worker.levels, None
        status, payload = answer[0], answer[1:]
        if status != "ok":
            self.close()
            self.failed.emit(payload[0])
            return
        self._answered = len(levels)
        if self._extent_m is not None:
            if self._solved is None:  # it solved this block in full itself: its finite elements are cached
                self._solved = levels
            else:
                self._full_wanted = levels
        self.ready.emit(len(levels), *payload)
        if self._wanted is not None:
            levels, self._wanted = self._wanted, None
            self._send(levels)
        self._send_full()

    def _poll_full(self) -> None:
        worker = self._full
        answer = worker.answer()
        if answer is None:
            return
        levels, worker.levels = worker.levels, None
        if answer[0] == "ok":
            self._solved = levels
            if len(levels) == self._answered and not self.busy:  # the newest answer, now in full
                self.ready.emit(len(levels), *answer[1:])
        else:  # the answers go on from the finite elements known
            worker.kill()
            self._full = None
        self._send_full()
