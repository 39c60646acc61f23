"""Files that would make a reader wait forever or eat the machine's memory (issue 49): a FIFO or a device for a
path, a session whose parts live in other files, tables whose chunks claim more rows than a session holds.
Each is refused in one line, opened in a child process with a time-out and a memory cap, so that a regression
fails its test instead of stalling the run or starving the machine."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from control.messages import LevelRecorded
from session import reader
from session.format import TABLES
from session.reader import open_session
from session.synthetic import frame_rows, level_record, tick_rows
from session.writer import SessionRecorder
from tests.session.test_recorder import INFO

REPO = Path(__file__).resolve().parents[2]


def run_child(kind: str, path) -> tuple[int, str, int]:
    """(exit code: 0 refused, 3 opened; what it printed; its peak memory in MiB) of
    tests/session/open_child.py on ``path``."""
    done = subprocess.run([sys.executable, "-m", "tests.session.open_child", kind, str(path)], cwd=REPO,
                          capture_output=True, text=True, timeout=20)
    assert done.returncode in (0, 3), done.stderr
    message, peak_mib = done.stdout.rstrip("\n").rsplit("\n", 1)
    return done.returncode, message, int(peak_mib)


def open_in_child(kind: str, path) -> tuple[int, str]:
    return run_child(kind, path)[:2]


def refusal(path, kind: str = "session") -> str:
    """The one line the reader refuses ``path`` with."""
    code, message = open_in_child(kind, path)
    assert code == 0 and "\n" not in message, message
    return message


def small_session(path: Path) -> Path:
    rec = SessionRecorder(path, INFO)
    rec.add_ticks(tick_rows(0, 2500))
    rec.add_frames(frame_rows(0, 250))
    rec.add_events([LevelRecorded(1.0, level_record(0, 0, 1.0, (0.01, 0.015)))])
    rec.close()
    return path


# ---- paths that are not files ------------------------------------------------------------------------


def test_a_fifo_or_a_device_is_refused_without_waiting_on_it(tmp_path):
    fifo = tmp_path / "session.h5"
    os.mkfifo(fifo)
    assert refusal(fifo) == f"{fifo}: this is a named pipe (FIFO), not a session file"
    assert refusal("/dev/zero") == "/dev/zero: this is a device, not a session file"
    assert refusal(tmp_path) == f"{tmp_path}: this is a folder, not a session file"


def test_hdf5_opens_the_file_that_was_checked_not_what_was_put_at_its_path_since(tmp_path):
    path = small_session(tmp_path / "session.h5")
    assert open_in_child("swapped", path) == (3, "opened")
    assert path.is_fifo()  # the race was run: a FIFO was waiting at the path when HDF5 opened it
    with open_session(tmp_path / "session.h5.moved") as s:
        assert s.n_ticks == 2500


# ---- parts of a session in other files ---------------------------------------------------------------

NOT_OURS = "not written by Palpation Console"
ONE_FILE = "a session keeps all of itself in one file, and nothing out of it is followed"


def test_the_writer_keeps_everything_in_its_one_file(tmp_path):
    """What the reader refuses below, the console never writes: only groups and datasets of the file's own."""
    with h5py.File(small_session(tmp_path / "s.h5"), "r") as f:
        links = {}
        f.visititems_links(lambda name, link: links.update({name: type(link)}))  # None: visit every link
        assert set(links.values()) == {h5py.HardLink}
        assert set(links) == {"meta", "stream", *TABLES}
        for ds in (f[name] for name in TABLES):
            assert not ds.is_virtual and ds.id.get_create_plist().get_external_count() == 0 and ds.chunks


def test_an_external_link_is_refused_without_opening_what_it_names(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    path = small_session(tmp_path / "s.h5")
    with h5py.File(path, "r+") as f:
        del f["meta"]
        f["meta"] = h5py.ExternalLink(str(fifo), "/meta")
    assert refusal(path) == f"{path}: the file was {NOT_OURS}: /meta is a link into another file, {fifo}; {ONE_FILE}"

    other = small_session(tmp_path / "other.h5")  # a file that would read well: still not followed
    path = small_session(tmp_path / "s2.h5")
    with h5py.File(path, "r+") as f:
        del f["stream"]
        f["stream"] = h5py.ExternalLink(str(other), "/stream")
    assert refusal(path) == f"{path}: the file was {NOT_OURS}: /stream is a link into another file, {other}; {ONE_FILE}"


def test_soft_links_are_followed_inside_the_file_and_refused_where_they_lead_out(tmp_path):
    path = small_session(tmp_path / "s.h5")
    with h5py.File(path, "r+") as f:
        f.move("levels", "kept")
        f["levels"] = h5py.SoftLink("/kept")
        f.move("stream/frames", "stream/frames_first")
        f["stream/frames_again"] = h5py.SoftLink("frames_first")  # relative: in /stream
        f["stream/frames"] = h5py.SoftLink("frames_again")  # two in a row
    assert open_in_child("session", path) == (3, "opened")
    with open_session(path) as s:
        assert len(s.levels) == 1 and s.n_ticks == 2500

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with h5py.File(path, "r+") as f:
        del f["levels"]
        f["elsewhere"] = h5py.ExternalLink(str(fifo), "/levels")
        f["levels"] = h5py.SoftLink("/elsewhere")
    assert refusal(path) == (f"{path}: the file was {NOT_OURS}: /elsewhere is a link into another file, {fifo}; "
                             f"{ONE_FILE}")

    with h5py.File(path, "r+") as f:
        del f["levels"]
        f["levels"] = h5py.SoftLink("/levels")
    assert refusal(path) == (f"{path}: the file is damaged: /levels is reached through more than 16 soft links in a "
                             "row (they go round in a loop)")


def test_rows_stored_in_other_files_are_refused_before_any_is_read(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    path = small_session(tmp_path / "s.h5")
    with h5py.File(path, "r") as f:
        levels = f["levels"][()]
    rows = tmp_path / "rows.bin"
    rows.write_bytes(levels.tobytes())
    for source in (fifo, rows):
        with h5py.File(path, "r+") as f:  # external raw storage: HDF5 reads the rows from ``source``
            del f["levels"]
            f.create_dataset("levels", shape=levels.shape, dtype=levels.dtype,
                             external=[(str(source), 0, levels.nbytes)])
        assert refusal(path) == (f"{path}: the file was {NOT_OURS}: /levels keeps its rows in another file, "
                                 f"{source}; {ONE_FILE}")

    other = small_session(tmp_path / "other.h5")
    path = small_session(tmp_path / "virtual.h5")
    with h5py.File(path, "r+") as f:  # a virtual dataset: its rows are the other file's
        events = f["events"]
        layout = h5py.VirtualLayout(shape=events.shape, dtype=events.dtype, maxshape=(None,))
        layout[:] = h5py.VirtualSource(str(other), "events", shape=events.shape)
        del f["events"]
        f.create_virtual_dataset("events", layout)
    assert refusal(path) == (f"{path}: the file was {NOT_OURS}: /events is a virtual dataset, whose rows HDF5 "
                             f"gathers from other datasets (in other files, too); {ONE_FILE}")


# ---- claims of more than a session holds -------------------------------------------------------------


def claiming(path: Path, name: str, rows: int, chunk_rows: int) -> Path:
    """A session whose /name holds ``rows`` rows of zeros in chunks of ``chunk_rows``: one compressed chunk
    stored again and again, so that the file stays small whatever its chunks add up to."""
    small_session(path)
    with h5py.File(path, "r+") as f:
        dtype = f[name].dtype
        del f[name]
        ds = f.create_dataset(name, shape=(rows,), maxshape=(None,), dtype=dtype, chunks=(chunk_rows,), shuffle=True,
                              compression="gzip", compression_opts=9, fletcher32=True)
        ds[:chunk_rows] = np.zeros(chunk_rows, dtype)
        mask, chunk = ds.id.read_direct_chunk((0,))
        for start in range(chunk_rows, rows, chunk_rows):
            ds.id.write_direct_chunk((start,), chunk, mask)
    return path


def test_tables_whose_many_small_chunks_add_up_to_more_than_a_session_holds_are_refused(tmp_path):
    levels = claiming(tmp_path / "levels.h5", "levels", 57_616, 16)  # 3,601 chunks of 16 levels
    assert levels.stat().st_size < 2**20
    assert refusal(levels) == (f"{levels}: the file is damaged or was not written by Palpation Console: /levels claims "
                               "57,616 rows (190 MB), more than a session can hold (57,600: 8 hours of force levels, "
                               "one every 0.5 s)")
    events = claiming(tmp_path / "events.h5", "events", 1_844_224, 1024)
    assert refusal(events) == (f"{events}: the file is damaged or was not written by Palpation Console: /events claims "
                               "1,844,224 rows (514 MB), more than a session can hold (1,843,200: 8 hours of 64 events "
                               "a second)")
    with open_session(claiming(tmp_path / "full.h5", "levels", 57_600, 16)) as s:  # as much as a session holds:
        assert "/levels: 57600 rows at the end never reached the disk" in s.warnings[0]  # read (and all zeros)


def test_a_claim_of_gigabytes_costs_neither_memory_nor_time(tmp_path):
    """A 3 MB file whose /levels claims 3.3 GB (a million levels) is refused within the child's time-out, in a
    process that could not have read it (open_child.py caps its memory), having needed about as much memory as
    importing the reader does (45 MiB)."""
    path = claiming(tmp_path / "huge.h5", "levels", 245 * 4096, 4096)
    assert path.stat().st_size < 4 * 2**20
    code, message, peak_mib = run_child("session", path)
    assert code == 0 and "/levels claims 1,003,520 rows (3,304 MB)" in message
    assert peak_mib < 200


def test_the_index_of_a_stream_is_bounded_too(tmp_path, monkeypatch):
    """The streams' bounds, at their real size, take files of tens of megabytes to pass: here they are made
    small, to see that their rows and chunks are counted over the whole index the same way."""
    path = claiming(tmp_path / "ticks.h5", "stream/ticks", 40 * 64, 64)
    monkeypatch.setitem(reader.ROW_BOUNDS, "stream/ticks", (40 * 64 - 1, "a test's bound"))
    with pytest.raises(reader.SessionFileError, match=r"/stream/ticks claims 2,560 rows \(1 MB\), more than a "
                                                      r"session can hold \(2,559: a test's bound\)"):
        open_session(path)
    monkeypatch.setitem(reader.ROW_BOUNDS, "stream/ticks", (40 * 64, "a test's bound"))
    monkeypatch.setattr(reader, "MAX_CHUNKS", 39)
    with pytest.raises(reader.SessionFileError, match="/stream/ticks is stored in more than 39 chunks"):
        open_session(path)
    monkeypatch.setattr(reader, "MAX_CHUNKS", 40)
    with open_session(path) as s:
        assert s.n_ticks == 0  # rows of zeros: written, but never by the console

    with h5py.File(path, "r+") as f:  # one chunk more, far beyond the others: not among the leading rows
        ticks = f["stream/ticks"]
        ticks.resize((10**9,))
        ticks.id.write_direct_chunk((10**9 - 64,), *reversed(ticks.id.read_direct_chunk((0,))))
    monkeypatch.setattr(reader, "MAX_CHUNKS", 41)
    monkeypatch.setitem(reader.ROW_BOUNDS, "stream/ticks", (41 * 64, "a test's bound"))
    with open_session(path) as s:
        assert s.n_ticks == 0 and "999,997,440 of its 1,000,000,000 rows are not in the file" in s.warnings[0]


def test_rows_are_read_a_bounded_piece_at_a_time(tmp_path, monkeypatch):
    path = small_session(tmp_path / "s.h5")
    with open_session(path) as s:
        as_whole = (s.levels, s.events, s.overview(), s.tick_rows(0, s.n_ticks),
                    s.tick_rows(100, 2400, ["force_measured_N", "x_slave_m"]), s.frames())
    reads = []  # the bytes of rows each read of HDF5 covers
    read = h5py.Dataset.__getitem__

    def counted(ds, args, new_dtype=None):
        rows = read(ds, args, new_dtype)
        reads.append(len(rows) * ds.dtype.itemsize)
        return rows

    monkeypatch.setattr(h5py.Dataset, "__getitem__", counted)
    monkeypatch.setattr(reader, "MAX_READ_BYTES", 16 * 2**10)  # 75 ticks, 21 frames, 4 levels
    with open_session(path) as s:
        in_pieces = (s.levels, s.events, s.overview(), s.tick_rows(0, s.n_ticks),
                     s.tick_rows(100, 2400, ["force_measured_N", "x_slave_m"]), s.frames())
    assert len(reads) > 2500 // 75 and max(reads) <= 16 * 2**10
    for whole, pieces in zip(as_whole, in_pieces):
        assert whole.dtype == pieces.dtype and whole.tobytes() == pieces.tobytes()
