"""Why late ticks were late: the kernel's own record of the loop's CPU, read with ftrace.

A tick row says *that* a tick started late, not why. While the loop bench runs, :class:`CpuTrace` records
the loop's CPU in a private ftrace instance (context switches, the scheduler's runtime accounting,
interrupts, timers, workqueue items), and :func:`attribute` splits every late tick's delay into:

``steal``
    the loop was on its CPU but the CPU did not run: the scheduler accounts a task's runtime without the
    time the hypervisor gave the virtual CPU to something else (paravirt steal clock), so wall time on
    the CPU minus accounted runtime is time stolen by the host;
``idle_wakeup``
    the loop slept, its wake-up timer fired late, and nothing ran on the CPU in between: a halted virtual
    CPU the hypervisor resumed late, or on bare metal a deep idle state;
``kernel``
    other work of this machine ran on the loop's CPU: kernel threads (named with their workqueue
    function), interrupts (a host stall inside an interrupt on an idle CPU counts here too), or another
    task;
``unexplained``
    the loop was on its CPU and nothing the guest records explains the delay: the loop's own work, or a
    host stall the steal clock did not count. Empty ticks paced the same way (the bench's floor) show
    these too, 1-3 ms long, so on this VM they are mostly the latter;
``untraced``
    a switch away from a task other than the idle task is missing from the trace near the tick (an event
    shows a task running that no recorded switch put there), so who had the CPU is unknown. Seen on this
    VM for a task outside the guest's usual scheduling path, which a SCHED_FIFO loop does not yield to.

A late tick is given the cause that explains most of its delay. Needs root and tracefs; :func:`open_trace`
says why not when either is missing, and the bench reports the run without an attribution.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

CAUSES = ("steal", "idle_wakeup", "kernel", "unexplained", "untraced")
EVENTS = ("sched/sched_switch", "sched/sched_stat_runtime", "irq/irq_handler_entry", "irq/irq_handler_exit",
          "irq/softirq_entry", "irq/softirq_exit", "irq_vectors", "timer/hrtimer_start",
          "timer/hrtimer_expire_entry", "workqueue/workqueue_execute_start")
TRACEFS = Path("/sys/kernel/tracing")
BUFFER_KB_PER_CPU = 32768  # ~400k events: a 30 s run on the loop's CPU needs about a third of it

_LINE = re.compile(r"^\s*(?P<comm>.*?)-(?P<pid>\d+)\s+\[(?P<cpu>\d+)\]\s+\S+\s+(?P<ts>\d+\.\d+):\s+"
                   r"(?P<event>\w+):\s?(?P<fields>.*)$")
_FIELD = re.compile(r"(\w+)=(\S+)")


class TraceUnavailable(RuntimeError):
    """Tracing cannot run here; the message says why."""


class CpuTrace:
    """A private ftrace instance recording one CPU, with the monotonic clock of ``time.monotonic``."""

    def __init__(self, root: Path, cpu: int, mounted_here: bool):
        self.root, self.cpu, self._mounted_here = root, cpu, mounted_here
        self.dir = root / "instances" / f"palpation-{os.getpid()}"

    def start(self) -> CpuTrace:
        self.dir.mkdir()
        try:
            self._write("tracing_on", "0")
            self._write("trace_clock", "mono")
            self._write("buffer_size_kb", str(BUFFER_KB_PER_CPU))
            self._write("tracing_cpumask", f"{1 << self.cpu:x}")
            for event in EVENTS:
                self._write(f"events/{event}/enable", "1")
            self._write("tracing_on", "1")
        except BaseException:
            self.close()
            raise
        return self

    def stop(self) -> tuple[str, int]:
        """Stop recording; returns the trace text and the number of events the buffer dropped."""
        self._write("tracing_on", "0")
        text = (self.dir / "trace").read_text(errors="replace")
        stats = (self.dir / "per_cpu" / f"cpu{self.cpu}" / "stats").read_text()
        lost = int(re.search(r"^overrun:\s*(\d+)", stats, re.M).group(1))
        return text, lost

    def close(self) -> None:
        if self.dir.exists():
            self._write("tracing_on", "0")
            self.dir.rmdir()  # the kernel frees the instance's buffers
        if self._mounted_here:
            subprocess.run(["umount", str(self.root)], check=False, capture_output=True)
            self._mounted_here = False

    def _write(self, name: str, value: str) -> None:
        (self.dir / name).write_text(value)


def open_trace(cpu: int | None) -> CpuTrace:
    """A trace of ``cpu`` (not started yet), or :class:`TraceUnavailable` with the reason."""
    if cpu is None:
        raise TraceUnavailable("the loop has no CPU of its own to trace")
    if os.geteuid() != 0:
        raise TraceUnavailable("tracing the loop's CPU needs root (ftrace)")
    mounted_here = False
    if not (TRACEFS / "instances").is_dir():
        done = subprocess.run(["mount", "-t", "tracefs", "nodev", str(TRACEFS)], capture_output=True, text=True)
        if done.returncode != 0 or not (TRACEFS / "instances").is_dir():
            raise TraceUnavailable(f"tracefs is not available: {done.stderr.strip() or 'no instances directory'}")
        mounted_here = True
    missing = [e for e in EVENTS if not (TRACEFS / "events" / e).exists()]
    if missing:
        if mounted_here:
            subprocess.run(["umount", str(TRACEFS)], check=False, capture_output=True)
        raise TraceUnavailable(f"this kernel lacks the trace events {', '.join(missing)}")
    return CpuTrace(TRACEFS, cpu, mounted_here)


class Recording:
    """One run's trace of the loop's CPU, or the reason there is none. Use it in a ``with`` block, so the
    trace instance is removed however the run ends."""

    def __init__(self):
        self._trace: CpuTrace | None = None
        self._why_not = "the trace was not started"
        self._since = math.inf
        self._text: str | None = None
        self._lost = 0

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc) -> None:
        if self._trace is not None:
            self._trace.close()

    def start(self, cpu: int | None) -> None:
        """Start recording ``cpu``; when that is not possible, remember why."""
        try:
            self._trace = open_trace(cpu).start()
        except (TraceUnavailable, OSError) as err:
            self._why_not = str(err)
            return
        self._since = time.monotonic()

    def stop(self) -> None:
        if self._trace is not None and self._text is None:
            self._text, self._lost = self._trace.stop()

    def attribute(self, ticks: np.ndarray, loop_pid: int, period_s: float) -> tuple[dict, list[LateTick]]:
        """The flat bench keys (causes' shares None without a usable trace) and the late ticks."""
        keys = {f"late_cause_{cause}_pct": None for cause in CAUSES}
        if self._text is None:
            return {**keys, "late_attribution": f"none: {self._why_not}"}, []
        if self._since > ticks["t_s"][0]:
            return {**keys, "late_attribution": "none: the trace started after the first tick analysed"}, []
        if self._lost:
            return {**keys, "late_attribution": f"none: the trace buffer dropped {self._lost} events"}, []
        timeline = parse(self._text, loop_pid)
        late_ticks = attribute(ticks, timeline, period_s)
        return {**summary(late_ticks, len(ticks)), "late_attribution": f"ftrace, {timeline.events} events"}, late_ticks


@dataclass
class CpuTimeline:
    """What the traced CPU did, as intervals (start_s, end_s) on the monotonic clock."""

    # the loop on its CPU: start, end, time stolen by the host, interrupt time net of the steal inside it
    loop_segments: list[tuple[float, float, float, float]] = field(default_factory=list)
    other_segments: list[tuple[float, float, str]] = field(default_factory=list)  # start, end, name
    irqs: list[tuple[float, float, str]] = field(default_factory=list)  # while the CPU idled
    wakeups: list[tuple[float, float]] = field(default_factory=list)  # loop timer fired at, late by (idle CPU)
    unseen_switches: list[tuple[float, float]] = field(default_factory=list)  # between these two events
    events: int = 0


def parse(text: str, loop_pid: int) -> CpuTimeline:
    """Build the CPU's timeline from ftrace's text output (one CPU, ``mono`` clock)."""
    timeline = CpuTimeline()
    current_pid, current_name, since, last_ts = None, "", None, None
    runtime_s = irq_s = 0.0
    work: list[str] = []
    irq_stack: list[tuple[float, str]] = []
    loop_timers: dict[str, float] = {}
    for line in text.splitlines():
        match = _LINE.match(line)
        if match is None:
            continue
        timeline.events += 1
        ts, event, raw = float(match["ts"]), match["event"], match["fields"]
        fields = dict(_FIELD.findall(raw))
        pid = int(match["pid"])
        if current_pid is None:
            current_pid, current_name, since = pid, match["comm"].strip(), ts
        elif pid != current_pid:
            # This kernel never records a switch away from the idle task: the CPU left idle right after the
            # idle task's last event (the interrupt that woke someone). Any other missing switch is a gap.
            if current_pid != 0:
                timeline.unseen_switches.append((last_ts, ts))
            _close_segment(timeline, current_pid, current_name, since, last_ts, runtime_s, irq_s, work, loop_pid)
            current_pid, current_name, since, runtime_s, irq_s, work = pid, match["comm"].strip(), last_ts, 0.0, 0.0, []
        last_ts = ts
        if event == "sched_switch":
            _close_segment(timeline, current_pid, current_name, since, ts, runtime_s, irq_s, work, loop_pid)
            current_pid, since, runtime_s, irq_s, work = int(fields["next_pid"]), ts, 0.0, 0.0, []
            current_name = fields["next_comm"]
        elif event == "sched_stat_runtime" and int(fields["pid"]) == loop_pid:
            runtime_s += int(fields["runtime"]) * 1e-9
        elif event == "workqueue_execute_start":
            work.append(raw.rsplit("function ", 1)[-1])
        elif event.endswith("_entry") and event != "hrtimer_expire_entry":
            irq_stack.append((ts, fields.get("name") or fields.get("action", "").strip("[]") or event[:-6]))
        elif event.endswith("_exit") and irq_stack:
            start, name = irq_stack.pop()
            if irq_stack:
                pass  # nested: the outer interrupt's interval covers it
            elif current_pid == 0:
                timeline.irqs.append((start, ts, name))
            elif current_pid == loop_pid:
                irq_s += ts - start
        elif event == "hrtimer_start" and current_pid == loop_pid and fields.get("function") == "hrtimer_wakeup":
            loop_timers[fields["hrtimer"]] = int(fields["expires"]) * 1e-9
        elif event == "hrtimer_expire_entry" and fields.get("hrtimer") in loop_timers:
            expires = loop_timers.pop(fields["hrtimer"])
            if current_pid == 0:
                timeline.wakeups.append((ts, max(0.0, ts - expires)))
    return timeline


def _close_segment(timeline: CpuTimeline, pid: int, name: str, start: float, end: float, runtime_s: float,
                   irq_s: float, work: list[str], loop_pid: int) -> None:
    if pid == loop_pid:
        # Interrupt time is charged to the loop's runtime, and any steal during an interrupt lengthens the
        # interrupt: count the steal once, and as interrupt work only what the steal does not explain.
        steal_s = max(0.0, (end - start) - runtime_s)
        timeline.loop_segments.append((start, end, steal_s, max(0.0, irq_s - steal_s)))
    elif pid != 0:
        label = f"{name} ({', '.join(sorted(set(work)))})" if work else name
        timeline.other_segments.append((start, end, label))


def _overlap(a0: float, a1: float, b0: float, b1: float) -> float:
    return max(0.0, min(a1, b1) - max(a0, b0))


@dataclass(frozen=True)
class LateTick:
    t_s: float
    late_s: float
    cause: str
    shares_s: dict[str, float]
    detail: str


def attribute(ticks: np.ndarray, timeline: CpuTimeline, period_s: float, threshold_s: float = 0.5e-3
              ) -> list[LateTick]:
    """The cause of every tick more than ``threshold_s`` late.

    A tick's delay is looked for between the start of the tick before it (a stall inside that tick's
    work delays this one) and its own start. The trace tells how much steal and interrupt time a stretch
    of the loop on its CPU had, not when inside it: a stretch reaching outside that window counts with
    the fraction it overlaps.
    """
    starts = ticks["t_s"]
    late = ticks["late_s"]
    result = []
    for i in np.nonzero(late > threshold_s)[0]:
        if i == 0:
            continue
        t1 = float(starts[i])
        t0 = min(float(starts[i - 1]), t1 - float(late[i]) - period_s)
        if any(e > t0 and s < t1 for s, e in timeline.unseen_switches):
            result.append(LateTick(t1, float(late[i]), "untraced", dict.fromkeys(CAUSES[:-1], 0.0), ""))
            continue
        kernel: dict[str, float] = defaultdict(float)
        for s, e, name in timeline.other_segments:
            if e > t0 and s < t1:
                kernel[name] += _overlap(s, e, t0, t1)
        for s, e, name in timeline.irqs:
            if e > t0 and s < t1:
                kernel[f"irq {name}"] += _overlap(s, e, t0, t1)
        steal = 0.0
        for s, e, seg_steal, seg_irq in timeline.loop_segments:
            if e > t0 and s < t1:
                # a segment's steal and interrupt time are not located inside it: prorate by overlap
                share = _overlap(s, e, t0, t1) / (e - s) if e > s else 1.0
                steal += seg_steal * share
                if seg_irq:
                    kernel["interrupts during the loop"] += seg_irq * share
        wakeup = sum(delay for ts, delay in timeline.wakeups if t0 < ts <= t1)
        kernel_s = sum(kernel.values())
        shares = {"steal": steal, "idle_wakeup": wakeup, "kernel": kernel_s,
                  "unexplained": max(0.0, float(late[i]) - steal - wakeup - kernel_s)}
        cause = max(shares, key=shares.__getitem__)
        detail = ""
        if cause == "kernel":
            top = max(kernel, key=kernel.__getitem__)
            detail = f"{top}: {kernel[top] * 1e3:.2f} ms"
        result.append(LateTick(t1, float(late[i]), cause, shares, detail))
    return result


def summary(late_ticks: list[LateTick], n_ticks: int) -> dict:
    """Flat bench keys: the share of all ticks that were late > threshold, per cause."""
    counts = {cause: 0 for cause in CAUSES}
    for tick in late_ticks:
        counts[tick.cause] += 1
    return {f"late_cause_{cause}_pct": 100.0 * counts[cause] / max(1, n_ticks) for cause in CAUSES}


def report(late_ticks: list[LateTick]) -> str:
    lines = [f"{'late ms':>8} {'cause':<12} {'steal':>7} {'wakeup':>7} {'kernel':>7} {'unexpl.':>7}  detail"]
    for tick in late_ticks:
        s = tick.shares_s
        lines.append(f"{tick.late_s * 1e3:8.2f} {tick.cause:<12} {s['steal'] * 1e3:7.2f} "
                     f"{s['idle_wakeup'] * 1e3:7.2f} {s['kernel'] * 1e3:7.2f} {s['unexplained'] * 1e3:7.2f}  "
                     f"{tick.detail}")
    return "\n".join(lines)
