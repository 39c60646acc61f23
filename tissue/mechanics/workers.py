"""The tissue model's independent pieces computed side by side, each in its own worker process.

A new phantom's model has up to three pieces that depend on nothing but the phantom: the tables at rest,
the tables with the inclusions where a compressed layer carries them, and the finite-strain fit. One
after another they took 38.7 s on the uneven phantom on an idle 2-core machine, over the 30 s a first
palpation may wait. They do not overlap within one process: they hold the GIL most of the time (32.6 s
with the fit in a thread), and numpy's BLAS threads gain them little (16.0 s for the tables with one BLAS
thread, 15.1 s with two) while two BLAS pools on two cores spin against each other (78 s with the
second tables in a process that kept its default pool). In two worker processes with one BLAS thread
each they took 21.9 s.

A worker is a fresh interpreter running :func:`serve`, whose BLAS is limited to one thread by its
environment, the one way to set that before numpy loads. It reads one pickled :class:`Job` on stdin and
writes pickled messages on stdout: progress, then the result or the exception.
The pickles only ever pass between this process and the children it started.
"""

from __future__ import annotations

import importlib
import logging
import os
import pickle
import queue
import subprocess
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tissue.mechanics.progress import Progress, stage

log = logging.getLogger(__name__)

_ONE_THREAD = {name: "1" for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
# Where the ``tissue`` package is imported from: the worker is told it explicitly and runs isolated (``-I``:
# no current folder, no PYTHON* variables, no user site on its path), so a folder holding a package of the
# same name as one of ours, where the console happens to be started, is never what a worker imports.
_ROOT = str(Path(__file__).resolve().parents[2])
# what a worker runs (not ``-m`` this module: the package imports it first, and it would run as a second copy
# of itself); a test replaces it to see a worker die
_COMMAND = [sys.executable, "-I", "-c", f"import sys; sys.path.insert(0, {_ROOT!r}); "
            f"from {__name__} import serve; serve()"]


@dataclass(frozen=True)
class Job:
    """``target`` ("module:function") called as ``function(*args, progress=callback)``."""

    name: str  # what it computes, for messages
    target: str
    args: tuple
    weight: float = 1.0  # its share of the whole's progress


class WorkerError(RuntimeError):
    """A worker stopped without a result (killed, out of memory, crashed)."""


def usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _call(job: Job, progress: Progress | None) -> Any:
    module, _, function = job.target.partition(":")
    return getattr(importlib.import_module(module), function)(*job.args, progress=progress)


def run(jobs: list[Job], workers: int, progress: Progress | None = None) -> list[Any]:
    """Every job's result, in order; with ``workers`` > 1 up to that many at a time in worker processes,
    taken in the order given (longest first balances best). A job's exception is raised here as it was
    raised there. If no worker can be started, the jobs run here one after another."""
    if workers <= 1 or len(jobs) <= 1:
        return _run_here(jobs, progress)
    try:
        return _run_in_workers(jobs, workers, progress)
    except OSError as err:  # no interpreter to start (a frozen build, a sandbox)
        log.warning("could not start a worker process (%s); computing the tissue model here", err)
        return _run_here(jobs, progress)


def _run_here(jobs: list[Job], progress: Progress | None) -> list[Any]:
    total = sum(job.weight for job in jobs)
    results, done = [], 0.0
    for job in jobs:
        results.append(_call(job, _named(stage(progress, done, done + job.weight / total), job.name)))
        done += job.weight / total
    return results


def _named(progress: Progress | None, name: str) -> Progress | None:
    """``progress`` with each message saying which piece it is about: several run at once."""
    if progress is None:
        return None
    return lambda fraction, message: progress(fraction, f"{name}: {message}")


class _Worker:
    def __init__(self, index: int, job: Job, messages: queue.Queue):
        self.index = index
        self.stderr = tempfile.TemporaryFile()
        env = dict(os.environ, **_ONE_THREAD)
        try:
            self.process = subprocess.Popen(_COMMAND, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                            stderr=self.stderr, env=env, cwd=_ROOT)
        except BaseException:
            self.stderr.close()
            raise
        try:
            with self.process.stdin as pipe:
                pipe.write(pickle.dumps(job, protocol=pickle.HIGHEST_PROTOCOL))
        except BrokenPipeError:  # it died before reading its job: the reader reports it, with its exit code
            pass
        self._reader = threading.Thread(target=self._read, args=(messages,), daemon=True)
        self._reader.start()

    def _read(self, messages: queue.Queue) -> None:
        try:
            while True:
                messages.put((self.index, pickle.load(self.process.stdout)))
        except Exception:  # the end of the stream, or a worker that died mid-message
            messages.put((self.index, ("gone", None)))

    def stop(self) -> str:
        """End it and say the last line it wrote to stderr (its last words, should it have died)."""
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()
        self._reader.join()
        self.process.stdout.close()
        self.stderr.seek(0)
        lines = self.stderr.read().decode("utf-8", "replace").strip().splitlines()
        self.stderr.close()
        return lines[-1] if lines else "no message"


def _run_in_workers(jobs: list[Job], workers: int, progress: Progress | None) -> list[Any]:
    total = sum(job.weight for job in jobs)
    fractions = [0.0] * len(jobs)
    named = [_named(progress, job.name) for job in jobs]
    results: dict[int, Any] = {}
    messages: queue.Queue = queue.Queue()
    running: dict[int, _Worker] = {}
    waiting = list(range(len(jobs)))
    try:
        while len(results) < len(jobs):
            while waiting and len(running) < workers:
                index = waiting.pop(0)
                running[index] = _Worker(index, jobs[index], messages)
            index, (kind, payload) = messages.get()
            if index not in running:  # the end of the stream of a worker that has given its result
                continue
            if kind == "progress":
                fractions[index] = min(1.0, max(0.0, payload[0]))
                if progress:
                    named[index](sum(f * job.weight for f, job in zip(fractions, jobs)) / total, payload[1])
                continue
            worker = running.pop(index)
            last_words = worker.stop()
            if kind == "error":
                raise payload
            if kind == "gone":
                raise WorkerError(f"the worker computing the {jobs[index].name} stopped with exit code "
                                  f"{worker.process.returncode} before its result: {last_words}")
            results[index] = payload
            fractions[index] = 1.0
    finally:
        for worker in running.values():
            worker.stop()
    return [results[i] for i in range(len(jobs))]


def serve() -> None:
    """A worker's whole life: one job from stdin, its messages to stdout."""
    # stdout carries the messages; anything else the computation prints goes to stderr
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    job = pickle.load(sys.stdin.buffer)

    def send(kind: str, payload: Any) -> None:
        pickle.dump((kind, payload), out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()

    try:
        result = _call(job, lambda fraction, message: send("progress", (fraction, message)))
    except Exception as err:
        try:
            pickle.dumps(err)
        except Exception:
            err = RuntimeError(f"{type(err).__name__}: {err}")
        send("error", err)
        return
    send("result", result)

