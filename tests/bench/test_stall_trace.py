"""The late-tick attribution reads ftrace's text output: fed with traces of known stalls, it must name them."""

import numpy as np

from bench import stall_trace

LOOP = 100


def line(comm: str, pid: int, ts: float, event: str, fields: str) -> str:
    return f"{comm:>16}-{pid:<7} [001] d..2. {ts:.6f}: {event}: {fields}"


def switch(ts: float, prev: tuple[str, int], nxt: tuple[str, int], state: str = "S") -> str:
    return line(prev[0], prev[1], ts, "sched_switch", f"prev_comm={prev[0]} prev_pid={prev[1]} prev_prio=59 "
                f"prev_state={state} ==> next_comm={nxt[0]} next_pid={nxt[1]} next_prio=120")


def runtime(ts: float, ns: int) -> str:
    return line("python", LOOP, ts, "sched_stat_runtime", f"comm=python pid={LOOP} runtime={ns} [ns]")


def ticks(*rows: tuple[float, float]) -> np.ndarray:
    out = np.zeros(len(rows), dtype=[("t_s", "f8"), ("late_s", "f8")])
    out["t_s"], out["late_s"] = zip(*rows)
    return out


def attribute(trace: list[str], tick_rows: np.ndarray) -> list[stall_trace.LateTick]:
    header = "# tracer: nop\n#\n#  TASK-PID  CPU#  TIMESTAMP  FUNCTION\n"
    return stall_trace.attribute(tick_rows, stall_trace.parse(header + "\n".join(trace), LOOP), 1e-3)


PYTHON, WORKER, IDLE = ("python", LOOP), ("kworker/1:2", 7), ("<idle>", 0)


def test_a_kernel_worker_that_takes_the_cpu_is_named():
    trace = [
        runtime(10.0001, 100_000),
        switch(10.0001, PYTHON, WORKER, state="R"),
        line("kworker/1:2", 7, 10.000105, "workqueue_execute_start",
             "work struct 00000000e61ea04c: function gc_worker"),
        switch(10.003, WORKER, PYTHON, state="I"),
    ]
    [late] = attribute(trace, ticks((10.0, 0.0), (10.0030, 2.0e-3)))
    assert late.cause == "kernel"
    assert "gc_worker" in late.detail
    assert abs(late.shares_s["kernel"] - 2.9e-3) < 1e-5


def test_a_wakeup_timer_that_fires_late_on_an_idle_cpu_is_an_idle_wakeup():
    trace = [
        line("python", LOOP, 20.0001, "hrtimer_start", "hrtimer=00000000aa function=hrtimer_wakeup "
             "expires=20000800000 softexpires=20000800000 mode=ABS"),
        runtime(20.0001, 100_000),
        switch(20.0001, PYTHON, ("swapper/1", 0)),
        line("<idle>", 0, 20.0040, "local_timer_entry", "vector=236"),
        line("<idle>", 0, 20.0040, "hrtimer_expire_entry",
             "hrtimer=00000000aa function=hrtimer_wakeup now=20004000000"),
        line("<idle>", 0, 20.0040, "local_timer_exit", "vector=236"),
        # the kernel records no switch away from the idle task: the loop's next event says it runs again
        line("python", LOOP, 20.0045, "hrtimer_start", "hrtimer=00000000bb function=hrtimer_wakeup "
             "expires=20001800000 softexpires=20001800000 mode=ABS"),
    ]
    [late] = attribute(trace, ticks((20.0, 0.0), (20.0041, 3.1e-3)))
    assert late.cause == "idle_wakeup"
    assert abs(late.shares_s["idle_wakeup"] - 3.2e-3) < 1e-5


def test_time_on_the_cpu_the_scheduler_did_not_account_is_steal():
    trace = [
        switch(30.0002, WORKER, PYTHON, state="I"),
        runtime(30.0027, 300_000),  # 0.3 ms of runtime in a 2.5 ms stretch on the CPU
        switch(30.0027, PYTHON, ("swapper/1", 0)),
    ]
    [late] = attribute(trace, ticks((30.0, 0.0), (30.0025, 1.5e-3)))
    assert late.cause == "steal"
    assert abs(late.shares_s["steal"] - 2.2e-3 * 2.3 / 2.5) < 1e-5


def test_a_late_tick_with_nothing_else_on_its_cpu_and_no_steal_is_unexplained():
    trace = [switch(40.0, WORKER, PYTHON, state="I"), runtime(40.0031, 3_100_000),
             switch(40.0031, PYTHON, ("swapper/1", 0))]
    [late] = attribute(trace, ticks((40.0, 0.0), (40.0030, 2.0e-3)))
    assert late.cause == "unexplained"


def test_a_switch_the_trace_missed_makes_the_cause_unknown_rather_than_a_guess():
    trace = [switch(50.0001, PYTHON, WORKER, state="R"),
             line("kworker/1:2", 7, 50.0002, "local_timer_entry", "vector=236"),
             line("tokio-rt-worker", 75, 50.0025, "local_timer_entry", "vector=236")]
    [late] = attribute(trace, ticks((50.0, 0.0), (50.0030, 2.0e-3)))
    assert late.cause == "untraced"


def test_summary_counts_every_late_tick_once_and_ignores_ticks_on_time():
    trace = [switch(10.0001, PYTHON, WORKER, state="R"), switch(10.003, WORKER, PYTHON, state="I")]
    rows = ticks((10.0, 0.0), (10.0030, 2.0e-3), (10.004, 0.0), (10.005, 0.4e-3))
    summary = stall_trace.summary(attribute(trace, rows), len(rows))
    assert summary == {"late_cause_steal_pct": 0.0, "late_cause_idle_wakeup_pct": 0.0,
                       "late_cause_kernel_pct": 25.0, "late_cause_unexplained_pct": 0.0, "late_cause_untraced_pct": 0.0}


def test_lines_that_are_not_events_are_skipped():
    timeline = stall_trace.parse("# tracer: nop\n\ngarbage line\n" + switch(1.0, PYTHON, WORKER), LOOP)
    assert timeline.events == 1


def test_a_run_without_a_trace_reports_why_and_no_shares():
    with stall_trace.Recording() as recording:
        recording.stop()
        keys, late_ticks = recording.attribute(ticks((1.0, 0.0), (1.003, 2e-3)), LOOP, 1e-3)
    assert late_ticks == []
    assert keys["late_attribution"] == "none: the trace was not started"
    assert all(keys[f"late_cause_{cause}_pct"] is None for cause in stall_trace.CAUSES)
