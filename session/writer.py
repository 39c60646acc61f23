"""Session recording: one self-describing HDF5 file per session (layout: :mod:`session.format`), written by a
thread of its own.

Crash safety. The file is written in HDF5's single-writer/multiple-reader (SWMR) mode: the layout above is
created first, then SWMR is switched on, after which HDF5 orders its metadata writes so that the file on
disk is consistent at every instant (that is what lets a reader follow a live file; it also means a file
left by a killed process opens). The writer flushes every ``flush_interval_s``, so a ``kill -9`` loses at
most that much plus what was still queued. Such a file carries HDF5's "open for writing" mark, which
readers without SWMR refuse: :mod:`session.reader` opens it in SWMR-read mode, without modifying it.
Metadata is checksummed throughout and there is no variable-length data (whose unchecked global heap can
send HDF5 into an endless loop), so a damaged file gives read errors, not hangs.

Full disk. After every flush the writer checks the free space on the file's disk; below ``min_free_bytes``
it stops recording cleanly (the file is closed and complete up to that point) and reports why. A write
that fails all the same (another program filled the disk, a quota, a file-size limit) also stops the
recording with a message, leaving the file as a kill at that instant would (HDF5 is cut off from it
before closing); the reader trims the tail that never landed. The chunk still filling up is rewritten at
every flush, so such a failure can also take the rows of that chunk with it: levels therefore get a chunk
each. Either way the producer side (:meth:`SessionRecorder.add_ticks` and friends) never blocks and never
raises, so the control side carries on regardless.
"""

from __future__ import annotations

import atexit
import errno as errno_codes
import json
import logging
import os
import queue
import re
import shutil
import threading
import time
import uuid as uuid_module
import weakref
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from control.telemetry import FRAME_DTYPE, TICK_DTYPE
from session.format import (
    CHUNK_ROWS,
    CLOCK_DTYPE,
    CLOCK_NOTES,
    EVENT_CODES,
    EVENT_DTYPE,
    FORMAT_NAME,
    FORMAT_VERSION,
    LEVEL_DTYPE,
    OVERVIEW_BUCKET_ROWS,
    OVERVIEW_DTYPE,
    TICK_CODES,
    TICK_NOTES,
    EventKind,
    Overview,
    event_row,
    rows_for_event,
)
from session.info import SessionInfo, software_version

log = logging.getLogger(__name__)


class RecorderError(RuntimeError):
    """The session file could not be created (no such folder, no permission, the file exists...)."""


# ---- the writer ----------------------------------------------------------------------------------------


class _Appender:
    """One resizable dataset and the rows waiting to go into it."""

    def __init__(self, ds: h5py.Dataset, numbered: bool = False):
        self.ds = ds
        self.n = ds.shape[0]
        self.numbered = numbered
        self.pending: list[np.ndarray] = []
        self.pending_rows = 0

    def add(self, rows: np.ndarray) -> None:
        self.pending.append(rows)
        self.pending_rows += len(rows)

    def write(self) -> int:
        if not self.pending_rows:
            return 0
        block = self.pending[0] if len(self.pending) == 1 else np.concatenate(self.pending)
        n0 = self.n
        if self.numbered:
            block["seq"] = np.arange(n0 + 1, n0 + 1 + len(block))
        self.ds.resize((n0 + len(block),))
        self.ds[n0:] = block
        # cleared only once written: after a failed write the rows still pending are the ones dropped
        self.pending.clear()
        self.pending_rows = 0
        self.n = n0 + len(block)
        return len(block)


@dataclass
class RecorderStatus:
    path: Path
    recording: bool  # accepting and writing data
    problem: str | None  # why recording stopped early (full disk, write error); None if it did not
    ticks_written: int
    frames_written: int
    levels_written: int
    events_written: int
    rows_lost: int  # tick rows missing from the stream (lost before the recorder got them)
    rows_dropped: int  # rows the recorder was given but did not write (stopped, or its queue overflowed)
    bytes_on_disk: int


_STOP = object()


class _Flush:
    def __init__(self):
        self.done = threading.Event()


_ERRNO_IN_MESSAGE = re.compile(r"errno = (\d+)")


def _describe_write_error(err: BaseException, path: Path) -> str:
    code = getattr(err, "errno", None)
    if not isinstance(code, int):
        match = _ERRNO_IN_MESSAGE.search(str(err))
        code = int(match.group(1)) if match else None
    if code == errno_codes.ENOSPC:
        why = "the disk is full"
    elif code == errno_codes.EDQUOT:
        why = "the disk quota is exceeded"
    elif code == errno_codes.EFBIG:
        why = "the file reached the largest size this system allows"
    elif code == errno_codes.EIO:
        why = "the disk reported an input/output error"
    else:
        first_line = str(err).splitlines()[0] if str(err) else type(err).__name__
        why = f"writing failed ({first_line})"
    return (f"Recording stopped: {why} while writing {path}. The session up to this point is kept in that file; "
            "the controller is unaffected.")


class SessionRecorder:
    """Writes one session to ``path`` from a thread of its own; feed it from any thread.

    The producer calls (:meth:`add_ticks`, :meth:`add_frames`, :meth:`add_events`, :meth:`add_note`) only
    queue their data: they never block on the disk and never raise for a recording that has stopped.
    Call :meth:`close` at the end of the session (it drains the queue and closes the file cleanly).

    ``on_problem(message)`` is called once, from the writer thread, if recording stops early; the same
    message stays in :attr:`problem`.
    """

    def __init__(self, path: str | Path, info: SessionInfo, *, flush_interval_s: float = 0.25,
                 block_rows: int = 512, min_free_bytes: int = 200 * 2**20, max_queued_bytes: int = 256 * 2**20,
                 compression: str | None = "gzip", on_problem: Callable[[str], None] | None = None):
        if not 0 < flush_interval_s <= 1.0:
            raise ValueError(f"flush_interval_s must be within (0, 1] s (a crash may lose that much), "
                             f"got {flush_interval_s!r}")
        if block_rows < 1:
            raise ValueError(f"block_rows must be >= 1, got {block_rows!r}")
        if compression not in (None, "lzf", "gzip"):
            raise ValueError(f"compression must be None, 'lzf' or 'gzip', got {compression!r}")
        self.path = Path(path)
        self.info = info
        self.uuid = str(uuid_module.uuid4())
        self.flush_interval_s = float(flush_interval_s)
        self.block_rows = int(block_rows)
        self.min_free_bytes = int(min_free_bytes)
        self.max_queued_bytes = int(max_queued_bytes)
        self._on_problem = on_problem
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._queued_bytes = 0
        self._count_lock = threading.Lock()
        self._accepting = True
        self._closed = False
        self.problem: str | None = None
        self.rows_dropped = 0
        self.rows_lost = 0
        self._last_tick: int | None = None
        self._overview = Overview()
        self._file = self._create(compression)
        # A daemon, so a recorder nobody closed cannot keep the process from exiting; _close_all still
        # writes it out at exit.
        self._thread = threading.Thread(target=self._run, name=f"session-writer {self.path.name}", daemon=True)
        self._thread.start()
        _OPEN.add(self)

    # ---- creation ------------------------------------------------------------------------------------

    def _create(self, compression: str | None) -> h5py.File:
        folder = self.path.parent
        try:
            folder.mkdir(parents=True, exist_ok=True)
            free = shutil.disk_usage(folder).free
        except OSError as err:
            raise RecorderError(f"cannot create the session folder {folder}: {err.strerror or err}") from None
        if free < self.min_free_bytes:
            raise RecorderError(f"cannot record to {folder}: only {free / 2**20:.0f} MB free on its disk; the "
                                f"recorder needs at least {self.min_free_bytes / 2**20:.0f} MB")
        try:
            # the oldest file format that keeps SWMR (crash safety): the HDF5 1.10 tools distributions ship
            # read it, where "latest" (HDF5 2.0's) gave h5ls *ERROR* for every dataset
            f = h5py.File(self.path, "w-", libver=("v110", "v110"), rdcc_nbytes=8 * 2**20)
        except FileExistsError:
            raise RecorderError(f"cannot record to {self.path}: the file already exists") from None
        except OSError as err:
            raise RecorderError(f"cannot create the session file {self.path}: {err}") from None
        try:
            self._write_layout(f, compression)
            f.swmr_mode = True
            f.flush()
        except Exception as err:
            f.close()
            self.path.unlink(missing_ok=True)
            raise RecorderError(f"cannot set up the session file {self.path}: {err}") from None
        return f

    def _write_layout(self, f: h5py.File, compression: str | None) -> None:
        info = self.info
        f.attrs["format"] = _fixed(FORMAT_NAME)
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["uuid"] = _fixed(self.uuid)
        f.attrs["created_utc"] = _fixed(datetime.now(timezone.utc).isoformat(timespec="milliseconds"))
        f.attrs["software"] = _fixed("palpation-console")
        f.attrs["software_version"] = _fixed(info.software_version or software_version())
        f.attrs["simulated"] = bool(info.simulated)
        meta = f.create_group("meta")
        for key, value in (("config_json", info.config), ("calibration_json", info.calibration),
                           ("rig_json", info.rig), ("phantom_json", info.phantom),
                           ("ground_truth_json", info.ground_truth)):
            meta.attrs[key] = _fixed(json.dumps(value, sort_keys=True, allow_nan=True, default=_json_default))
        # Fletcher-32 checksums every chunk, so a damaged chunk is an error on reading, never garbage handed
        # to the decompressor. Deflate at level 1 after byte-shuffling: 190-255x real time and ~200 MB per
        # hour on the 2-vCPU machine (LZF: ~300x, 220 MB/h, but outside h5py few HDF5 tools read it;
        # no compression: ~390x, 1 GB/h). See bench/sessions_bench.py.
        filters: dict[str, Any] = {"fletcher32": True}
        if compression is not None:
            filters.update(compression=compression, shuffle=True)
            if compression == "gzip":
                filters["compression_opts"] = 1

        def table(parent: h5py.Group, name: str, dtype: np.dtype, chunk_key: str, description: str):
            ds = parent.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype,
                                       chunks=(CHUNK_ROWS[chunk_key],), **filters)
            ds.attrs["description"] = _fixed(description)
            return ds

        stream = f.create_group("stream")
        self._ticks = _Appender(table(stream, "ticks", TICK_DTYPE, "ticks",
                                      "one row per control period (control.telemetry.TICK_DTYPE)"))
        self._frames = _Appender(table(stream, "frames", FRAME_DTYPE, "frames",
                                       "one row per tactile frame (control.telemetry.FRAME_DTYPE)"))
        self._overview_ds = _Appender(table(stream, "overview", OVERVIEW_DTYPE, "overview",
                                            f"min/max per {OVERVIEW_BUCKET_ROWS} tick rows, for timelines"))
        self._overview_ds.ds.attrs["bucket_rows"] = OVERVIEW_BUCKET_ROWS
        self._levels = _Appender(table(f, "levels", LEVEL_DTYPE, "levels",
                                       "one row per recorded force level (control.messages.LevelRecord)"),
                                 numbered=True)
        self._events = _Appender(table(f, "events", EVENT_DTYPE, "events",
                                       "one row per event; see session.format.EventKind"), numbered=True)
        self._clock = _Appender(table(f, "clock", CLOCK_DTYPE, "clock",
                                      "one row per reading of the loop's clock and UTC together"))
        numbering = {key: TICK_NOTES[key] for key in ("region", "level")}
        for ds, codes, notes in ((self._ticks.ds, TICK_CODES, TICK_NOTES), (self._levels.ds, None, numbering),
                                 (self._events.ds, EVENT_CODES, numbering), (self._clock.ds, None, CLOCK_NOTES)):
            if codes is not None:
                ds.attrs["codes_json"] = _fixed(json.dumps(codes, sort_keys=True))
            ds.attrs["notes_json"] = _fixed(json.dumps(notes, sort_keys=True))

    # ---- producer side (any thread) ------------------------------------------------------------------

    def _put(self, item, nbytes: int, nrows: int) -> None:
        with self._count_lock:
            if not self._accepting or self._queued_bytes + nbytes > self.max_queued_bytes:
                self.rows_dropped += nrows
                return
            self._queued_bytes += nbytes
        self._queue.put((item, nbytes))

    def add_ticks(self, rows: np.ndarray) -> None:
        """TICK_DTYPE rows, oldest first, as read from the controller's ring (copied: the caller keeps them)."""
        if len(rows):
            rows = _own_copy(rows, TICK_DTYPE, "add_ticks")
            self._put(("ticks", rows), rows.nbytes, len(rows))

    def add_frames(self, rows: np.ndarray) -> None:
        """FRAME_DTYPE rows, oldest first."""
        if len(rows):
            rows = _own_copy(rows, FRAME_DTYPE, "add_frames")
            self._put(("frames", rows), rows.nbytes, len(rows))

    def add_events(self, events: Iterable) -> None:
        """control.messages events, in order; objects of other types (health reports...) are ignored."""
        events = list(events)
        if events:
            self._put(("events", events), 256 * len(events), len(events))

    def add_clock(self, t_s: float, utc_ns: int) -> None:
        """The loop's clock read ``t_s`` at UTC ``utc_ns`` (ns since the epoch): what lines the session up with
        other recordings. Give one when the session begins, about every CLOCK_INTERVAL_S of loop time, and one
        just before :meth:`close`."""
        self._put(("clock", (float(t_s), int(utc_ns))), 16, 1)

    def add_note(self, text: str, t_s: float) -> None:
        """An operator's note at loop time ``t_s``."""
        self._put(("note", (float(t_s), str(text))), 256, 1)

    def add_controller_lost(self, how: str) -> None:
        """The controller stopped on its own (``how``: its exit, as the bridge saw it), after the rows queued."""
        self._put(("controller_lost", str(how)), 256, 1)

    # ---- control ---------------------------------------------------------------------------------------

    @property
    def recording(self) -> bool:
        return self._accepting

    def flush(self, timeout_s: float = 30.0) -> bool:
        """Block until everything queued so far is on disk; False on time-out or if recording has stopped."""
        if not self._thread.is_alive():
            return False
        marker = _Flush()
        self._queue.put((marker, 0))
        return marker.done.wait(timeout_s) and self.problem is None

    def close(self, timeout_s: float = 60.0) -> RecorderStatus:
        """Write what is queued, mark the file closed and close it; safe to call twice."""
        if not self._closed:
            self._closed = True
            _OPEN.discard(self)
            with self._count_lock:
                self._accepting = False
            self._queue.put((_STOP, 0))
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.error("the session writer did not finish within %.0f s; %s may lack its last rows",
                      timeout_s, self.path)
        return self.status()

    def status(self) -> RecorderStatus:
        try:
            size = self.path.stat().st_size
        except OSError:
            size = 0
        return RecorderStatus(
            path=self.path, recording=self._accepting, problem=self.problem, ticks_written=self._ticks.n,
            frames_written=self._frames.n, levels_written=self._levels.n, events_written=self._events.n,
            rows_lost=self.rows_lost, rows_dropped=self.rows_dropped, bytes_on_disk=size)

    def __enter__(self) -> SessionRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- writer thread ---------------------------------------------------------------------------------

    def _run(self) -> None:
        next_flush = time.monotonic() + self.flush_interval_s
        try:
            while True:
                timeout = next_flush - time.monotonic()
                try:
                    item, nbytes = self._queue.get(timeout=max(timeout, 0.0)) if timeout > 0 else \
                        self._queue.get_nowait()
                except queue.Empty:
                    item, nbytes = None, 0
                if nbytes:
                    with self._count_lock:
                        self._queued_bytes -= nbytes
                if item is _STOP:
                    self._finish()
                    return
                if isinstance(item, _Flush):
                    self._flush()
                    stopped = self._disk_nearly_full()
                    item.done.set()
                    if stopped:
                        return
                    next_flush = time.monotonic() + self.flush_interval_s
                    continue
                if item is not None:
                    self._take(item)
                if time.monotonic() >= next_flush:
                    self._flush()
                    next_flush = time.monotonic() + self.flush_interval_s
                    if self._disk_nearly_full():
                        return
        except Exception as err:  # noqa: BLE001 - any failure stops the recording with a message, never silently
            self._fail(err)
        finally:
            self._release_waiters()

    def _take(self, item) -> None:
        kind, payload = item
        if kind == "ticks":
            self._check_gaps(payload)
            self._ticks.add(payload)
            overview = self._overview.add(payload)
            if len(overview):
                self._overview_ds.add(overview)
        elif kind == "frames":
            self._frames.add(payload)
        elif kind == "events":
            for event in payload:
                row, level = rows_for_event(event)
                if row is not None:
                    self._add_event(row)
                if level is not None:
                    self._levels.add(np.array([level], LEVEL_DTYPE))
        elif kind == "clock":
            self._clock.add(np.array([payload], CLOCK_DTYPE))
        elif kind == "note":
            t_s, text = payload
            self._add_event(event_row(t_s, EventKind.NOTE, text=text))
        elif kind == "controller_lost":
            self._add_event(event_row(self._last_time(), EventKind.CONTROLLER_LOST, text=payload))
        if self._ticks.pending_rows >= self.block_rows:
            self._ticks.write()
        if self._frames.pending_rows >= max(1, self.block_rows // 8):
            self._frames.write()

    def _add_event(self, row: tuple) -> None:
        self._events.add(np.array([row], EVENT_DTYPE))

    def _check_gaps(self, ticks: np.ndarray) -> None:
        index = ticks["tick"]
        previous = self._last_tick if self._last_tick is not None else int(index[0]) - 1
        steps = np.diff(index, prepend=previous)
        self._last_tick = int(index[-1])
        gaps = steps > 1
        if gaps.any():
            lost = int((steps[gaps] - 1).sum())
            self.rows_lost += lost
            t = float(ticks["t_s"][np.argmax(gaps)])
            self._add_event(event_row(t, EventKind.ROWS_LOST, value=float(lost), text="ticks"))
        restarts = steps <= 0
        if restarts.any():
            t = float(ticks["t_s"][np.argmax(restarts)])
            self._add_event(event_row(t, EventKind.RECORDER, text="the controller restarted: the tick counter "
                                                                  "began again from 0"))

    def _flush(self) -> None:
        for appender in (self._ticks, self._frames, self._overview_ds, self._levels, self._events, self._clock):
            appender.write()
        self._file.flush()

    def _disk_nearly_full(self) -> bool:
        try:
            free = shutil.disk_usage(self.path.parent).free
        except OSError:
            return False  # cannot tell; a write that fails is still caught
        if free >= self.min_free_bytes:
            return False
        message = (f"Recording stopped: only {free / 2**20:.0f} MB left on the disk holding {self.path} "
                   f"(the recorder keeps {self.min_free_bytes / 2**20:.0f} MB free). The session up to this "
                   "point is kept in that file; the controller is unaffected. Free some space and start a new "
                   "session to go on recording.")
        self._stop_accepting(message)
        self._add_event(event_row(self._last_time(), EventKind.RECORDER, text=message))
        self._close_file()
        self._report(message)
        return True

    def _last_time(self) -> float:
        if self._last_tick is not None and len(self._overview.tail):
            return float(self._overview.tail["t_s"][-1])
        n = self._ticks.n
        return float(self._ticks.ds[n - 1]["t_s"]) if n else 0.0

    def _finish(self) -> None:
        overview = self._overview.finish()
        if len(overview):
            self._overview_ds.add(overview)
        closed_at = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
        self._add_event(event_row(self._last_time(), EventKind.CLOSED, text=closed_at))
        self._close_file()

    def _close_file(self) -> None:
        self._flush()
        self._file.close()

    def _stop_accepting(self, message: str) -> None:
        with self._count_lock:
            self._accepting = False
        self.problem = message
        # Whatever is still queued will not be written: count it as dropped.
        while True:
            try:
                item, nbytes = self._queue.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, _Flush):
                item.done.set()
            elif item is not _STOP and item is not None:
                kind, payload = item
                # a note, a clock pair and a lost controller are one row each; the rest are blocks of rows
                self.rows_dropped += 1 if kind in ("note", "clock", "controller_lost") else len(payload)
        for appender in (self._ticks, self._frames, self._levels, self._events, self._clock):
            appender.pending.clear()
            appender.pending_rows = 0

    def _fail(self, err: BaseException) -> None:
        if isinstance(err, (OSError, RuntimeError)):
            message = _describe_write_error(err, self.path)
        else:
            message = (f"Recording stopped: the session writer failed ({type(err).__name__}: {err}). The session "
                       f"up to this point is kept in {self.path}; the controller is unaffected.")
            log.error("session writer failed", exc_info=err)
        appenders = (self._ticks, self._frames, self._overview_ds, self._levels, self._events, self._clock)
        pending = sum(a.pending_rows for a in appenders)
        self._stop_accepting(message)
        self.rows_dropped += pending
        self._detach_from_disk()
        for appender in appenders:
            appender.ds = None
        try:
            self._file.close()
        except Exception:  # noqa: BLE001 - nothing more can reach the file; the reader trims what did not land
            log.warning("closing %s after a write error failed", self.path, exc_info=True)
        self._report(message)

    def _detach_from_disk(self) -> None:
        """Point HDF5's file descriptor at the null device, so what it still writes on closing goes nowhere.

        The file then stays as the failure left it, like one whose process was killed at that instant (which
        SWMR keeps readable), and closing cannot fail: after a failed close HDF5 2.0 crashes the process
        when it exits.
        """
        try:
            fd = self._file.id.get_vfd_handle()
            null = os.open(os.devnull, os.O_RDWR)
            try:
                os.dup2(null, fd)
            finally:
                os.close(null)
        except (OSError, RuntimeError, ValueError, TypeError):
            log.warning("could not detach %s from the disk after a write error", self.path, exc_info=True)

    def _report(self, message: str) -> None:
        log.warning("%s", message)
        if self._on_problem is not None:
            try:
                self._on_problem(message)
            except Exception:  # noqa: BLE001 - a faulty callback must not take the writer down
                log.exception("on_problem callback failed")

    def _release_waiters(self) -> None:
        with self._count_lock:
            self._accepting = False
        while True:
            try:
                item, _ = self._queue.get_nowait()
            except queue.Empty:
                return
            if isinstance(item, _Flush):
                item.done.set()


_OPEN: weakref.WeakSet[SessionRecorder] = weakref.WeakSet()


@atexit.register
def _close_all() -> None:
    for recorder in list(_OPEN):
        recorder.close()


def _fixed(text: str) -> np.bytes_:
    """Text as a fixed-length UTF-8 attribute: stored in the checksummed object header, unlike
    variable-length strings, whose unchecked global heap can make a damaged file hang the reader."""
    return np.bytes_(text.encode("utf-8"))


def _own_copy(rows: np.ndarray, dtype: np.dtype, caller: str) -> np.ndarray:
    if getattr(rows, "dtype", None) != dtype:
        raise TypeError(f"{caller} takes rows of control.telemetry's dtype, got {getattr(rows, 'dtype', type(rows))}")
    return np.array(rows, copy=True).reshape(-1)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot store {type(value).__name__} in the session metadata")
