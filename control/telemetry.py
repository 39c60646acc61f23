"""Row layouts the loop publishes: one tick row per control period, one frame row per new sensor frame.

The controller process copies these rows into shared-memory rings; the GUI and the session recorder
read them from there. The field names are the stream's public names (they appear in session files), so
they carry their units.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

ROWS, COLS = 4, 15

TICK_DTYPE = np.dtype(
    [
        ("tick", np.int64),  # index of the control period since the loop started
        ("t_s", np.float64),  # loop clock at the start of the tick
        ("late_s", np.float64),  # how late the tick started against its absolute deadline (driver)
        ("compute_s", np.float64),  # the loop's own computation: ControlLoop.step (driver)
        # reading the devices and applying the step's output; on the simulated rig mostly the simulation
        # of the world up to this tick (driver)
        ("io_s", np.float64),
        ("missed_ticks", np.int64),  # cumulative periods skipped by the stall policy (driver)
        ("phase", np.int8),
        ("sz", np.int8),
        ("region_done", np.int8),
        ("fault", np.int8),
        ("region", np.int16),
        ("level", np.int16),  # current level index, -1 outside the ramp
        ("n_levels", np.int16),
        ("force_desired_N", np.float64),  # F_d magnitude, pushing into the tissue
        ("force_measured_N", np.float64),  # F_ts: total force of the latest tactile frame
        ("rmse_N", np.float64),  # RMSE of F_d - F_ts over the settle window (NaN outside SETTLING)
        ("x_ref_m", np.float64, (3,)),  # X_r of Eq. 2
        ("v_ref_m_s", np.float64, (3,)),
        ("x_des_m", np.float64, (3,)),  # X_d: the mapped master / jog position
        ("x_slave_m", np.float64, (3,)),  # X_s: measured TSI position
        ("indentation_m", np.float64),  # live TSI indentation depth (NaN without contact)
        ("sensor_seq", np.int64),
        ("sensor_age_s", np.float64),
        ("master_age_s", np.float64),
        ("slave_age_s", np.float64),
    ]
)

FRAME_DTYPE = np.dtype(
    [
        ("tick", np.int64),  # tick at which the loop first saw the frame
        ("sensor_seq", np.int64),
        ("t_s", np.float64),  # the frame's own timestamp
        ("tsi_position_m", np.float64, (3,)),  # X_s interpolated at the frame's timestamp
        ("pressure_pa", np.float32, (ROWS, COLS)),
        ("dL_m", np.float32, (ROWS, COLS)),  # live per-element indentation (NaN: no contact)
        ("stiffness_pa", np.float32, (ROWS, COLS)),  # live Eq. 1 (NaN: no contact)
    ]
)


def empty_tick() -> np.ndarray:
    row = np.zeros((), dtype=TICK_DTYPE)
    for name in ("rmse_N", "indentation_m", "sensor_age_s", "master_age_s", "slave_age_s"):
        row[name] = np.nan
    row["level"] = -1
    row["sensor_seq"] = -1
    return row


def empty_frame() -> np.ndarray:
    row = np.zeros((), dtype=FRAME_DTYPE)
    row["sensor_seq"] = -1
    row["dL_m"] = np.nan
    row["stiffness_pa"] = np.nan
    return row


@dataclass(frozen=True, slots=True)
class LoopHealth:
    """How well the controller process keeps its period, as measured by its driver."""

    rate_hz: float  # ticks per second over the last report interval
    late_over_0_5ms_pct: float  # since start
    p99_abs_jitter_us: float  # over the last report interval
    missed_ticks: int  # since start
    longest_stall_ms: float  # since start
    rt_priority: bool  # SCHED_FIFO granted
    cpu: int | None  # the CPU the loop is pinned to, if any
    warning: str = ""  # why RT priority or pinning was not granted


@dataclass(slots=True)
class LiveSnapshot:
    """What the GUI gets at display rate: never one signal per tick."""

    tick: np.ndarray  # latest TICK_DTYPE row (a copy)
    frame: np.ndarray | None  # latest FRAME_DTYPE row (a copy); None before the first frame
    ticks: np.ndarray  # every TICK_DTYPE row since the previous snapshot, oldest first
    events: list = field(default_factory=list)  # control.messages events since the previous snapshot
    health: LoopHealth | None = None
