"""One time base (issue 51): every session pairs its loop clock with UTC, the reader maps loop time to UTC
through the pairs, and the exports carry it; older files fall back to created_utc and say so."""

from __future__ import annotations

import csv
import time
from datetime import datetime

import h5py
import numpy as np
import pytest

import app.recording as recording
from app.session_commands import export_main
from control.telemetry import FRAME_DTYPE
from session.format import CLOCK_INTERVAL_S
from session.info import SessionInfo
from session.reader import ClockMap, SessionFileError, open_session
from session.synthetic import tick_rows
from session.writer import SessionRecorder

INFO = SessionInfo(config={}, calibration={"pitch_m": 2e-3})


def test_the_map_is_linear_between_pairs_and_runs_at_the_loop_rate_beyond():
    base = 1_700_000_000_123_456_789
    clock = ClockMap(np.array([10.0, 11.0, 12.0]), np.array([base, base + 1_000_400_000, base + 2_000_400_000]))
    t = np.array([9.5, 10.0, 10.5, 11.0, 11.25, 12.0, 13.5])
    expected = base + np.array([-500_000_000, 0, 500_200_000, 1_000_400_000, 1_250_400_000, 2_000_400_000,
                                3_500_400_000])
    assert clock(t).dtype == np.int64 and clock(t).tolist() == expected.tolist()  # to the nanosecond


def test_the_map_is_monotonic_whatever_order_the_pairs_came_in_and_a_stepped_back_wall_clock():
    base = 1_700_000_000_000_000_000
    # out of order, one loop time twice, and UTC stepped back 0.3 s between the second and the third
    t_s = np.array([2.0, 0.0, 1.0, 1.0, 3.0])
    utc = np.array([base + 700_000_000, base, base + 1_000_000_000, base + 5, base + 1_700_000_000])
    clock = ClockMap(t_s, utc)
    mapped = clock(np.linspace(-1.0, 4.0, 501))
    assert (np.diff(mapped) >= 0).all()
    assert clock(np.array([1.0]))[0] == base + 1_000_000_000  # the first pairing of a loop time is kept
    assert clock(np.array([1.5, 2.0]))[0] == clock(np.array([2.0]))[0] == base + 1_000_000_000  # UTC stands still


def test_a_simulated_session_pairs_its_clocks_from_start_to_end_on_a_nominal_time_line(recorded):
    with open_session(recorded[0]) as s:
        pairs = s.clock
        t0, t1 = s.tick_rows(0, 1)["t_s"][0], s.tick_rows(s.n_ticks - 1, s.n_ticks)["t_s"][0]
        created = datetime.fromisoformat(s.created_utc).timestamp()
        utc_first_tick = s.utc_ns(np.array([t0]))[0]
        assert s.clock_note == ""
    assert pairs["t_s"][0] <= t0 and pairs["t_s"][-1] >= t1  # the start and the end
    steps = np.diff(pairs["t_s"])
    assert (steps > 0).all() and steps[:-1].max() <= CLOCK_INTERVAL_S + 0.1  # about every second between
    assert len(pairs) >= (t1 - t0) / (CLOCK_INTERVAL_S + 0.1)
    # simulated time is nominal: one second of UTC per simulated second, from when recording began
    nominal = pairs["utc_ns"][0] + np.round((pairs["t_s"] - pairs["t_s"][0]) * 1e9).astype(np.int64)
    assert np.abs(pairs["utc_ns"] - nominal).max() <= 1
    assert abs(utc_first_tick / 1e9 - created) < 1.0


def test_the_console_pairs_its_controllers_clock_with_utc_when_it_starts_every_second_and_when_it_closes(
        tmp_path, monkeypatch):
    class Bridge:
        def add_sink(self, sink):
            pass

    fake_monotonic = [1000.0]
    monkeypatch.setattr(recording, "read_clocks", lambda: (fake_monotonic[0], time.time_ns()))
    session = recording.SessionRecording(Bridge(), INFO, folder=tmp_path, recorder_options={"min_free_bytes": 0})
    session.driver_started()
    for k in range(5):  # rows handed over every 0.6 s of the controller's clock
        fake_monotonic[0] += 0.6
        session.add_rows(tick_rows(100 * k, 100), np.zeros(0, FRAME_DTYPE), [])
    fake_monotonic[0] += 0.2
    session.driver_stopped(None)
    with open_session(session.last_status.path) as s:
        pairs = s.clock
    assert pairs["t_s"].tolist() == pytest.approx([1000.0, 1001.2, 1002.4, 1003.2])
    now_ns = datetime.now().timestamp() * 1e9
    assert (np.abs(pairs["utc_ns"] - now_ns) < 60e9).all() and (np.diff(pairs["utc_ns"]) >= 0).all()


def _as_version_2(path):
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = 2
        del f["clock"]


def test_a_file_from_before_the_clock_falls_back_to_created_utc_and_the_exports_say_so(tmp_path, capsys):
    path = tmp_path / "v2.h5"
    rec = SessionRecorder(path, INFO, min_free_bytes=0)
    rec.add_ticks(tick_rows(5000, 2000))  # its loop clock starts at 5 s
    rec.add_clock(5.0, 1_800_000_000_000_000_000)
    rec.close()
    _as_version_2(path)
    with open_session(path) as s:
        assert len(s.clock) == 0 and s.format_version == 2
        assert "version 2" in s.clock_note and "created_utc" in s.clock_note and "\n" not in s.clock_note
        created_ns = round(datetime.fromisoformat(s.created_utc).timestamp() * 1e3) * 1_000_000
        assert s.utc_ns(np.array([5.0, 6.5])).tolist() == [created_ns, created_ns + 1_500_000_000]
    assert export_main([str(path), "--csv", str(tmp_path), "--tables", "ticks"]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("warning: the session stores no pairs")


def test_a_version_3_file_without_its_clock_is_damaged(tmp_path):
    path = tmp_path / "v3.h5"
    SessionRecorder(path, INFO, min_free_bytes=0).close()
    with h5py.File(path, "r+") as f:
        del f["clock"]
    with pytest.raises(SessionFileError, match="the dataset /clock is missing"):
        open_session(path)


def test_every_exported_table_carries_utc_beside_the_loop_time(recorded, tmp_path, capsys):
    path = recorded[0]
    assert export_main([str(path), "--csv", str(tmp_path), "--tables", "ticks,levels"]) == 0
    with open(tmp_path / f"{path.stem}-ticks.csv", newline="") as f:
        reader = csv.reader(f)
        header = next(reader)
        rows = list(reader)
    assert header[header.index("t_s") + 1] == "utc_ns"
    t_s = np.array([float(r[header.index("t_s")]) for r in rows])
    utc = np.array([int(r[header.index("utc_ns")]) for r in rows])
    with open_session(path) as s:
        assert utc.tolist() == s.utc_ns(t_s).tolist()
        level_utc = s.utc_ns(s.levels["t_s"])
    assert (np.diff(utc) > 0).all()
    with open(tmp_path / f"{path.stem}-levels.csv", newline="") as f:
        levels = list(csv.DictReader(f))
    assert [int(r["utc_ns"]) for r in levels[::60]] == level_utc.tolist()
