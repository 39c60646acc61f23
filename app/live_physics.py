"""The live maps' physics (:mod:`session.live`): homogeneous tissue rebuilt from the areas palpated so far, as
the reviewer's analysis rebuilds it from the whole session (:meth:`session.physics.BlockResponse.from_levels`).

Its finite elements take 14-20 s a time on this project's 2-core machine, longer than an area takes to
palpate, and mostly in Python, which would hold the GUI's interpreter: they run in a worker process, at a
lower priority than the console and off the 1 kHz loop's CPU. One runs at a time; the areas palpated
meanwhile wait for the next, which takes every level recorded by then. Each area's block is new (its
surface grows with the areas measured), so nothing of it is kept in the tissue cache: the reviewer solves
the final one.

Even so, on this project's 2-core machine (a virtual one) the solves stall the loop on its own CPU: over
100 s of the autopilot on the flat phantom, 175-288 ticks missed and stalls of 17-24 ms, against 2-7 and
2.4 ms without them, and 15 and 4.9 ms beside an unrelated process as busy with the CPU but not with memory.
The console therefore holds the worker (:meth:`LivePhysics.hold`) while the loop controls force: 61 ticks
missed and 7 ms, and the findings come between areas or after the last one. Between areas, with the TSI in
the air, a solve still cost the loop stalls of 25-36 ms; most of that was the kernel's work on the huge pages
numpy asks for, which the console no longer asks for (``app/process.py``): over 140 s, 22-27 ticks missed
and stalls of 12-15 ms.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import tempfile

import numpy as np
from PySide6 import QtCore

from app.realtime import loop_cpu
from session.analysis import expected_patterns
from session.info import SessionInfo
from session.physics import BlockResponse

Extent = tuple[float, float, float, float]  # (x0, x1, y0, y1) in m
POLL_MS = 100  # how often the console looks for the answer: a tenth of a second on 14-20 s is nothing
NICENESS = 10  # below the console: the operator's display never waits for the tissue model


def patterns_of(levels: np.ndarray, info: SessionInfo, extent_m: Extent | None = None) -> tuple[dict, str]:
    """({map: its pattern on every record of ``levels``} as the reviewer's analysis takes them, how the tissue
    was obtained) for the tissue that reaches over ``extent_m`` and the palpated areas, and ends there; without
    ``extent_m``, over the areas palpated so far, where it ends not known. Raises ValueError where the areas
    cannot be modelled."""
    with tempfile.TemporaryDirectory(prefix="palpation-live-") as cache:
        tissue = BlockResponse.from_levels(levels, info, cache, extent_m=extent_m,
                                           ends_known=extent_m is not None)
        return expected_patterns(tissue, levels), tissue.description


def _serve(connection, info: SessionInfo, extent_m: Extent | None) -> None:
    """The worker: the physics of every levels array received, until the console's end of the pipe closes."""
    if hasattr(os, "nice"):
        os.nice(NICENESS)
    busy = loop_cpu()
    if busy is not None:
        os.sched_setaffinity(0, os.sched_getaffinity(0) - {busy})
    while True:
        try:
            levels = connection.recv()
        except (EOFError, OSError):
            return
        try:
            answer = ("ok", patterns_of(levels, info, extent_m))
        except (ValueError, MemoryError, OSError, np.linalg.LinAlgError) as err:
            answer = ("error", str(err) or type(err).__name__)
        connection.send(answer)


class LivePhysics(QtCore.QObject):
    """:meth:`request` the physics of the levels recorded so far; ``ready(records, patterns, description)``
    answers for the first ``records`` of them (``session.live.LiveMaps.set_physics``), ``failed(reason)`` says
    why it cannot be had. One worker process serves every request of the session (it keeps its memory for the
    next one); :meth:`close` stops it, a computation under way or not (the console closing). ``extent_m``:
    where the tissue is known to reach (the autopilot's plan), else it is taken to end where the areas do."""

    ready = QtCore.Signal(int, object, str)
    failed = QtCore.Signal(str)

    def __init__(self, info: SessionInfo, parent: QtCore.QObject | None = None, extent_m: Extent | None = None):
        super().__init__(parent)
        self._info = info
        self._extent_m = extent_m
        self._context = multiprocessing.get_context("spawn")  # a fork of the GUI would copy Qt's threads' state
        self._worker: tuple[multiprocessing.Process, object] | None = None  # process, the console's end of the pipe
        self._records = 0  # of the request under way; 0: none
        self._wanted: np.ndarray | None = None  # levels asked for while a request was under way, or held
        self._held = False
        self._timer = QtCore.QTimer(self)
        self._timer.setInterval(POLL_MS)
        self._timer.timeout.connect(self._poll)

    @property
    def busy(self) -> bool:
        return self._records > 0

    @property
    def ends_known(self) -> bool:
        """Whether the tissue is known to end where the plan says (else it may go on beyond the areas)."""
        return self._extent_m is not None

    def hold(self, held: bool) -> None:
        """Stop the worker where it is (``held``) or let it go on: the console holds it while the loop controls
        force, for its solves stalled the loop's ticks (module docstring). Nothing is sent to a held worker
        nor read from it: the console would wait on a pipe that only a running worker empties or fills, and
        only the console can let it run again."""
        if held == self._held or not hasattr(signal, "SIGSTOP"):
            return
        self._held = held
        if self._worker is not None:
            try:
                os.kill(self._worker[0].pid, signal.SIGSTOP if held else signal.SIGCONT)
            except ProcessLookupError:
                pass  # it ended: the next poll or request says so
        if not held and not self.busy and self._wanted is not None:
            levels, self._wanted = self._wanted, None
            self._send(levels)

    def request(self, levels: np.ndarray) -> None:
        if not len(levels):
            return
        if self.busy or self._held:
            self._wanted = levels
            return
        self._send(levels)

    def close(self) -> None:
        self._timer.stop()
        self._wanted = None
        self._records = 0
        if self._worker is not None:
            process, pipe = self._worker
            self._worker = None
            process.kill()
            process.join()
            pipe.close()

    def _send(self, levels: np.ndarray) -> None:
        if self._worker is None:
            pipe, theirs = self._context.Pipe()
            process = self._context.Process(target=_serve, args=(theirs, self._info, self._extent_m),
                                            name="live-physics")
            process.start()
            theirs.close()  # the worker holds the only other end: its death reads as the end of the pipe
            self._worker = (process, pipe)
        try:
            self._worker[1].send(levels)
        except OSError as err:  # it ended since its last answer (killed for memory, say)
            self.close()
            self.failed.emit(f"its process could not be reached ({err})")
            return
        self._records = len(levels)
        self._timer.start()

    def _poll(self) -> None:
        if self._held:
            return
        process, pipe = self._worker
        try:
            if not pipe.poll():
                return
            status, payload = pipe.recv()
        except (EOFError, OSError):
            status, payload = "error", f"its process ended without an answer (exit code {process.exitcode})"
        records, self._records = self._records, 0
        self._timer.stop()
        if status == "ok":
            self.ready.emit(records, *payload)
            if self._wanted is not None and not self._held:
                levels, self._wanted = self._wanted, None
                self._send(levels)
        else:
            self.close()
            self.failed.emit(payload)
