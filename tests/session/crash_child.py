"""A console stand-in for the crash tests: records synthetic data and gets killed, or runs out of file space.

``python -m tests.session.crash_child kill PATH``: feeds ticks at 1 kHz (frames at 100 Hz, a level every
0.5 s) in 20 ms batches, as the GUI's bridge does, printing ``fed <ticks> <levels>`` after each batch,
until it is killed.

``python -m tests.session.crash_child forget PATH``: hands 5000 ticks to a recorder and exits without
closing it.

``python -m tests.session.crash_child fsize PATH LIMIT_BYTES``: the same with the process's file-size
limit set to LIMIT_BYTES, so writing fails as on a full disk; once the recorder reports the problem it
keeps feeding (the control side must not notice), then prints one JSON line and exits.
"""

from __future__ import annotations

import json
import resource
import signal
import sys
import threading
import time

from control.messages import LevelRecorded
from hardware.interfaces import TactileConstraints
from session.info import SessionInfo, calibration_of
from session.synthetic import frame_rows, level_record, tick_rows
from session.writer import SessionRecorder

INFO = SessionInfo(config={"purpose": "crash test"}, calibration=calibration_of(TactileConstraints(), 0.0))


def _level(k: int, t_s: float) -> LevelRecorded:
    return LevelRecorded(t_s, level_record(k // 7, k % 7, 1.0 + k % 7, (0.004 + 0.008 * (k // 7), 0.015), t_s=t_s))


def kill(path: str) -> None:
    recorder = SessionRecorder(path, INFO, flush_interval_s=0.25)
    pace = threading.Event()
    t0 = time.monotonic()
    fed = levels = 0
    while True:
        pace.wait(0.02)
        due = int((time.monotonic() - t0) * 1000)
        if due <= fed:
            continue
        recorder.add_ticks(tick_rows(fed, due - fed))
        recorder.add_frames(frame_rows(fed // 10, due // 10 - fed // 10))
        while (levels + 1) * 500 <= due:
            recorder.add_events([_level(levels, (levels + 1) * 0.5)])
            levels += 1
        fed = due
        print(f"fed {fed} {levels}", flush=True)


def fsize(path: str, limit: int) -> None:
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails with EFBIG instead of killing us
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
    problem = threading.Event()
    recorder = SessionRecorder(path, INFO, flush_interval_s=0.05, min_free_bytes=0, compression=None,
                               on_problem=lambda message: problem.set())
    fed = calls_after = 0
    while calls_after < 100 and fed < 5_000_000:  # 50x faster than real time: a few flushes succeed first
        recorder.add_ticks(tick_rows(fed, 250))
        recorder.add_events([_level(fed // 250, fed * 1e-3)])
        fed += 250
        if problem.is_set():
            calls_after += 1
        else:
            problem.wait(0.005)
    status = recorder.close()
    print(json.dumps({"problem": status.problem, "fed": fed, "calls_after": calls_after,
                      "recording": status.recording, "ticks_written": status.ticks_written,
                      "rows_dropped": status.rows_dropped}), flush=True)


def forget(path: str) -> None:
    SessionRecorder(path, INFO).add_ticks(tick_rows(0, 5000))


if __name__ == "__main__":
    if sys.argv[1] == "kill":
        kill(sys.argv[2])
    elif sys.argv[1] == "forget":
        forget(sys.argv[2])
    else:
        fsize(sys.argv[2], int(sys.argv[3]))
