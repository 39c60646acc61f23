"""The session file format: the layout of one self-describing HDF5 file per session, its row types, and
how control events become rows.

Layout, format ``palpation-console-session`` (the one place it is defined; docs/session-format.md explains
it for readers outside Python; :mod:`session.writer` writes it, :mod:`session.reader` reads it)::

    /                       attrs: format, format_version (int), uuid, created_utc (ISO 8601), software,
                            software_version, simulated (bool)
    /meta                   group; each attr is JSON text, SI units, key names carry units:
        config_json         the full configuration the controller ran with: {"control": ..., "rig": ..., "sim": ...}
        calibration_json    sensor geometry {rows, cols, pitch_m, element_area_m2, full_scale_pa,
                            frame_rate_hz} and table_height_m, the height the L0 values are measured from;
                            ``elements``: the array's calibration its frames were corrected by, if one was
                            loaded (hardware.array_calibration.ArrayCalibration.to_mapping: gain, gain_sigma)
        rig_json            what was built (hardware.rig.Rig.description)
        phantom_json        simulated sessions: the phantom definition (its TOML as a table); null otherwise
        ground_truth_json   simulated sessions: the phantom's tumours [{x_m, y_m, z_m, depth_m, diameter_m,
                            youngs_modulus_pa}]; [] otherwise
    /stream/ticks           TICK_DTYPE (control.telemetry): one row per control period, oldest first. ``tick``
                            counts the loop's periods, so a jump in it is rows lost before the file
    /stream/frames          FRAME_DTYPE: one row per tactile frame
    /stream/overview        OVERVIEW_DTYPE: one row per OVERVIEW_BUCKET_ROWS consecutive tick rows, their time
                            span and the min/max of the channels a timeline draws (derived from the ticks;
                            lets a viewer show hours at a glance without reading them)
    /levels                 LEVEL_DTYPE: one row per recorded force level (control.messages.LevelRecord)
    /events                 EVENT_DTYPE: one row per event, kinds in EventKind; a cleanly closed file ends
                            with one "closed" row
    /clock                  CLOCK_DTYPE: one row per reading of the loop's clock and UTC together, when
                            recording began, about every CLOCK_INTERVAL_S of loop time and when it ended
                            (version 3)

Every dataset carries ``description`` (one line: what a row is); /stream/overview carries ``bucket_rows``
(:data:`OVERVIEW_BUCKET_ROWS`). /stream/ticks, /levels and /events carry ``notes_json`` (what a column means
where its name cannot say: that ``missed_ticks`` is a running total, that regions and levels count from 0
where the console shows them from 1; for /clock, what a pair means, on the simulated rig too:
:data:`CLOCK_NOTES`), and /stream/ticks and /events ``codes_json``, the name of every code of their coded
integer columns (:data:`TICK_CODES`; for /events per kind, :data:`EVENT_CODES`).

Text attributes are fixed-length UTF-8 strings. Every dataset is 1-D, chunked, resizable, appended in blocks,
byte-shuffled, deflated (level 1) and Fletcher-32 checksummed, all of it built into every HDF5, so any HDF5
tool reads the file. In /levels and /events ``seq`` is the row's index + 1, and no real tick, frame or clock
row is all zero bytes, so a row whose data never reached the disk (HDF5 reads it as zeros) is recognisable.

Versions. A column added to a dataset bumps :data:`FORMAT_VERSION`, and :data:`ADDED_COLUMNS` says from which
version on a column is written, so a reader gives older files the column as NaN (-1 for integers).
A dataset added bumps it too, and :data:`ADDED_TABLES` says from which version on it is written; a reader
gives an older file the dataset without rows. Version 2 added each level's per-element scatter over its
settle window (``pressure_std_pa``, ``window_frames``); version 1 files may also lack ``io_s`` in
/stream/ticks, added before this rule. Version 3 added /clock.
"""

from __future__ import annotations

import math

import numpy as np

from control.messages import (
    CommandApplied,
    CommandRefused,
    FaultCleared,
    FaultKind,
    FaultRaised,
    LevelRecord,
    LevelRecorded,
    LevelTimedOut,
    Notice,
    PhaseChanged,
    RegionAborted,
    RegionDone,
    SzChanged,
)
from control.telemetry import COLS, FRAME_DTYPE, ROWS, TICK_DTYPE
from hardware.interfaces import Phase

FORMAT_NAME = "palpation-console-session"
FORMAT_VERSION = 3
OVERVIEW_BUCKET_ROWS = 1000

_GRID = (ROWS, COLS)
LEVEL_DTYPE = np.dtype(
    [
        ("seq", np.int64),
        ("region", np.int32),
        ("level", np.int32),
        ("t_s", np.float64),
        ("force_desired_N", np.float64),
        ("force_measured_N", np.float64),
        ("rmse_N", np.float64),
        ("settle_time_s", np.float64),
        ("tsi_position_m", np.float64, (3,)),
        ("indentation_m", np.float64),
        ("pressure_pa", np.float64, _GRID),
        ("pressure_std_pa", np.float64, _GRID),  # scatter of the frames over the settle window (version 2)
        ("window_frames", np.int32),  # frames averaged (version 2)
        ("element_force_N", np.float64, _GRID),
        ("onset_height_m", np.float64, _GRID),
        ("L0_m", np.float64, _GRID),
        ("dL_m", np.float64, _GRID),
        ("stiffness_pa", np.float64, _GRID),
    ]
)

EVENT_TEXT_BYTES = 240
EVENT_DTYPE = np.dtype(
    [
        ("seq", np.int64),
        ("t_s", np.float64),
        ("kind", "S16"),
        ("region", np.int32),  # -1 when the event is not about a region
        ("level", np.int32),  # -1 when not about a level
        ("code", np.int32),  # kind-specific: S_z, Phase, FaultKind, notice severity (0 info, 1 warning)
        ("value", np.float64),  # kind-specific: force of a level, rows lost, ... (NaN when unused)
        ("text", f"S{EVENT_TEXT_BYTES}"),  # UTF-8, cut at a character boundary
    ]
)

CLOCK_DTYPE = np.dtype(
    [
        ("t_s", np.float64),  # the loop's clock
        ("utc_ns", np.int64),  # UTC at that instant, ns since 1970-01-01 (Unix time: leap seconds not counted)
    ]
)
# Pairs this far apart in loop time keep the interpolated UTC within a millisecond of the wall clock's even
# while NTP slews it at its fastest (500 ppm), and cost 16 bytes a second.
CLOCK_INTERVAL_S = 1.0

# Channels of the timeline overview: (name in OVERVIEW_DTYPE, tick field, index into a vector field or None)
OVERVIEW_CHANNELS: tuple[tuple[str, str, int | None], ...] = (
    ("force_measured_N", "force_measured_N", None),
    ("force_desired_N", "force_desired_N", None),
    ("indentation_m", "indentation_m", None),
    ("tsi_z_m", "x_slave_m", 2),
    ("late_s", "late_s", None),
)
OVERVIEW_DTYPE = np.dtype(
    [("row_start", np.int64), ("n_rows", np.int32), ("t_start_s", np.float64), ("t_end_s", np.float64)]
    + [(f"{name}_{stat}", np.float64) for name, _, _ in OVERVIEW_CHANNELS for stat in ("min", "max")]
)



def _codes(kind) -> dict[str, str]:
    return {str(int(member)): member.name for member in kind}


_SZ_CODES = {"0": "force control in z (S_z = 0)", "1": "position control in z (S_z = 1)"}
# The meaning of every coded integer column, stored with the file (``codes_json`` attributes) so that a reader
# without this code can decode it.
TICK_CODES = {"phase": _codes(Phase), "sz": _SZ_CODES, "region_done": {"0": "no", "1": "yes"},
              "fault": _codes(FaultKind)}
EVENT_CODES = {"sz": _SZ_CODES, "phase": _codes(Phase), "fault": _codes(FaultKind), "fault_cleared": _codes(FaultKind),
               "notice": {"0": "info", "1": "warning"}, "region_done": "the number of levels recorded"}
TICK_NOTES = {
    "tick": "index of the control period since the loop started; a jump between rows is rows lost",
    "t_s": "the loop's clock at the start of the tick, s; the session's own time is t_s minus the first row's",
    "missed_ticks": "running total since the loop started of the control periods the stall policy skipped "
                    "(not a count per row: the periods skipped before a row are its value minus the previous "
                    "row's)",
    "region": "palpated area, counted from 0 in the order palpated (the console shows it counted from 1)",
    "level": "force level within the area's ramp, counted from 0 (the console shows it counted from 1); "
             "-1 outside the ramp",
}

CLOCK_NOTES = {
    "t_s": "the loop's clock, s, as t_s of /stream/ticks",
    "utc_ns": "UTC at the instant the loop's clock read t_s, ns since 1970-01-01 (Unix time: leap seconds not "
              "counted); between pairs UTC is interpolated linearly, beyond the first and the last it runs on at "
              "the loop clock's rate. On the controller the two clocks are read together. A simulated session "
              "runs on a virtual clock, faster than real time: there utc_ns is a nominal time line, the moment "
              "recording began plus the simulated time since, which lines up only with other exports of the "
              "same session",
}

# How a finding the console told the surgeon begins, among the session's notes (what was told, and when)
FINDINGS_TOLD = "Console told the surgeon:"


class EventKind:
    """Values of the ``kind`` column of /events."""

    SZ = "sz"  # code = S_z, text = who switched it
    PHASE = "phase"  # code = Phase, level, value = number of levels, text = phase name
    LEVEL = "level"  # region, level, value = F_d; the level's data is the matching /levels row
    LEVEL_TIMEOUT = "level_timeout"  # region, level, value = F_d, text = why
    REGION_DONE = "region_done"  # region, code = number of levels, value = the force it was capped at (NaN: none)
    REGION_ABORTED = "region_aborted"  # region, text = why
    FAULT = "fault"  # code = FaultKind, text = message
    FAULT_CLEARED = "fault_cleared"  # code = FaultKind
    APPLIED = "applied"  # text = "<command>: <what changed>"
    REFUSED = "refused"  # text = "<command>: <reason>"
    NOTICE = "notice"  # code = 0 info / 1 warning, text
    NOTE = "note"  # text = the operator's note, or a finding the console told the surgeon (FINDINGS_TOLD ...)
    ROWS_LOST = "rows_lost"  # value = rows missing from the stream before this point, text = "ticks"
    RECORDER = "recorder"  # text = what the recorder did (stopped on a full disk, ...)
    CONTROLLER_LOST = "controller_lost"  # the controller stopped on its own (killed, crashed); text = how
    CLOSED = "closed"  # the last row of a cleanly closed file; text = UTC time of closing


# A chunk that is still filling up is rewritten at every flush; if that write fails (full disk), the rows
# it held before are lost too. Levels are the data that matter most, so each gets a chunk of its own.
CHUNK_ROWS = {"ticks": 1024, "frames": 128, "overview": 256, "levels": 1, "events": 16, "clock": 64}

# Columns written from a format version on: (dataset, column) -> the first version that always has it. A file
# of an older version may lack the column; the reader gives it NaN there.
ADDED_COLUMNS: dict[tuple[str, str], int] = {
    ("stream/ticks", "io_s"): 2,
    ("levels", "pressure_std_pa"): 2,
    ("levels", "window_frames"): 2,
}

# Datasets written from a format version on: name -> the first version that always has it. A file of an older
# version may lack the dataset; the reader gives it no rows.
ADDED_TABLES: dict[str, int] = {
    "clock": 3,
}

TABLES: dict[str, np.dtype] = {
    "stream/ticks": TICK_DTYPE,
    "stream/frames": FRAME_DTYPE,
    "stream/overview": OVERVIEW_DTYPE,
    "levels": LEVEL_DTYPE,
    "events": EVENT_DTYPE,
    "clock": CLOCK_DTYPE,
}


# ---- events and level records as rows ------------------------------------------------------------------


def event_text(value: str) -> bytes:
    """UTF-8, cut at a character boundary to fit the events' text column."""
    raw = value.encode("utf-8")
    if len(raw) <= EVENT_TEXT_BYTES:
        return raw
    return raw[:EVENT_TEXT_BYTES].decode("utf-8", errors="ignore").encode("utf-8")


def level_row(record: LevelRecord) -> tuple:
    """A LEVEL_DTYPE row (without its seq) for one level record."""
    return (0, record.region, record.level, record.t_s, record.force_desired_N, record.force_measured_N,
            record.rmse_N, record.settle_time_s, record.tsi_position_m, record.indentation_m, record.pressure_pa,
            record.pressure_std_pa, record.window_frames, record.element_force_N, record.onset_height_m, record.L0_m,
            record.dL_m, record.stiffness_pa)


def event_row(t_s: float, kind: str, *, region: int = -1, level: int = -1, code: int = 0, value: float = math.nan,
              text: str = "") -> tuple:
    return (0, t_s, kind.encode("ascii"), region, level, code, value, event_text(text))


def rows_for_event(event) -> tuple[tuple | None, tuple | None]:
    """(event row, level row or None) for a control.messages event; (None, None) for other objects."""
    k = EventKind
    if isinstance(event, LevelRecorded):
        r = event.record
        return (event_row(event.t_s, k.LEVEL, region=r.region, level=r.level, value=r.force_desired_N),
                level_row(r))
    if isinstance(event, SzChanged):
        row = event_row(event.t_s, k.SZ, code=int(event.sz), text=event.source.name.lower())
    elif isinstance(event, PhaseChanged):
        row = event_row(event.t_s, k.PHASE, level=event.level, code=int(event.phase), value=float(event.n_levels),
                        text=event.phase.name)
    elif isinstance(event, LevelTimedOut):
        row = event_row(event.t_s, k.LEVEL_TIMEOUT, region=event.region, level=event.level,
                        value=event.force_desired_N, text=event.message)
    elif isinstance(event, RegionDone):
        row = event_row(event.t_s, k.REGION_DONE, region=event.region, code=event.n_levels, value=event.capped_N,
                        text=event.cap_text())
    elif isinstance(event, RegionAborted):
        row = event_row(event.t_s, k.REGION_ABORTED, region=event.region, text=event.reason)
    elif isinstance(event, FaultRaised):
        row = event_row(event.t_s, k.FAULT, code=int(event.kind), text=event.message)
    elif isinstance(event, FaultCleared):
        row = event_row(event.t_s, k.FAULT_CLEARED, code=int(event.kind), text=event.kind.name)
    elif isinstance(event, CommandRefused):
        row = event_row(event.t_s, k.REFUSED, text=f"{event.command_name}: {event.reason}")
    elif isinstance(event, CommandApplied):
        row = event_row(event.t_s, k.APPLIED, text=f"{type(event.command).__name__}: {event.message}")
    elif isinstance(event, Notice):
        row = event_row(event.t_s, k.NOTICE, code=1 if event.level == "warning" else 0, text=event.message)
    else:
        return None, None
    return row, None


class Overview:
    """Folds tick rows into OVERVIEW_DTYPE buckets of OVERVIEW_BUCKET_ROWS rows (the writer as it goes; a
    reader for buckets the writer never wrote)."""

    def __init__(self):
        self.tail = np.empty(0, TICK_DTYPE)
        self.rows_done = 0  # tick rows already folded into complete buckets

    @staticmethod
    def buckets(ticks: np.ndarray, row_start: int, size: int) -> np.ndarray:
        n = len(ticks) // size if size else 0
        out = np.zeros(n, OVERVIEW_DTYPE)
        if n == 0:
            return out
        t = ticks["t_s"][: n * size].reshape(n, size)
        out["row_start"] = row_start + np.arange(n) * size
        out["n_rows"] = size
        out["t_start_s"] = t[:, 0]
        out["t_end_s"] = t[:, -1]
        for name, source, index in OVERVIEW_CHANNELS:
            column = ticks[source][: n * size]
            if index is not None:
                column = column[:, index]
            column = column.reshape(n, size)
            # fmin/fmax skip NaN (no contact, outside a ramp) and give NaN only for an all-NaN bucket
            out[f"{name}_min"] = np.fmin.reduce(column, axis=1)
            out[f"{name}_max"] = np.fmax.reduce(column, axis=1)
        return out

    def add(self, ticks: np.ndarray) -> np.ndarray:
        rows = np.concatenate([self.tail, ticks]) if len(self.tail) else ticks
        full = self.buckets(rows, self.rows_done, OVERVIEW_BUCKET_ROWS)
        used = len(full) * OVERVIEW_BUCKET_ROWS
        self.tail = rows[used:].copy()
        self.rows_done += used
        return full

    def finish(self) -> np.ndarray:
        if not len(self.tail):
            return np.zeros(0, OVERVIEW_DTYPE)
        last = self.buckets(self.tail, self.rows_done, len(self.tail))
        self.rows_done += len(self.tail)
        self.tail = self.tail[:0]
        return last
