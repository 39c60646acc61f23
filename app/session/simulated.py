"""Record a whole simulated session: the scripted operator palpates the phantom on a virtual clock.

The rows reach the recorder in the pieces the GUI's bridge would hand it (every ``chunk_s`` of simulated
time), so a recording made here is the same file the console makes, only faster than real time.
"""

from __future__ import annotations

from pathlib import Path

from app.config import AppConfig
from app.fastforward import FastForward, FastForwardTimeout
from app.rigs import build_rig
from app.session.recorder import RecorderStatus, SessionInfo, SessionRecorder
from hardware.rig import Rig
from hardware.settings import ConfigError


def record_simulation(path: str | Path, config: AppConfig, *, rig: Rig | None = None, max_time_s: float = 900.0,
                      chunk_s: float = 0.1, **recorder_options) -> RecorderStatus:
    """Palpate every area of the configured phantom and record it to ``path``; returns the recorder's status.

    ``rig``: a simulated rig built for ``config`` (to choose its tissue model, say); built from the config
    when not given. Raises ConfigError if the rig has no scripted operator, FastForwardTimeout if the operator
    has not finished after ``max_time_s`` of simulated time (the file is still closed cleanly).
    """
    if chunk_s <= 0:
        raise ValueError(f"chunk_s must be > 0, got {chunk_s!r}")
    rig = rig if rig is not None else build_rig(config.rig)
    operator = rig.master
    if operator is None or not hasattr(operator, "finished"):
        raise ConfigError("rig.backend", "recording a simulation needs the simulated rig's scripted operator")
    recorder = SessionRecorder(path, SessionInfo.from_rig(config, rig), **recorder_options)
    try:
        with FastForward(config.control, rig) as ff:
            while not operator.finished:
                if ff.now_s > max_time_s:
                    raise FastForwardTimeout(f"the scripted operator had not finished after {max_time_s:g} s of "
                                             f"simulated time ({len(operator.outcomes)} areas done)")
                ff.run_for(chunk_s)
                recorder.add_ticks(ff.ticks)
                recorder.add_frames(ff.frames)
                recorder.add_events(ff.events)
                ff.clear()
    finally:
        status = recorder.close()
    return status
