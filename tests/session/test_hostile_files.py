"""Files that would make a reader wait forever or eat the machine's memory (issue 49): a FIFO or a device for a
path, a session whose parts live in other files. Each is refused in one line, in a child process (the reader's
own time-out and memory cap), so that a regression fails its test instead of stalling the run."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import h5py

from control.messages import LevelRecorded
from session.format import TABLES
from session.reader import open_session
from session.synthetic import level_record
from session.synthetic import tick_rows
from session.writer import SessionRecorder

from tests.session.test_recorder import INFO

REPO = Path(__file__).resolve().parents[2]


def open_in_child(kind: str, path) -> tuple[int, str]:
    """(exit code: 0 refused, 3 opened; what it printed) of tests/session/open_child.py on ``path``."""
    done = subprocess.run([sys.executable, "-m", "tests.session.open_child", kind, str(path)], cwd=REPO,
                          capture_output=True, text=True, timeout=20)
    assert done.returncode in (0, 3), done.stderr
    return done.returncode, done.stdout.rsplit("\n", 2)[0]


def refusal(path, kind: str = "session") -> str:
    """The one line the reader refuses ``path`` with."""
    code, message = open_in_child(kind, path)
    assert code == 0 and "\n" not in message, message
    return message


def small_session(path: Path) -> Path:
    rec = SessionRecorder(path, INFO)
    rec.add_ticks(tick_rows(0, 2500))
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
