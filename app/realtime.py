"""Asking the operating system for real-time service: SCHED_FIFO and a CPU of one's own, where permitted.

The console's controller process and the UDP slave both run a 1 kHz loop and both ask for it the same way;
a refusal is never fatal, it is said in one sentence for the operator.
"""

from __future__ import annotations

import ctypes
import os
import sys
import time
from dataclasses import dataclass


def read_clocks() -> tuple[float, int]:
    """The controller's loop clock (s) and UTC (ns since the epoch), read together: the loop runs on
    ``time.monotonic()``, one clock for every process of the machine (app/controller.py)."""
    return time.monotonic(), time.time_ns()


def loop_cpu() -> int | None:
    """The CPU the loop pins itself to when it may (the last one this process may use), or None (one CPU, or
    no pinning on this OS): other heavy work keeps off it."""
    if not hasattr(os, "sched_getaffinity"):
        return None
    cpus = sorted(os.sched_getaffinity(0))
    return cpus[-1] if len(cpus) >= 2 else None


@dataclass
class RealtimeClaim:
    """What was granted, why not the rest (``warning``, '' when all was), and how to give it back."""

    realtime: bool
    cpu: int | None
    warning: str
    _saved_scheduler: tuple | None = None
    _saved_affinity: set[int] | None = None

    def release(self) -> None:
        """Restore the scheduling and CPUs the calling thread had (for a loop that runs in a thread or a
        process that lives on after it; a controller process that ends with its loop need not)."""
        if self._saved_scheduler is not None:
            os.sched_setscheduler(0, *self._saved_scheduler)
            self._saved_scheduler = None
        if self._saved_affinity is not None:
            os.sched_setaffinity(0, self._saved_affinity)
            self._saved_affinity = None


def claim_realtime(realtime: bool = True, priority: int = 50, pin_cpu: bool = False) -> RealtimeClaim:
    """SCHED_FIFO at ``priority`` for the calling thread and, with ``pin_cpu``, the CPU of :func:`loop_cpu`."""
    warnings = []
    cpu = saved_affinity = saved_scheduler = None
    if pin_cpu:
        mine = loop_cpu()
        if not hasattr(os, "sched_setaffinity"):
            warnings.append("CPU pinning is not available on this OS")
        elif mine is None:
            warnings.append("only one CPU is available, so the loop shares it with the GUI")
        else:
            try:
                before = os.sched_getaffinity(0)
                os.sched_setaffinity(0, {mine})
                cpu, saved_affinity = mine, before
            except OSError as err:
                warnings.append(f"could not pin the loop to CPU {mine} ({err.strerror})")
    if realtime:
        if not hasattr(os, "sched_setscheduler"):
            warnings.append("real-time priority (SCHED_FIFO) is not available on this OS; expect late ticks")
        else:
            try:
                before = (os.sched_getscheduler(0), os.sched_getparam(0))
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
                saved_scheduler = before
            except OSError as err:
                warnings.append(
                    f"real-time priority (SCHED_FIFO) was refused ({err.strerror}); expect late ticks. Grant "
                    "CAP_SYS_NICE or an rtprio limit (/etc/security/limits.conf) to the user running the console")
    if saved_scheduler is None and sys.platform.startswith("linux"):
        _set_timer_slack_ns(1)
    return RealtimeClaim(saved_scheduler is not None, cpu, "; ".join(warnings), saved_scheduler, saved_affinity)


def _set_timer_slack_ns(ns: int) -> None:
    # Normal threads get 50 us of timer slack on every sleep; 1 ns brings the wake-up median from ~110 to
    # ~65 us late here. RT threads have no slack anyway. Failure only costs precision, so it is not fatal.
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(29, ctypes.c_ulong(ns), 0, 0, 0)  # PR_SET_TIMERSLACK
    except (OSError, AttributeError):
        pass
