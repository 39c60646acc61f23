"""Read a session file, read-only, validating it first.

:func:`open_session` either returns a :class:`Session` or raises :class:`SessionFileError` whose message
names the file and the problem in words an operator can act on: missing, not a regular file (a folder, a
FIFO, a device: refused without waiting on them), empty, not HDF5 (a foreign file), HDF5 but not a session,
a session from a newer version, truncated, corrupt. Nothing in here ever
writes to the file: a session left open by a killed console is opened in HDF5's SWMR-read mode (see
:mod:`session.writer`), which reads it as it is.

A file whose last writes never reached the disk (killed console, full disk) reads as zeros past the
last good row; those rows are trimmed and the session carries a warning saying so. A file cut short (a copy
that stopped, a full disk) is opened as if its missing tail were zeros: what lies wholly in the part that
is there is read, and the warnings say what was lost.

Nothing the file declares is trusted before it is checked against the file itself: a table's rows are
read only as far as its stored chunks reach inside the file (a crafted header claiming 10^10 rows costs
nothing), a table whose chunks hold more rows than a session can (:data:`ROW_BOUNDS`) is refused before any
of them is read, rows are read :data:`MAX_READ_BYTES` at a time, chunks and metadata attributes are bounded
in size before HDF5 is asked to load them, and
positions and the element pitch are checked for sense before anything is laid out on a grid. Nothing out of
the file is followed: a link into another file, a soft link that leads there, rows stored in another file or
gathered from others (a virtual dataset) are refused before HDF5 is asked to follow them.
"""

from __future__ import annotations

import ctypes
import functools
import io
import json
import math
import os
import re
import stat
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from control.config import RATE_HZ_RANGE
from control.telemetry import TICK_DTYPE
from hardware.array_calibration import ArrayCalibration, ArrayCalibrationError
from session.format import (
    ADDED_COLUMNS,
    ADDED_TABLES,
    CLOCK_DTYPE,
    CLOCK_INTERVAL_S,
    FORMAT_NAME,
    FORMAT_VERSION,
    OVERVIEW_BUCKET_ROWS,
    OVERVIEW_DTYPE,
    TABLES,
    EventKind,
    Overview,
)

_META_KEYS = ("config_json", "calibration_json", "rig_json", "phantom_json", "ground_truth_json")
_TAIL_WINDOWS = 64  # how far back (in chunks) a damaged stream tail is looked for
_READ_ERRORS = (OSError, RuntimeError, KeyError, ValueError, TypeError)

# Our chunks are at most 0.4 MB (session.format.CHUNK_ROWS); a chunk this large did not come from the
# console, and HDF5 would allocate it whole to read a single row of it.
MAX_CHUNK_BYTES = 16 * 2**20
# A stored chunk is never larger than its rows plus the filters' overhead (deflate's stored blocks add
# 5 bytes per 64 KB, Fletcher-32 four bytes); a larger one is damage or a crafted size.
_CHUNK_SLACK = 1.01
_CHUNK_OVERHEAD_BYTES = 1024
MAX_META_BYTES = 16 * 2**20  # a /meta attribute (JSON); ours are a few kB

# What a session can hold. A table whose chunks hold more rows than this is refused before any of its rows is
# read, however its header or its chunks divide the claim (many small chunks add up to millions of rows). A
# session is taken to last at most a working day, 8 hours, recorded without a pause at the highest rates the
# console records at (at the default 1 kHz loop and 100 Hz frames, the streams' bounds hold 40 hours or more).
# /levels and /events are read whole: their bounds cap what a session holds in memory, 190 MiB of levels and
# 513 MiB of events; the streams are read in pieces on request, and their bounds cap the time a pass over one
# takes (the overview recomputed for a file that lacks it).
SESSION_BOUND_S = 8 * 3600
_MAX_TICKS = int(SESSION_BOUND_S * RATE_HZ_RANGE[1])
ROW_BOUNDS: dict[str, tuple[int, str]] = {
    # a row per control period, at the fastest rate the loop may run (control.config.RATE_HZ_RANGE)
    "stream/ticks": (_MAX_TICKS, f"8 hours of control periods at {RATE_HZ_RANGE[1] / 1e3:g} kHz"),
    # a row per tactile frame, at 1 kHz: no tactile array the console drives sends faster (the simulated and
    # the serial array's bound; the UDP one forwards the slave's), one frame per control period by default
    "stream/frames": (SESSION_BOUND_S * 1000, "8 hours of tactile frames at 1 kHz"),
    "stream/overview": (-(-_MAX_TICKS // OVERVIEW_BUCKET_ROWS),
                        f"one per {OVERVIEW_BUCKET_ROWS} of the most control periods"),
    # a level is recorded once the force has settled over a window of at least min_settle_s (0.5 s by default,
    # the paper's ramp) since the level before: 2 a second, were the probe never moved between areas
    "levels": (SESSION_BOUND_S * 2, "8 hours of force levels, one every 0.5 s"),
    # levels at that pace bring 4 events a second (the level, the next level's phase); the recorder adds a
    # rows_lost event at most once per batch of rows the display hands it, 60 a second, were it to fall behind
    # at every refresh for all 8 hours; areas, faults, commands and notes come at an operator's pace
    "events": (SESSION_BOUND_S * 64, "8 hours of 64 events a second"),
    # a pair every CLOCK_INTERVAL_S of loop time; twice that leaves room for the pairs of a start and an end
    "clock": (int(2 * SESSION_BOUND_S / CLOCK_INTERVAL_S), "8 hours of clock pairs, two a second"),
}
# The chunks of a table looked through to find where its rows end, at about 3 us each (3 s at most); a real
# session's largest table has about 225,000 (8 hours of frames at 1 kHz in the writer's 128-row chunks).
MAX_CHUNKS = 2**20
# The most one read asks of HDF5: rows are read this much at a time, so that neither the read's buffer nor
# HDF5's own for it grows with what a caller asks for at once (chunks are decompressed one at a time anyway).
MAX_READ_BYTES = 4 * 2**20
# HDF5 follows links, and reads rows, into other files of its own accord: a file named there may be a FIFO,
# whose open never returns, or any file on the disk. The writer keeps everything in the one file (groups and
# datasets of its own, no links, no external or virtual storage), so the reader follows nothing out of it.
_ONE_FILE = "a session keeps all of itself in one file, and nothing out of it is followed"
MAX_SOFT_LINKS = 16  # soft links followed in a row to one object, as HDF5's own limit (H5L_NUM_LINKS)
MAX_COORDINATE_M = 1.0  # a position further than this from the tissue frame's origin is not on any tissue
PITCH_RANGE_M = (0.1e-3, 20e-3)  # tactile element pitches this reader makes sense of


class SessionFileError(Exception):
    """The file cannot be read as a session; the message says why."""

    def __init__(self, path: str | Path, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)
        self.problem = problem


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def _explain_open_error(err: BaseException) -> str:
    text = str(err)
    if "truncated file" in text:
        m = re.search(r"eof = (\d+).*stored_eof = (\d+)", text)
        sizes = f" ({int(m.group(1)):,} of {int(m.group(2)):,} bytes)" if m else ""
        return (f"the file is truncated{sizes}: it was cut short while being copied or written (a full disk?)")
    if "already open for write" in text or "file consistency flags" in text:
        return ("the file was not closed cleanly and HDF5 cannot recover it: it was not written in SWMR mode, "
                "so it did not come from this console")
    if "signature" in text:
        return "the file is not an HDF5 file"
    return f"the file is corrupt: HDF5 cannot open it ({_first_line(err)})"


@dataclass(frozen=True)
class RegionEntry:
    """One palpated area as recorded: consecutive /levels rows with the same region index."""

    region: int
    rows: tuple[int, ...]  # indices into Session.levels, lowest level first
    centre_xy_m: tuple[float, float]  # mean recorded TSI position over its levels
    outcome: str  # "done" | "aborted" | "incomplete"


class Session:
    """A validated, open session file. Use as a context manager or call :meth:`close`.

    Small tables (levels, events, metadata) are read at once; the streams are read on request.
    """

    def __init__(self, path: Path, f: h5py.File, size: int, recovered: bool, note: str, damage: str = "",
                 padded: _PaddedFile | None = None):
        self.path = path
        self._f = f
        self._padded = padded
        self._file_bytes = size  # of the file HDF5 opened, as checked before it did
        self.recovered = recovered
        # why the file could not be opened normally (truncated, ...): what a read failure then means
        self._damage = damage or "the file is corrupt"
        self.warnings: list[str] = []
        if recovered:
            self.warnings.append(note)
        try:
            self._load()
        except SessionFileError:
            self._close_file()
            raise
        except _READ_ERRORS as err:
            self._close_file()
            raise SessionFileError(path, f"{self._damage}: HDF5 could not read it ({_first_line(err)})") from None

    # ---- loading and validation ------------------------------------------------------------------------

    def _fail(self, problem: str):
        if self._padded is not None:  # cut short: that is the cause of whatever else is wrong
            problem = f"{self._damage}; {problem}"
        raise SessionFileError(self.path, problem)

    def _load(self) -> None:
        f = self._f
        attrs = f.attrs
        if "format" not in attrs:
            names = ", ".join(sorted(f.keys())[:8]) or "nothing"
            self._fail(f"this HDF5 file is not a Palpation Console session: it has no 'format' attribute "
                       f"(it contains: {names})")
        fmt = _as_str(attrs["format"])
        if fmt != FORMAT_NAME:
            self._fail(f"this HDF5 file is not a Palpation Console session: its format is {fmt!r}, "
                       f"expected {FORMAT_NAME!r}")
        try:
            version = int(attrs["format_version"])
        except (KeyError, TypeError, ValueError, OverflowError):  # OverflowError: infinity
            self._fail("the session has no readable 'format_version' attribute: the file is damaged")
        if version > FORMAT_VERSION:
            self._fail(f"the session was written by a newer Palpation Console (session format version {version}; "
                       f"this version reads up to {FORMAT_VERSION}). Update Palpation Console to open it.")
        if version < 1:
            self._fail(f"the session's format_version is {version}, which no Palpation Console ever wrote: "
                       "the file is damaged")
        self.format_version = version
        self.uuid = _as_str(attrs.get("uuid", ""))
        self.created_utc = _as_str(attrs.get("created_utc", ""))
        self.software_version = _as_str(attrs.get("software_version", ""))
        self.simulated = bool(attrs.get("simulated", False))

        meta = self._member("meta")
        if not isinstance(meta, h5py.Group):
            self._fail("the file is damaged: the /meta group is missing")
        values = {}
        for key in _META_KEYS:
            if key not in meta.attrs:
                self._fail(f"the file is damaged: /meta has no {key!r} attribute")
            stored = meta.attrs.get_id(key).get_storage_size()
            if stored > MAX_META_BYTES:
                self._fail(f"the file is damaged or was not written by Palpation Console: /meta attribute {key!r} "
                           f"is {stored / 2**20:.0f} MB (at most {MAX_META_BYTES // 2**20} MB expected)")
            try:
                values[key] = json.loads(_as_str(meta.attrs[key]))
            except json.JSONDecodeError as err:
                self._fail(f"the file is damaged: /meta attribute {key!r} is not valid JSON ({err})")
        for key in ("config_json", "calibration_json", "rig_json"):
            if not isinstance(values[key], dict):
                self._fail(f"the file is damaged: /meta attribute {key!r} is not a JSON object")
        if values["phantom_json"] is not None and not isinstance(values["phantom_json"], dict):
            self._fail("the file is damaged: /meta attribute 'phantom_json' is neither null nor a JSON object")
        truth = values["ground_truth_json"]
        if not isinstance(truth, list) or not all(
                isinstance(t, dict) and all(_is_coordinate(t.get(k)) for k in ("x_m", "y_m")) for t in truth):
            self._fail("the file is damaged: /meta attribute 'ground_truth_json' is not a list of tumours with "
                       f"x_m and y_m within {MAX_COORDINATE_M:g} m of the origin")
        self.config: dict[str, Any] = values["config_json"]
        self.calibration: dict[str, Any] = values["calibration_json"]
        # the tactile array's calibration the console took out of every frame (hardware/array_calibration.py)
        self.array_calibration: ArrayCalibration | None = None
        if "elements" in self.calibration:
            try:
                self.array_calibration = ArrayCalibration.from_mapping(self.calibration["elements"],
                                                                       "the array's calibration")
            except ArrayCalibrationError as err:
                self.warnings.append(f"{err}: its frames were corrected by a calibration this file does not "
                                     f"hold intact")
        self.rig: dict[str, Any] = values["rig_json"]
        self.phantom: dict[str, Any] | None = values["phantom_json"]
        self.ground_truth: list[dict[str, Any]] = truth
        pitch = self.calibration.get("pitch_m")
        lo, hi = PITCH_RANGE_M
        if not isinstance(pitch, (int, float)) or not lo <= pitch <= hi:
            self._fail(f"the file is damaged: the calibration's element pitch_m must be between {lo * 1e3:g} and "
                       f"{hi * 1e3:g} mm (got {pitch!r})")

        self._ds: dict[str, h5py.Dataset] = {}
        absent = set()
        for name, dtype in TABLES.items():
            ds = self._member(name)
            if ds is None and version < ADDED_TABLES.get(name, 0):
                absent.add(name)  # written only from a later version on
                continue
            if not isinstance(ds, h5py.Dataset):
                self._fail(f"the file is damaged: the dataset /{name} is missing")
            self._check_rows_are_here(name, ds)
            optional = {column for (table, column), since in ADDED_COLUMNS.items() if table == name and version < since}
            problem = _dtype_problem(ds.dtype, dtype, optional)
            if problem or ds.ndim != 1:
                self._fail(f"the file is damaged: /{name} does not hold the expected rows ({problem or 'not 1-D'})")
            self._ds[name] = ds
        self._stored = {name: 0 if name in absent else self._stored_rows(name) for name in TABLES}

        self.levels = self._placed_levels(self._read_numbered("levels"))
        self.events = self._read_numbered("events")
        self.n_ticks = self._valid_stream_length("stream/ticks")
        self.n_frames = self._valid_stream_length("stream/frames")
        clock = np.zeros(0, CLOCK_DTYPE) if "clock" in absent else _conform(
            self._read_rows("clock", 0, self._valid_stream_length("clock")), CLOCK_DTYPE)
        self.clock = clock[np.isfinite(clock["t_s"])]  # pairs of clocks, in the order recorded
        self._clock_map: ClockMap | None = None
        self._overview: np.ndarray | None = None
        self.closed_cleanly = bool(len(self.events)) and self.events["kind"][-1] == EventKind.CLOSED.encode()
        for row in self.events[self.events["kind"] == EventKind.RECORDER.encode()]:
            self.warnings.append(_as_str(row["text"]))
        for row in self.events[self.events["kind"] == EventKind.CONTROLLER_LOST.encode()]:
            self.warnings.append(f"The controller stopped on its own at t = {float(row['t_s']):.1f} s (loop time): "
                                 f"{_as_str(row['text'])}")
        lost = self.events[self.events["kind"] == EventKind.ROWS_LOST.encode()]["value"]
        self.rows_lost = int(lost[np.isfinite(lost)].sum())  # an infinite count is damage, and no int
        if self.rows_lost:
            self.warnings.append(f"{self.rows_lost} tick rows were lost before they reached the file "
                                 "(the display fell behind the controller)")

    def _member(self, path: str) -> h5py.HLObject | None:
        """The object at ``path`` (from the root), or None if there is none, looked up one link at a time so
        that no link into another file is ever followed (soft links are, within the file)."""
        obj, trail, todo, hops = self._f, [], [part for part in path.split("/") if part], 0
        while todo:
            if not isinstance(obj, h5py.Group):
                return None
            part = todo.pop(0)
            name, links = part.encode(), obj.id.links
            if not links.exists(name):
                return None
            kind = links.get_info(name).type
            if kind == h5py.h5l.TYPE_HARD:
                obj = obj[part]
                trail.append(part)
            elif kind == h5py.h5l.TYPE_SOFT:
                hops += 1
                if hops > MAX_SOFT_LINKS:
                    self._fail(f"the file is damaged: /{path} is reached through more than {MAX_SOFT_LINKS} soft links "
                               "in a row (they go round in a loop)")
                target = _as_str(links.get_val(name))
                if target.startswith("/"):
                    obj, trail = self._f, []
                todo = [p for p in target.split("/") if p] + todo
            else:
                where = "/" + "/".join([*trail, part])
                leads = (f"is a link into another file, {_as_str(links.get_val(name)[0])}"
                         if kind == h5py.h5l.TYPE_EXTERNAL else "is a user-defined link")
                self._fail(f"the file was not written by Palpation Console: {where} {leads}; {_ONE_FILE}")
        return obj

    def _check_rows_are_here(self, name: str, ds: h5py.Dataset) -> None:
        """Refuses a dataset whose rows HDF5 would read from other files."""
        if ds.is_virtual:
            self._fail(f"the file was not written by Palpation Console: /{name} is a virtual dataset, whose rows "
                       f"HDF5 gathers from other datasets (in other files, too); {_ONE_FILE}")
        plist = ds.id.get_create_plist()
        if plist.get_external_count():
            self._fail(f"the file was not written by Palpation Console: /{name} keeps its rows in another file, "
                       f"{_as_str(plist.get_external(0)[0])}; {_ONE_FILE}")

    def _stored_rows(self, name: str) -> int:
        """How many leading rows of /name lie wholly inside the file (not what its header declares)."""
        ds = self._ds[name]
        declared = ds.shape[0]
        row_bytes = ds.dtype.itemsize
        if ds.chunks is None:
            offset = ds.id.get_offset()
            if offset is None:  # compact (inside its header, so bounded by it) or never written
                n = declared if ds.id.get_storage_size() >= declared * row_bytes else 0
            else:
                n = min(declared, max(0, self._file_bytes - offset) // row_bytes)
            self._check_claim(name, n)
        else:
            rows_per_chunk = ds.chunks[0]
            chunk_bytes = rows_per_chunk * row_bytes
            if chunk_bytes > MAX_CHUNK_BYTES:
                self._fail(f"the file is damaged or was not written by Palpation Console: /{name} is stored in "
                           f"chunks of {chunk_bytes / 2**20:,.0f} MB (at most {MAX_CHUNK_BYTES // 2**20} MB expected)")
            largest = chunk_bytes * _CHUNK_SLACK + _CHUNK_OVERHEAD_BYTES
            limit = ROW_BOUNDS[name][0]
            # which chunks of the declared extent lie wholly in the file (no more than MAX_CHUNKS can all be
            # there), and a slot after them that stays empty
            present = np.zeros(min(-(-declared // rows_per_chunk), MAX_CHUNKS) + 1, bool)
            chunks = claimed = oversized = 0

            def visit(chunk) -> str | None:
                nonlocal chunks, claimed, oversized
                chunks += 1
                start = chunk.chunk_offset[0]
                claimed += max(0, min(rows_per_chunk, declared - start))
                if chunks > MAX_CHUNKS or claimed > limit:
                    return "refused"  # below; the rest of the index need not be read
                if chunk.size > largest:
                    oversized = max(oversized, chunk.size)
                elif start // rows_per_chunk < len(present) - 1 and chunk.byte_offset + chunk.size <= self._file_bytes:
                    present[start // rows_per_chunk] = True
                return None

            try:
                ds.id.chunk_iter(visit)
            except _READ_ERRORS:
                where = "lies in the part of the file that is missing" if self._padded else "is damaged"
                self.warnings.append(f"/{name}: the index of its rows {where}, so none of them could be read")
                return 0
            if chunks > MAX_CHUNKS:
                self._fail(f"the file is damaged or was not written by Palpation Console: /{name} is stored in more "
                           f"than {MAX_CHUNKS:,} chunks (a session's largest table has about 225,000)")
            self._check_claim(name, claimed)
            if oversized:
                self._fail(f"the file is damaged: a chunk of /{name} claims {oversized:,} bytes, more than its "
                           f"{chunk_bytes:,} bytes of rows")
            n = min(declared, int(np.argmin(present)) * rows_per_chunk)
        if n < declared and name != "stream/overview":  # the overview is recomputed from the ticks
            self.warnings.append(f"/{name}: {declared - n:,} of its {declared:,} rows are not in the file (never "
                                 "written, or in a part of the file that is missing) and were left out")
        return n

    def _check_claim(self, name: str, rows: int) -> None:
        """Refuses a table holding more rows than a session can (:data:`ROW_BOUNDS`)."""
        limit, what = ROW_BOUNDS[name]
        if rows > limit:
            ds = self._ds[name]
            declared = ds.shape[0]
            self._fail(f"the file is damaged or was not written by Palpation Console: /{name} claims {declared:,} rows "
                       f"({declared * ds.dtype.itemsize / 2**20:,.0f} MB), more than a session can hold ({limit:,}: "
                       f"{what})")

    def _placed_levels(self, levels: np.ndarray) -> np.ndarray:
        """The level records whose recorded position is a place on the tissue (others cannot be mapped)."""
        xy = levels["tsi_position_m"][:, :2]
        placed = np.isfinite(xy).all(axis=1) & (np.abs(xy) <= MAX_COORDINATE_M).all(axis=1)
        if placed.all():
            return levels  # not a copy of them: that would double what the levels take
        self.warnings.append(f"/levels: {int((~placed).sum())} level records with a position that is not a number "
                             f"or lies beyond {MAX_COORDINATE_M:g} m of the origin were left out")
        return levels[placed]

    def _read_numbered(self, name: str) -> np.ndarray:
        rows = _conform(self._read_rows(name, 0, self._stored[name]), TABLES[name])
        good = rows["seq"] == np.arange(1, len(rows) + 1)
        if not good.all():
            keep = int(np.argmin(good))
            self.warnings.append(f"/{name}: {len(rows) - keep} rows at the end never reached the disk and were "
                                 "left out")
            rows = rows[:keep]
        return rows

    def _read_rows(self, name: str, start: int, stop: int, fields: list[str] | None = None) -> np.ndarray:
        ds = self._ds[name]
        stored = fields
        if any(f not in ds.dtype.names for f in (fields or TABLES[name].names)):
            stored = [f for f in (fields or TABLES[name].names) if f in ds.dtype.names]
        try:
            rows = _read_in_pieces(ds, start, stop, stored)
        except _READ_ERRORS as err:
            self._fail(f"{self._damage}: HDF5 could not read rows {start}-{stop} of /{name} ({_first_line(err)})")
        if stored is not fields:  # an older file: give its rows the columns added since, as NaN
            wanted = TABLES[name] if not fields else np.dtype([(f, TABLES[name][f]) for f in fields])
            rows = _conform(rows, wanted)
        return rows

    def _valid_stream_length(self, name: str) -> int:
        """Rows up to the last one that reached the disk (later ones read as zeros or fail to read)."""
        ds = self._ds[name]
        n = self._stored[name]
        window = ds.chunks[0] if ds.chunks else 1024
        for _ in range(_TAIL_WINDOWS):
            if n == 0:
                break
            start = max(0, n - window)
            try:
                block = _read_in_pieces(ds, start, n)
            except _READ_ERRORS:
                n = start
                continue
            written = block.view(np.uint8).reshape(len(block), -1).any(axis=1)
            if written.any():
                n = start + int(np.flatnonzero(written)[-1]) + 1
                break
            n = start
        if n < self._stored[name]:
            self.warnings.append(f"/{name}: the last {self._stored[name] - n} rows never reached the disk and were "
                                 "left out")
        return n

    # ---- metadata helpers --------------------------------------------------------------------------------

    @property
    def pitch_m(self) -> float:
        return float(self.calibration["pitch_m"])

    @property
    def element_area_m2(self) -> float:
        value = self.calibration.get("element_area_m2")
        return float(value) if isinstance(value, (int, float)) and value > 0 else self.pitch_m**2

    @property
    def min_indentation_m(self) -> float:
        """The recording's contact.min_indentation_m (Eq. 1 is not evaluated below it)."""
        contact = _table(_table(self.config, "control"), "contact")
        value = contact.get("min_indentation_m")
        return float(value) if isinstance(value, (int, float)) and value > 0 else 0.2e-3

    @property
    def tissue_extent_m(self) -> tuple[float, float, float, float] | None:
        """(x_min, x_max, y_min, y_max) of the tissue in the tissue frame, where the file records it (a
        simulated phantom's footprint); None otherwise."""
        table = _table(self.phantom, "phantom") if self.phantom else {}
        size = [table.get(key) for key in ("length_m", "width_m")]
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < math.inf for v in size):
            return (0.0, float(size[0]), 0.0, float(size[1]))
        return None

    @property
    def phantom_name(self) -> str:
        if self.phantom:
            return str(_table(self.phantom, "phantom").get("name", ""))
        return str(self.rig.get("phantom", ""))

    # ---- regions and events ------------------------------------------------------------------------------

    def regions(self) -> list[RegionEntry]:
        levels = self.levels
        outcomes: dict[int, str] = {}
        for row in self.events:
            kind = row["kind"]
            if kind == EventKind.REGION_DONE.encode():
                outcomes[int(row["region"])] = "done"
            elif kind == EventKind.REGION_ABORTED.encode():
                outcomes[int(row["region"])] = "aborted"
        entries: list[RegionEntry] = []
        start = 0
        for i in range(1, len(levels) + 1):
            if i == len(levels) or levels["region"][i] != levels["region"][start]:
                rows = tuple(range(start, i))
                pos = levels["tsi_position_m"][start:i]
                region = int(levels["region"][start])
                entries.append(RegionEntry(region, rows, (float(pos[:, 0].mean()), float(pos[:, 1].mean())),
                                           outcomes.get(region, "incomplete")))
                start = i
        return entries

    def event_dicts(self) -> list[dict[str, Any]]:
        """The events as plain dicts (text decoded, NaN values as None)."""
        out = []
        for row in self.events:
            value = float(row["value"])
            out.append({"t_s": float(row["t_s"]), "kind": _as_str(row["kind"]), "region": int(row["region"]),
                        "level": int(row["level"]), "code": int(row["code"]),
                        "value": value if math.isfinite(value) else None, "text": _as_str(row["text"])})
        return out

    # ---- the time base ---------------------------------------------------------------------------------------

    @property
    def clock_note(self) -> str:
        """One line on where the session's UTC comes from when the file stores no pairs of clocks; '' when
        it does."""
        if len(self.clock):
            return ""
        stored = (f"its format (version {self.format_version}) predates them"
                  if self.format_version < ADDED_TABLES["clock"] else "none reached the file")
        return (f"the session stores no pairs of its loop clock and UTC ({stored}): UTC is taken as created_utc "
                f"({self.created_utc}) at the first tick, good to about a second")

    def utc_ns(self, t_s) -> np.ndarray:
        """UTC, in ns since the epoch (int64), at loop times ``t_s``: see :class:`ClockMap`. A file without
        pairs (:attr:`clock_note`) is taken to have begun at its created_utc. Raises SessionFileError if it has
        neither."""
        if self._clock_map is None:
            if len(self.clock):
                self._clock_map = ClockMap(self.clock["t_s"], self.clock["utc_ns"])
            else:
                try:
                    created = datetime.fromisoformat(self.created_utc)
                except ValueError:
                    raise SessionFileError(self.path, f"the session stores no pairs of its loop clock and UTC, and "
                                                      f"its created_utc {self.created_utc!r} is not a time: its UTC "
                                                      f"is unknown") from None
                utc = round(created.timestamp() * 1e6) * 1000  # created_utc holds milliseconds: exact in us
                first = self.tick_rows(0, 1, ["t_s"])["t_s"]
                self._clock_map = ClockMap(first[:1] if len(first) else np.zeros(1), np.array([utc], np.int64))
        try:
            return self._clock_map(t_s)
        except ValueError as err:
            raise SessionFileError(self.path, f"the file is damaged: {err}") from None

    # ---- streams -----------------------------------------------------------------------------------------

    def time_span_s(self) -> tuple[float, float]:
        """Loop time of the first and last tick row (0, 0 for a file without ticks)."""
        ov = self.overview()
        if not len(ov):
            return (0.0, 0.0)
        return (float(ov["t_start_s"][0]), float(ov["t_end_s"][-1]))

    def overview(self) -> np.ndarray:
        """OVERVIEW_DTYPE rows covering every valid tick row (buckets the writer never wrote are computed)."""
        if self._overview is None:
            stored = _conform(self._read_rows("stream/overview", 0, self._stored["stream/overview"]),
                              OVERVIEW_DTYPE)
            expected = np.arange(len(stored)) * OVERVIEW_BUCKET_ROWS
            good = (stored["row_start"] == expected) & (stored["n_rows"] > 0)
            good &= stored["row_start"] + stored["n_rows"] <= self.n_ticks
            keep = len(stored) if good.all() else int(np.argmin(good))
            stored = stored[:keep]
            done = int(stored["row_start"][-1] + stored["n_rows"][-1]) if keep else 0
            pieces = [stored]
            step = OVERVIEW_BUCKET_ROWS * 100
            while done < self.n_ticks:
                stop = min(self.n_ticks, done + step)
                ticks = self._read_rows("stream/ticks", done, stop)
                full = Overview.buckets(ticks, done, OVERVIEW_BUCKET_ROWS)
                used = len(full) * OVERVIEW_BUCKET_ROWS
                pieces.append(full)
                if used < len(ticks):
                    pieces.append(Overview.buckets(ticks[used:], done + used, len(ticks) - used))
                done = stop
            self._overview = np.concatenate(pieces) if len(pieces) > 1 else stored
        return self._overview

    def tick_rows(self, start: int, stop: int, fields: list[str] | None = None) -> np.ndarray:
        start, stop = max(0, int(start)), min(self.n_ticks, int(stop))
        if stop <= start:
            return np.empty(0, TICK_DTYPE if not fields else [(f, TICK_DTYPE[f]) for f in fields])
        return self._read_rows("stream/ticks", start, stop, fields)

    def ticks_between(self, t0_s: float, t1_s: float, fields: list[str] | None = None) -> np.ndarray:
        """Tick rows with t0_s <= t_s <= t1_s at full resolution (``fields``: only those columns)."""
        ov = self.overview()
        if not len(ov) or t1_s < t0_s:
            return self.tick_rows(0, 0, fields)
        first = int(np.searchsorted(ov["t_end_s"], t0_s, side="left"))
        last = int(np.searchsorted(ov["t_start_s"], t1_s, side="right")) - 1
        if first >= len(ov) or last < first:
            return self.tick_rows(0, 0, fields)
        start = int(ov["row_start"][first])
        stop = int(ov["row_start"][last] + ov["n_rows"][last])
        want = list(dict.fromkeys(["t_s", *(fields or [])])) if fields else None
        rows = self.tick_rows(start, stop, want)
        inside = (rows["t_s"] >= t0_s) & (rows["t_s"] <= t1_s)
        rows = rows[inside]
        if fields and "t_s" not in fields:
            rows = _conform(rows, np.dtype([(f, TICK_DTYPE[f]) for f in fields]))
        return rows

    def frames(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        stop = self.n_frames if stop is None else min(int(stop), self.n_frames)
        return self._read_rows("stream/frames", max(0, int(start)), stop)

    # ---- lifetime ----------------------------------------------------------------------------------------

    def close(self) -> None:
        self._close_file()

    def _close_file(self) -> None:
        if self._f.id.valid:
            self._f.close()
        if self._padded is not None:
            self._padded.close()

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"Session({str(self.path)!r}, {len(self.levels)} levels, {self.n_ticks} ticks, "
                f"{'recovered' if self.recovered else 'clean'})")


class ClockMap:
    """Loop time to UTC through pairs of readings of both clocks: linear between neighbouring pairs, and
    beyond the first and the last pair at the loop clock's rate (one second of UTC a second).

    Monotonic however the pairs came: they are taken in order of loop time (a repeated loop time keeps its
    first pairing), and a wall clock stepped back between two pairs (NTP correcting it) gives a stretch over
    which UTC stands still, never one in which it runs backwards."""

    def __init__(self, t_s: np.ndarray, utc_ns: np.ndarray):
        t_s, utc_ns = np.asarray(t_s, np.float64), np.asarray(utc_ns, np.int64)
        usable = np.isfinite(t_s)
        if not usable.any():
            raise ValueError("a clock map needs at least one pair with a finite loop time")
        t_s, utc_ns = t_s[usable], utc_ns[usable]
        order = np.argsort(t_s, kind="stable")
        t_s, utc_ns = t_s[order], utc_ns[order]
        first = np.concatenate([[True], np.diff(t_s) > 0])
        t_s, utc_ns = t_s[first], np.maximum.accumulate(utc_ns[first])
        self.t_s = t_s
        # UTC relative to the first pair, as float64: exact to well under a nanosecond over 8 hours, where
        # nanoseconds since 1970 in a float64 would be rounded to 256 ns
        self._base = int(utc_ns[0])
        self._rel = (utc_ns - utc_ns[0]).astype(np.float64)

    def __call__(self, t_s) -> np.ndarray:
        t = np.asarray(t_s, np.float64)
        if not np.isfinite(t).all():
            raise ValueError("loop times must be finite to be mapped to UTC")
        rel = np.interp(t, self.t_s, self._rel)
        rel = np.where(t < self.t_s[0], self._rel[0] + (t - self.t_s[0]) * 1e9, rel)
        rel = np.where(t > self.t_s[-1], self._rel[-1] + (t - self.t_s[-1]) * 1e9, rel)
        return self._base + np.round(rel).astype(np.int64)


def open_session(path: str | Path) -> Session:
    """Open and validate a session file; raises :class:`SessionFileError` naming the problem."""
    path = Path(path)
    fd, size = _open_regular_file(path)
    try:
        return _open_hdf5(path, fd, size)
    finally:
        os.close(fd)  # HDF5 holds a descriptor of its own


def _open_regular_file(path: Path) -> tuple[int, int]:
    """A read-only descriptor of ``path`` and its size, if it is a regular file; else SessionFileError.

    open() of a FIFO waits for a writer (forever, if none comes) and a device such as /dev/zero never ends,
    so the path is opened without blocking and judged by what the descriptor is, not by what the path was a
    moment before: it could be swapped in between."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise SessionFileError(path, "no such file") from None
    except OSError as err:
        raise SessionFileError(path, f"the file cannot be read ({err.strerror or err})") from None
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode):
        os.close(fd)
        raise SessionFileError(path, f"this is {_not_a_file(info.st_mode)}, not a session file")
    return fd, info.st_size


def _not_a_file(mode: int) -> str:
    """What a path that is not a regular file is, in words."""
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a named pipe (FIFO)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return "not a regular file"


def _hdf5_name(fd: int, path: Path) -> str:
    """The name HDF5 is to open: on Linux, /proc/self/fd/<fd>, which opens the very file ``fd`` is, so that
    nothing swapped in at ``path`` after it was checked (a FIFO, whose open would block) is opened instead;
    elsewhere the path itself."""
    own = f"/proc/self/fd/{fd}"
    return own if os.path.exists(own) else str(path)


def _open_hdf5(path: Path, fd: int, size: int) -> Session:
    if size == 0:
        raise SessionFileError(path, "the file is empty (0 bytes): the recording never started writing")
    try:
        head = os.read(fd, 8)
    except OSError as err:
        raise SessionFileError(path, f"the file cannot be read ({err.strerror or err})") from None
    name = _hdf5_name(fd, path)
    if not _looks_like_hdf5(name, head):
        raise SessionFileError(path, "this is not a session file: it is not an HDF5 file at all "
                                     f"(it starts with {head[:8]!r})")
    try:
        f = h5py.File(name, "r")
        return Session(path, f, size, recovered=False, note="")
    except SessionFileError:
        raise
    except _READ_ERRORS as plain_err:
        stored_eof = _stored_eof(plain_err)
        if stored_eof is not None:
            return _open_truncated(path, name, size, stored_eof, plain_err)
        # A session the console was killed while recording carries HDF5's "open for writing" mark;
        # SWMR-read mode opens it as it is, without clearing the mark (the reviewer never writes).
        try:
            f = _open_swmr_read(name)
        except _READ_ERRORS:
            raise SessionFileError(path, _explain_open_error(plain_err)) from None
        if f is None:
            raise SessionFileError(path, _explain_open_error(plain_err)
                                   + " (this installation's HDF5 cannot be told to give up on damaged data quickly, "
                                     "so the file is not opened in recovery mode)") from None
        note = ("The recording did not end cleanly (the console stopped while recording, or the file is "
                "still being written); showing everything that reached the disk.")
        return Session(path, f, size, recovered=True, note=note)


# HDF5 refuses a file shorter than the end its superblock records, and has no option to read it anyway.
_TRUNCATED = re.compile(r"truncated file: eof = (\d+).*stored_eof = (\d+)")
_MAX_FILE_BYTES = 2**50


def _stored_eof(err: BaseException) -> int | None:
    m = _TRUNCATED.search(str(err))
    return int(m.group(2)) if m else None


def _open_truncated(path: Path, name: str, size: int, stored_eof: int, err: BaseException) -> Session:
    """Open a file cut short as though its missing tail were zeros: HDF5 then reads every object that lies
    wholly in the part that is there, and fails (checksums) on the rest, which the session leaves out."""
    damage = _explain_open_error(err)
    if not size < stored_eof <= _MAX_FILE_BYTES:
        raise SessionFileError(path, damage) from None
    padded = _PaddedFile(name, stored_eof)
    try:
        # Not SWMR (only POSIX files can be): a file-object driver does not check the mark a killed writer
        # leaves, and a reader that never writes has no use for it.
        f = h5py.File(padded, "r")
    except _READ_ERRORS:
        padded.close()
        raise SessionFileError(path, damage + " and too little of it is left to open") from None
    lost = (stored_eof - size) / stored_eof
    note = f"{damage}; {lost:.1%} of it is missing, showing what could be read from the rest"
    return Session(path, f, size, recovered=True, note=note[0].upper() + note[1:], damage=damage, padded=padded)


class _PaddedFile(io.RawIOBase):
    """A read-only view of a file extended with zeros to ``length`` bytes, for h5py's file-object driver."""

    def __init__(self, name: str, length: int):
        super().__init__()
        self._file = open(name, "rb")  # noqa: SIM115 - closed by close(), with the session
        self._real = os.fstat(self._file.fileno()).st_size
        self._length = length
        self._pos = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self._length}[whence]
        self._pos = max(0, base + offset)
        return self._pos

    def tell(self) -> int:
        return self._pos

    def readinto(self, buffer) -> int:
        view = memoryview(buffer).cast("B")
        want = max(0, min(len(view), self._length - self._pos))
        got = 0
        if self._pos < self._real:
            self._file.seek(self._pos)
            got = self._file.readinto(view[:min(want, self._real - self._pos)]) or 0
        view[got:want] = bytes(want - got)
        self._pos += want
        return want

    def close(self) -> None:
        self._file.close()
        super().close()


# A SWMR reader retries a metadata block whose checksum fails, sleeping 1 ns, 2 ns, 4 ns, ... between
# attempts; HDF5's default of 100 attempts makes a damaged file hang the reader practically forever.
# 20 attempts still ride out a block the writer is rewriting (about 1 ms of retries), then fail.
SWMR_READ_ATTEMPTS = 20


@functools.cache
def _hdf5_library() -> ctypes.CDLL | None:
    """The HDF5 library h5py runs on, to set the one file-access property h5py does not wrap."""
    candidates: list[str] = []
    maps = Path("/proc/self/maps")
    if maps.exists():  # Linux: exactly the library loaded in this process
        for line in maps.read_text().splitlines():
            name = line.rsplit(" ", 1)[-1]
            if "libhdf5" in Path(name).name and "_hl" not in Path(name).name:
                candidates.append(name)
    package = Path(h5py.__file__).parent
    for pattern in ("../h5py.libs/libhdf5*", ".dylibs/libhdf5*", "hdf5*.dll"):
        candidates += [str(p) for p in sorted(package.glob(pattern)) if "_hl" not in p.name]
    for candidate in dict.fromkeys(candidates):
        try:
            lib = ctypes.CDLL(candidate)
            setter = lib.H5Pset_metadata_read_attempts
        except (OSError, AttributeError):
            continue
        setter.argtypes = [ctypes.c_int64, ctypes.c_uint]
        setter.restype = ctypes.c_int
        return lib
    return None


def _open_swmr_read(name: str) -> h5py.File | None:
    lib = _hdf5_library()
    if lib is None:
        return None
    fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    if lib.H5Pset_metadata_read_attempts(fapl.id, SWMR_READ_ATTEMPTS) < 0:
        return None
    fid = h5py.h5f.open(os.fsencode(name), h5py.h5f.ACC_RDONLY | h5py.h5f.ACC_SWMR_READ, fapl=fapl)
    return h5py.File(fid)


def _looks_like_hdf5(name: str, head: bytes) -> bool:
    if head == b"\x89HDF\r\n\x1a\n":
        return True
    try:
        return bool(h5py.is_hdf5(name))  # the signature may also sit at 512, 1024, ... bytes
    except OSError:
        return False


def _read_in_pieces(ds: h5py.Dataset, start: int, stop: int, fields: list[str] | None = None) -> np.ndarray:
    """Rows ``start`` to ``stop`` of ``ds`` (only ``fields``, if given), asking HDF5 for at most
    MAX_READ_BYTES of rows at a time."""
    source = ds.fields(fields) if fields else ds
    dtype = np.dtype([(f, ds.dtype.fields[f][0]) for f in fields]) if fields else ds.dtype
    rows = np.empty(max(0, stop - start), dtype)
    step = max(1, MAX_READ_BYTES // ds.dtype.itemsize)
    for first in range(start, stop, step):
        last = min(stop, first + step)
        rows[first - start:last - start] = source[first:last]
    return rows


def _is_coordinate(value: Any) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value) and abs(value) <= MAX_COORDINATE_M


def _table(mapping: dict, key: str) -> dict:
    value = mapping.get(key)
    return value if isinstance(value, dict) else {}


def _as_str(value: Any) -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.ndarray) and value.shape == ():
        return _as_str(value[()])
    return str(value)


def _dtype_problem(actual: np.dtype, expected: np.dtype, optional: set[str] = frozenset()) -> str | None:
    """None if every expected field (but those ``optional``) is present with a compatible type and shape."""
    if actual.names is None:
        return "not a table of named columns"
    missing = [name for name in expected.names if name not in actual.names and name not in optional]
    if missing:
        return f"missing column(s) {', '.join(missing)}"
    for name in expected.names:
        if name not in actual.names:
            continue
        a, e = actual.fields[name][0], expected.fields[name][0]
        if a.shape != e.shape or a.base.kind != e.base.kind:
            return f"column {name} is {a}, expected {e}"
    return None


def _conform(rows: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """``rows`` with ``dtype``'s columns; a column an older file lacks is NaN, or -1 for an integer column."""
    if rows.dtype == dtype:
        return rows
    out = np.empty(len(rows), dtype)
    for name in dtype.names:
        if name in rows.dtype.names:
            out[name] = rows[name]
        else:
            out[name] = -1 if dtype[name].base.kind in "iu" else np.nan
    return out
