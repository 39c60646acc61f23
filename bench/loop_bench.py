"""How well the controller process keeps its 1 kHz period on this machine.

Runs the controller process on the simulated rig for ``PALPATION_BENCH_SECONDS`` (default 25 s) per
configuration: with a pyqtgraph window redrawing at 60 Hz in this process (offscreen platform) and
without, each with and without SCHED_FIFO (the loop is pinned to a CPU of its own in all four when
permitted). Every tick row is read back from the shared-memory ring, so the statistics cover every tick.

Writes ``loop.json``: a flat object whose unprefixed keys describe the run WITH the GUI and RT priority
requested (the console's normal configuration) and whose ``<config>_`` keys describe all four runs.
Each tick's work is reported in two parts, as the tick row records it: ``compute_*`` is the loop's own
computation (``ControlLoop.step``: law, state machine, frame analysis, safety), ``io_*`` is reading the
devices and applying the result, which on the simulated rig is mostly simulating the world (robot,
tissue, sensor, operator) up to the tick; ``tick_work_*`` is the two together, the time the tick
actually took. Also measures the same split on the fast-forward driver, where no other process and no
idle CPU cools the caches between ticks.

Two figures say what the late ticks are made of. ``late_cause_*_pct`` splits them by cause (host steal,
a late wake-up of an idle CPU, other kernel work on the loop's CPU, or nothing the guest records), read
from an ftrace record of the loop's CPU (:mod:`bench.stall_trace`; needs root, else ``late_attribution``
says why).
``floor_*`` paces empty ticks the same way in a process of their own: the lateness this machine adds
to a loop that does nothing, the floor under ``late_over_0_5ms_pct``.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.controller import ControllerProcess, PacingOptions, pacing_floor
from app.fastforward import FastForward
from app.rigs import RigSpec, build_rig
from bench import stall_trace
from control.config import ControlConfig
from control.telemetry import TICK_DTYPE

NAME = "loop"
WARMUP_S = 0.5  # start-up transients (first frame analysed, caches filled) are not the steady state
DISPLAY_HZ = 60.0


@dataclass(frozen=True)
class Setup:
    key: str
    gui: bool
    realtime: bool


SETUPS = [
    Setup("gui_rt", gui=True, realtime=True),
    Setup("gui_nort", gui=True, realtime=False),
    Setup("nogui_rt", gui=False, realtime=True),
    Setup("nogui_nort", gui=False, realtime=False),
]
PRIMARY = "gui_rt"
REPORTED = ("late_over_0_5ms_pct", "late_over_1ms_pct", "p99_abs_jitter_us", "longest_stall_ms", "compute_p50_us",
            "compute_p99_us", "io_p50_us", "io_p99_us", "tick_work_p50_us", "tick_work_p99_us",
            "late_over_0_5ms_after_overrun_pct", "missed_ticks", "ticks", "lost_rows", "rt_priority",
            "paints_per_s", "load_avg_1min", "steal_pct", "late_total_ms", "loop_cpu_steal_ms",
            *(f"late_cause_{cause}_pct" for cause in stall_trace.CAUSES), "late_attribution")


def duration_s(default_s: float = 25.0, least_s: float = 2 * WARMUP_S) -> float:
    """How long a benchmark runs: ``PALPATION_BENCH_SECONDS``, else ``default_s``; at least ``least_s``."""
    raw = os.environ.get("PALPATION_BENCH_SECONDS", f"{default_s:g}")
    try:
        value = float(raw)
    except ValueError:
        raise ValueError(f"PALPATION_BENCH_SECONDS must be a number of seconds, got {raw!r}") from None
    if value < least_s:
        raise ValueError(f"PALPATION_BENCH_SECONDS must be at least {least_s:g} s, got {value:g}")
    return value


def tick_statistics(ticks: np.ndarray, period_s: float) -> dict:
    """The timing figures of a run, from its tick rows (warm-up already removed)."""
    late = ticks["late_s"]
    compute = ticks["compute_s"]
    io = ticks["io_s"]
    work = compute + io
    intervals = np.diff(ticks["t_s"])
    # A resynchronised stall spans several periods by design; its lateness is counted in longest_stall.
    jitter = np.abs(intervals - period_s)
    # Why a tick started late: its predecessor was still computing past the threshold, or the process
    # woke up late (scheduler, host). Only the second is the pacing's business.
    late_ticks = late[1:] > 0.5e-3
    deadline = ticks["t_s"][1:] - late[1:]
    overran = ticks["t_s"][:-1] + work[:-1] > deadline + 0.5e-3
    return {
        "late_over_0_5ms_after_overrun_pct": float(100.0 * np.count_nonzero(late_ticks & overran) / len(ticks)),
        "ticks": int(len(ticks)),
        "late_over_0_5ms_pct": float(100.0 * np.mean(late > 0.5e-3)),
        "late_over_1ms_pct": float(100.0 * np.mean(late > 1e-3)),
        "p99_abs_jitter_us": float(np.percentile(jitter, 99) * 1e6),
        "longest_stall_ms": float(late.max() * 1e3),
        "compute_p50_us": float(np.percentile(compute, 50) * 1e6),
        "compute_p99_us": float(np.percentile(compute, 99) * 1e6),
        "io_p50_us": float(np.percentile(io, 50) * 1e6),
        "io_p99_us": float(np.percentile(io, 99) * 1e6),
        "tick_work_p50_us": float(np.percentile(work, 50) * 1e6),
        "tick_work_p99_us": float(np.percentile(work, 99) * 1e6),
        "missed_ticks": int(ticks["missed_ticks"][-1] - ticks["missed_ticks"][0]),
        "late_total_ms": float(late[late > 0.5e-3].sum() * 1e3),
    }


def _run_without_gui(process: ControllerProcess, seconds: float, on_started) -> tuple[list[np.ndarray], float]:
    """Drain the ring at display rate, as the bridge would, with nothing else running here."""
    process.start()
    on_started()
    chunks, cursor = [], 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        time.sleep(1.0 / DISPLAY_HZ)
        rows, cursor, _ = process.ticks.read_since(cursor)
        chunks.append(rows)
        process.drain_events()
    process.stop()
    return chunks, 0.0


def _run_with_gui(process: ControllerProcess, seconds: float, on_started) -> tuple[list[np.ndarray], float]:
    """The console's stack: the bridge's worker thread drains the rings, a pyqtgraph window in this
    process is fed and repainted on every snapshot (60 Hz)."""
    import pyqtgraph as pg
    from PySide6.QtCore import QEvent, QEventLoop, QObject, QTimer
    from PySide6.QtWidgets import QApplication

    from app.bridge import ControllerBridge

    app = QApplication.instance() or QApplication([])
    win = pg.GraphicsLayoutWidget(size=(1000, 600))
    force_plot = win.addPlot(title="force")
    force_plot.setXRange(-5.0, 0.0)  # time relative to now on a fixed axis: one paint per frame
    force_plot.setYRange(-1.0, 10.0)
    force_curve = force_plot.plot(pen="y")
    height_curve = force_plot.plot(pen="c")
    image = pg.ImageItem(axisOrder="row-major", levels=(0.0, 100e3))
    win.addViewBox(row=1, col=0).addItem(image)

    class PaintCounter(QObject):
        count = 0

        def eventFilter(self, obj, event):
            if event.type() == QEvent.Type.Paint:
                self.count += 1
            return False

    counter = PaintCounter()
    win.viewport().installEventFilter(counter)
    win.show()

    chunks: list[np.ndarray] = []
    history = np.empty(0, dtype=TICK_DTYPE)

    def redraw(snapshot):
        nonlocal history
        chunks.append(snapshot.ticks)
        history = np.concatenate([history, snapshot.ticks])[-5000:]
        t = history["t_s"] - history["t_s"][-1]
        force_curve.setData(t, history["force_measured_N"])
        height_curve.setData(t, history["x_slave_m"][:, 2] * 100.0)
        if snapshot.frame is not None:
            image.setImage(np.ascontiguousarray(snapshot.frame["pressure_pa"], dtype=np.float32), autoLevels=False)

    bridge = ControllerBridge(lambda: process, display_hz=DISPLAY_HZ)
    bridge.snapshot.connect(redraw)
    problems: list[str] = []
    bridge.start_failed.connect(problems.append)
    bridge.crashed.connect(problems.append)
    waiting = QEventLoop()
    bridge.started.connect(waiting.quit)
    bridge.start_failed.connect(waiting.quit)
    bridge.start()
    waiting.exec()
    if problems:
        bridge.shutdown()
        raise RuntimeError(problems[0])
    on_started()
    started = time.monotonic()
    QTimer.singleShot(round(seconds * 1000.0), waiting.quit)
    waiting.exec()
    elapsed = time.monotonic() - started
    bridge.shutdown()
    app.processEvents()  # the last snapshots queued before the shutdown
    paints = counter.count
    win.viewport().removeEventFilter(counter)
    win.close()
    win.deleteLater()
    app.processEvents()
    if problems:
        raise RuntimeError(problems[0])
    return chunks, paints / elapsed


def _cpu_counters() -> dict[str, tuple[int, int]] | None:
    """(steal, total) jiffies per /proc/stat line ("cpu" for all CPUs, "cpu1", ...), or None without it."""
    try:
        with open("/proc/stat") as stat:
            lines = [line.split() for line in stat if line.startswith("cpu")]
        return {line[0]: (int(line[8]), sum(int(v) for v in line[1:])) for line in lines}
    except (OSError, ValueError, IndexError):
        return None


def run_setup(setup: Setup, config: ControlConfig, seconds: float) -> dict:
    load_1min = os.getloadavg()[0]  # other work on the machine shows up in every non-RT figure
    before = _cpu_counters()
    options = PacingOptions(realtime=setup.realtime, pin_cpu=True)
    process = ControllerProcess(config, RigSpec(), options, tick_capacity=65536)
    with stall_trace.Recording() as recording:
        try:
            drive = _run_with_gui if setup.gui else _run_without_gui
            chunks, paints_per_s = drive(process, seconds, lambda: recording.start(process.started_info.cpu))
            recording.stop()
        finally:
            process.stop()
    if process.exitcode != 0:
        raise RuntimeError(f"{setup.key}: the controller process exited with code {process.exitcode}: "
                           f"{process.failure}")
    after = _cpu_counters()
    # Time the hypervisor ran something else on our virtual CPUs: no priority inside the guest helps.
    # Compare the loop CPU's share with late_total_ms, the time the late ticks lost.
    info = process.started_info
    steal_pct = loop_cpu_steal_ms = None
    if before and after:
        steal_pct = 100.0 * (after["cpu"][0] - before["cpu"][0]) / max(1, after["cpu"][1] - before["cpu"][1])
        line = f"cpu{info.cpu}"
        if info.cpu is not None and line in before and line in after:
            loop_cpu_steal_ms = (after[line][0] - before[line][0]) * 1e3 / os.sysconf("SC_CLK_TCK")
    ticks = np.concatenate(chunks)
    # rows overwritten before the display read them show up as gaps in the tick index
    lost = int(ticks["tick"][-1] - ticks["tick"][0] + 1 - len(ticks))
    ticks = ticks[ticks["t_s"] >= ticks["t_s"][0] + WARMUP_S]
    stats = tick_statistics(ticks, config.period_s)
    stats.update(_attribution(recording, ticks, process.started_info.pid, config.period_s, setup.key))
    stats.update(lost_rows=lost, rt_priority=bool(info.rt_priority), cpu=info.cpu, warning=info.warning,
                 paints_per_s=float(paints_per_s), load_avg_1min=load_1min, steal_pct=steal_pct,
                 loop_cpu_steal_ms=loop_cpu_steal_ms)
    return stats


def _attribution(recording: stall_trace.Recording, ticks: np.ndarray, loop_pid: int, period_s: float,
                 key: str) -> dict:
    keys, late_ticks = recording.attribute(ticks, loop_pid, period_s)
    if late_ticks:
        print(f"loop: {key}: late ticks and their causes (ms)\n{stall_trace.report(late_ticks)}")
    return keys


def floor_run(config: ControlConfig, seconds: float) -> dict:
    """The machine's own floor: empty ticks paced like the loop's (SCHED_FIFO, its CPU), in a process of
    their own, traced like the loop. Late ticks here cannot be the loop's doing."""
    options = PacingOptions()
    with mp.get_context("spawn").Pool(1) as pool, stall_trace.Recording() as recording:
        pending = pool.apply_async(pacing_floor, (options, config.period_s, seconds))
        # the floor's process pins itself to the last CPU, as the controller does
        recording.start(sorted(os.sched_getaffinity(0))[-1] if options.pin_cpu else None)
        floor = pending.get()
        recording.stop()
    ticks = np.zeros(len(floor.late_s), dtype=[("t_s", "f8"), ("late_s", "f8")])
    ticks["t_s"], ticks["late_s"] = floor.started_s, floor.late_s
    ticks = ticks[round(WARMUP_S / config.period_s):]
    late = ticks["late_s"]
    stats = {"late_over_0_5ms_pct": float(100.0 * np.mean(late > 0.5e-3)),
             "late_over_1ms_pct": float(100.0 * np.mean(late > 1e-3)),
             "longest_stall_ms": float(late.max() * 1e3), "rt_priority": bool(floor.rt_priority), "cpu": floor.cpu,
             **_attribution(recording, ticks, floor.pid, config.period_s, "floor")}
    return {f"floor_{key}": value for key, value in stats.items()}


def compute_split(config: ControlConfig, seconds: float = 5.0) -> dict:
    """Simulator (io) vs loop (compute) cost per tick on the virtual clock: ticks back to back, caches warm."""
    with FastForward(config, build_rig(RigSpec())) as ff:
        ff.run_for(seconds)
        ticks = ff.ticks[int(WARMUP_S * config.rate_hz):]
        io, compute = ticks["io_s"], ticks["compute_s"]
    return {
        "sim_poll_p50_us": float(np.percentile(io, 50) * 1e6),
        "loop_step_p50_us": float(np.percentile(compute, 50) * 1e6),
        "loop_step_p99_us": float(np.percentile(compute, 99) * 1e6),
    }


def run(out_dir: Path) -> dict:
    seconds = duration_s()
    config = ControlConfig()
    results = {}
    for setup in SETUPS:
        print(f"loop: {setup.key} for {seconds:g} s ...", flush=True)
        results[setup.key] = run_setup(setup, config, seconds)

    flat: dict = {"duration_s": seconds, "warmup_s": WARMUP_S, "rate_hz": config.rate_hz, "cpus": os.cpu_count()}
    primary = results[PRIMARY]
    flat.update({k: primary[k] for k in REPORTED})
    flat["rt_warning"] = primary["warning"]
    for key, stats in results.items():
        flat.update({f"{key}_{k}": stats[k] for k in REPORTED})
    flat.update(compute_split(config))
    print(f"loop: pacing floor (empty ticks) for {seconds:g} s ...", flush=True)
    floor = floor_run(config, seconds)
    flat.update(floor)

    print(_table(results))
    causes = ", ".join(f"{cause} {floor[f'floor_late_cause_{cause}_pct']:.3f} %" for cause in stall_trace.CAUSES
                       if floor[f"floor_late_cause_{cause}_pct"] is not None)
    print(f"floor (empty ticks paced the same way): late>0.5ms {floor['floor_late_over_0_5ms_pct']:.3f} %, "
          f"late>1ms {floor['floor_late_over_1ms_pct']:.3f} %, longest stall {floor['floor_longest_stall_ms']:.1f} ms, "
          f"RT {floor['floor_rt_priority']}; causes: {causes or floor['floor_late_attribution']}")
    if not primary["rt_priority"]:
        print(f"loop: real-time priority was NOT granted: {primary['warning']}")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{NAME}.json").write_text(json.dumps(flat, indent=2, sort_keys=True) + "\n")
    return flat


def _table(results: dict) -> str:
    columns = [("late>0.5ms%", "late_over_0_5ms_pct", "{:.3f}"), ("late>1ms%", "late_over_1ms_pct", "{:.3f}"),
               ("of:overrun%", "late_over_0_5ms_after_overrun_pct", "{:.3f}"),
               ("p99|jit|us", "p99_abs_jitter_us", "{:.0f}"), ("stall_ms", "longest_stall_ms", "{:.1f}"),
               ("cmp_p50us", "compute_p50_us", "{:.0f}"), ("cmp_p99us", "compute_p99_us", "{:.0f}"),
               ("io_p50us", "io_p50_us", "{:.0f}"), ("work_p50us", "tick_work_p50_us", "{:.0f}"),
               ("work_p99us", "tick_work_p99_us", "{:.0f}"),
               ("missed", "missed_ticks", "{}"), ("RT", "rt_priority", "{}"), ("paints/s", "paints_per_s", "{:.0f}"),
               ("load", "load_avg_1min", "{:.1f}"), ("steal%", "steal_pct", "{:.2f}"),
               ("late_ms", "late_total_ms", "{:.1f}"), ("cpu_steal_ms", "loop_cpu_steal_ms", "{:.0f}"),
               *((f"{cause}%", f"late_cause_{cause}_pct", "{:.3f}") for cause in stall_trace.CAUSES)]

    def cell(fmt: str, value) -> str:
        return "n/a" if value is None else fmt.format(value)

    lines = ["config     " + "".join(f"{title:>12}" for title, _, _ in columns)]
    for key, stats in results.items():
        lines.append(f"{key:<11}" + "".join(f"{cell(fmt, stats[name]):>12}" for _, name, fmt in columns))
    return "\n".join(lines)
