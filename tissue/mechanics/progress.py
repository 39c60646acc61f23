"""Progress reporting for long precomputations: ``progress(fraction, message)`` callbacks."""

from __future__ import annotations

import shutil
import sys
import time
from typing import Callable, TextIO

Progress = Callable[[float, str], None]


def stage(progress: Progress | None, start: float, end: float) -> Progress | None:
    """A callback mapping a sub-task's own 0..1 onto [start, end] of the parent's progress."""
    if progress is None:
        return None

    def report(fraction: float, message: str) -> None:
        progress(start + (end - start) * min(1.0, max(0.0, fraction)), message)

    return report


class TextProgressBar:
    """A one-line terminal progress bar, redrawn in place at most every ``interval_s``.

    ``TextProgressBar()(0.42, "condensing")`` draws ``[########            ]  42% condensing``.
    """

    def __init__(self, stream: TextIO | None = None, width: int = 30, interval_s: float = 0.1):
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.interval_s = interval_s
        self._last = -1.0
        self._shown = ""

    def __call__(self, fraction: float, message: str) -> None:
        fraction = min(1.0, max(0.0, fraction))
        now = time.monotonic()
        if fraction < 1.0 and now - self._last < self.interval_s:
            return
        self._last = now
        filled = int(round(fraction * self.width))
        line = f"[{'#' * filled}{' ' * (self.width - filled)}] {fraction * 100:3.0f}% {message}"
        # a line longer than the terminal wraps, and the carriage return then redraws only its last part
        line = line[:max(self.width + 6, shutil.get_terminal_size().columns - 1)]
        pad = max(0, len(self._shown) - len(line))
        self.stream.write("\r" + line + " " * pad)
        self._shown = line
        if fraction >= 1.0:  # close the line; whatever comes next starts a fresh one
            self.stream.write("\n")
            self._shown = ""
        self.stream.flush()
