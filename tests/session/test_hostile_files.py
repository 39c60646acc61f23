"""Files that would make a reader wait forever or eat the machine's memory (issue 49): a FIFO or a device for a
path, a session whose parts live in other files. Each is refused in one line, in a child process (the reader's
own time-out and memory cap), so that a regression fails its test instead of stalling the run."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from session.reader import open_session
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
