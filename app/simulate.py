"""``palpation-console simulate``: palpate a phantom headlessly with the scripted operator and print what the
loop records."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from app.config import AppConfig
from app.fastforward import FastForward
from app.rigs import build_rig
from control.messages import (
    CommandApplied,
    CommandRefused,
    FaultRaised,
    LevelRecorded,
    LevelTimedOut,
    Notice,
    RegionAborted,
    RegionDone,
)
from hardware.settings import ConfigError
from session.info import new_session_path
from session.writer import RecorderError, SessionRecorder
from tissue.mechanics.progress import TextProgressBar


def _level_line(r) -> str:
    stiff = r.stiffness_pa[np.isfinite(r.stiffness_pa)]
    med = f"{np.median(stiff) / 1e3:7.1f}" if stiff.size else "    n/a"
    peak = f"{np.max(stiff) / 1e3:7.1f}" if stiff.size else "    n/a"
    contact = int(np.isfinite(r.dL_m).sum())
    depth = f"{r.indentation_m * 1e3:6.2f}" if math.isfinite(r.indentation_m) else "   n/a"
    return (f"  {r.level + 1:>5} {r.force_desired_N:8.2f} {r.force_measured_N:8.3f} {depth} {contact:>7}"
            f" {med} {peak} {r.pressure_pa.max() / 1e3:9.1f} {r.rmse_N:7.3f} {r.settle_time_s:7.2f}")


HEADER = ("  level  F_d [N] F_ts [N] depth[mm] contact E_med[kPa] E_max[kPa] p_max[kPa] RMSE[N] settle[s]")


def simulate(config: AppConfig, max_time_s: float = 600.0, verbose: bool = False, record: bool = True,
             path: Path | None = None) -> int:
    """Palpate the phantom end to end on a virtual clock with the scripted operator, as in Section IV-A;
    prints every recorded level and, unless ``record`` is False, records the session to a new file in the
    sessions folder (or to ``path``), as the console does (so that ``stitch`` and ``review`` work without the
    GUI). Returns the exit code: 0 if every area was done without a problem, 2 if the session could not be
    recorded."""
    if config.rig.backend != "sim":
        raise ConfigError("rig.backend", f"simulate palpates the simulated rig, not {config.rig.backend!r}"
                                         " (use `run` for real hardware)")
    rig = build_rig(config.rig, progress=TextProgressBar())
    operator = rig.master
    if operator is None or not hasattr(operator, "finished"):
        raise ConfigError("rig.backend", "simulate needs the simulated rig's scripted operator")
    recorder = None
    if record:
        from app.recording import recording_summary, session_info

        path = path if path is not None else new_session_path()
        try:
            recorder = SessionRecorder(path, session_info(config, rig))
        except RecorderError as err:
            print(f"error: {err} (simulate --no-record palpates without recording)", file=sys.stderr)
            return 2
    phantom = rig.description.get("phantom", config.rig.phantom)
    print(f"Palpating phantom {phantom!r} with the scripted operator ({config.control.ramp.n_levels} levels, "
          f"{config.control.ramp.force_min_N:g}-{config.control.ramp.force_max_N:g} N)")
    if recorder is not None:
        print(f"Recording the session to {recorder.path}")
    try:
        return _palpate(config, rig, operator, max_time_s, verbose, recorder)
    finally:
        if recorder is not None:
            status = recorder.close()
            print(f"Session recorded: {status.path} ({recording_summary(status)})")


def _palpate(config: AppConfig, rig, operator, max_time_s: float, verbose: bool, recorder) -> int:
    failures = 0
    done = 0
    with FastForward(config.control, rig) as ff:
        clock = None
        if recorder is not None:
            from app.recording import NominalClock

            clock = NominalClock(recorder, ff)
        printed = 0
        deadline_s = max_time_s

        def report() -> None:
            nonlocal printed, failures, done
            for event in ff.events[printed:]:
                if isinstance(event, LevelRecorded):
                    if event.record.level == 0:
                        x, y, _ = event.record.tsi_position_m
                        print(f"\nRegion {event.record.region + 1} at x = {x * 1e3:.1f} mm, y = {y * 1e3:.1f} mm")
                        print(HEADER)
                    print(_level_line(event.record))
                elif isinstance(event, RegionDone):
                    done += 1
                    cap = event.cap_text()
                    print(f"  region {event.region + 1} done ({event.n_levels} levels{', ' + cap if cap else ''})")
                elif isinstance(event, (FaultRaised, LevelTimedOut, RegionAborted)):
                    failures += 1
                    print(f"  ! {getattr(event, 'message', None) or getattr(event, 'reason', '')}")
                elif isinstance(event, (CommandApplied, CommandRefused, Notice)) and verbose:
                    print(f"  {event}")
            if recorder is not None:
                recorder.add_ticks(ff.ticks)
                recorder.add_frames(ff.frames)
                recorder.add_events(ff.events)
                clock.every_interval()
            ff.clear()  # the rows are in the file (or not wanted): keep memory flat over long runs
            printed = 0

        while not operator.finished:
            ff.run_for(1.0)
            report()
            if ff.now_s > deadline_s:
                print(f"error: the scripted operator had not finished after {deadline_s:g} s of simulated time",
                      file=sys.stderr)
                return 1
        report()
        if clock is not None:
            clock.pair()
    print(f"\n{done} of {len(operator.regions)} regions done, {failures} problems, "
          f"{ff.now_s:.1f} s of simulated time")
    return 0 if done == len(operator.regions) and failures == 0 else 1
