"""Session files open in the HDF5 tools a distribution ships (issue 13): h5ls and h5dump of HDF5 1.10.

The bootstrap installs them (hdf5-tools); the writer asks for the oldest file format that keeps SWMR."""

from __future__ import annotations

import shutil
import subprocess

import pytest

from control.messages import LevelRecorded
from session.reader import open_session
from session.synthetic import level_record
from session.writer import SessionRecorder
from tests.session.test_reader import _drop_columns
from tests.session.test_recorder import INFO

TOOLS = [shutil.which("h5ls"), shutil.which("h5dump")]
pytestmark = pytest.mark.skipif(None in TOOLS, reason="the HDF5 tools are not installed (make bootstrap does)")


def _tools_read(path) -> None:
    listing = subprocess.run(["h5ls", "-r", str(path)], capture_output=True, text=True, timeout=60)
    assert listing.returncode == 0, listing.stderr
    assert "*ERROR*" not in listing.stdout, listing.stdout
    assert "/stream/ticks" in listing.stdout and "/levels" in listing.stdout
    header = subprocess.run(["h5dump", "-H", str(path)], capture_output=True, text=True, timeout=60)
    assert header.returncode == 0, header.stderr
    assert 'DATASET "ticks"' in header.stdout and "force_measured_N" in header.stdout
    # and the data itself, not only the header
    data = subprocess.run(["h5dump", "-d", "/levels", str(path)], capture_output=True, text=True, timeout=60)
    assert data.returncode == 0 and "pressure_pa" in data.stdout, data.stderr


def test_a_recorded_session_and_a_reference_palpation_open_in_h5ls_and_h5dump(recorded, reference_recorded):
    _tools_read(recorded[0])
    _tools_read(reference_recorded)


def test_a_version_1_file_the_reader_accepts_opens_in_them_too(tmp_path):
    rec = SessionRecorder(tmp_path / "v1.h5", INFO)
    rec.add_events([LevelRecorded(1.0, level_record(0, 0, 1.0, (0.004, 0.015)))])
    rec.close()
    _drop_columns(tmp_path / "v1.h5", "levels", {"pressure_std_pa", "window_frames"}, version=1)
    with open_session(tmp_path / "v1.h5") as s:
        assert s.format_version == 1
    _tools_read(tmp_path / "v1.h5")
