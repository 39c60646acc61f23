"""The session recorder: layout, what goes in comes out, gaps, full disks, write errors and kill -9."""

from __future__ import annotations

import dataclasses
import errno
import json
import math
import signal
import subprocess
import sys
from collections import namedtuple
from datetime import datetime
from pathlib import Path

import h5py
import numpy as np
import pytest

from app.config import load_config
from app.recording import session_info
from app.rigs import build_rig
from control.messages import FaultKind, FaultRaised, LevelRecorded, Notice, PhaseChanged, RegionDone, Source, SzChanged
from control.telemetry import FRAME_DTYPE, TICK_DTYPE
from hardware.interfaces import Phase, TactileConstraints
from session import writer as recorder_module
from session.format import EVENT_DTYPE, FORMAT_NAME, FORMAT_VERSION, LEVEL_DTYPE, OVERVIEW_BUCKET_ROWS, EventKind
from session.info import SessionInfo, calibration_of, new_session_path, sessions_dir
from session.reader import open_session
from session.synthetic import frame_rows, level_record, tick_rows
from session.writer import RecorderError, SessionRecorder
from tests.session.conftest import RAMP, REGIONS_XY_M

REPO = Path(__file__).resolve().parents[2]
def same_rows(a: np.ndarray, b: np.ndarray) -> bool:
    """Bit-for-bit equality (NaN included, which == and array_equal treat as different)."""
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


INFO = SessionInfo(config={"control": {"ramp": RAMP}}, calibration=calibration_of(TactileConstraints(), 0.0),
                   rig={"backend": "test"})


# ---- a real recorded session -----------------------------------------------------------------------


def test_recorded_session_is_self_describing(recorded):
    path, status = recorded
    assert status.problem is None and status.rows_lost == 0 and status.rows_dropped == 0
    with h5py.File(path, "r") as f:  # a cleanly closed file opens without SWMR
        assert f.attrs["format"].decode() == FORMAT_NAME
        assert int(f.attrs["format_version"]) == FORMAT_VERSION
        assert len(f.attrs["uuid"].decode()) == 36
        assert datetime.fromisoformat(f.attrs["created_utc"].decode()).tzinfo is not None
        assert f.attrs["software_version"].decode()
        assert bool(f.attrs["simulated"])
        meta = {k: json.loads(v.decode()) for k, v in f["meta"].attrs.items()}
        assert meta["config_json"]["control"]["ramp"]["force_max_N"] == RAMP["force_max_N"]
        assert meta["config_json"]["rig"]["backend"] == "sim"
        assert meta["calibration_json"]["pitch_m"] == 2e-3 and meta["calibration_json"]["rows"] == 4
        assert [r["centre_xy_m"] for r in meta["phantom_json"]["phantom"]["regions"]] == [list(r) for r in REGIONS_XY_M]
        assert [round(g["depth_m"], 6) for g in meta["ground_truth_json"]] == [0.002, 0.007, 0.01]
        assert meta["rig_json"]["tissue_model"]
        assert f["stream/ticks"].dtype == TICK_DTYPE and f["stream/frames"].dtype == FRAME_DTYPE
        assert f["levels"].dtype == LEVEL_DTYPE and f["events"].dtype == EVENT_DTYPE
        for name in ("stream/ticks", "stream/frames", "levels", "events"):
            assert f[name].maxshape == (None,) and f[name].chunks is not None and f[name].fletcher32
        ticks = f["stream/ticks"][:]
        assert len(ticks) == status.ticks_written
        assert np.array_equal(ticks["tick"], np.arange(len(ticks)))  # every period, in order
        assert len(f["stream/frames"]) == status.frames_written > len(ticks) // 20
        events = f["events"][:]
        assert np.array_equal(events["seq"], np.arange(1, len(events) + 1))
        assert events["kind"][-1] == b"closed"
        kinds = set(events["kind"])
        assert {b"sz", b"phase", b"level", b"region_done"} <= kinds
        levels = f["levels"][:]
        assert len(levels) == 3 * 3 == status.levels_written
        assert list(levels["region"]) == [0, 0, 0, 1, 1, 1, 2, 2, 2]
        assert np.allclose(levels["force_desired_N"], [0.5, 1.0, 1.5] * 3)
        assert np.allclose(levels["tsi_position_m"][::3, :2], REGIONS_XY_M, atol=2e-4)
        overview = f["stream/overview"][:]
        # issue 13: the file says what its codes and its less obvious columns mean, without this code
        codes = json.loads(f["stream/ticks"].attrs["codes_json"].decode())
        notes = json.loads(f["stream/ticks"].attrs["notes_json"].decode())
        event_codes = json.loads(f["events"].attrs["codes_json"].decode())
        level_notes = json.loads(f["levels"].attrs["notes_json"].decode())
    assert {codes["phase"][str(p)] for p in np.unique(ticks["phase"])} >= {"APPROACH", "SETTLING", "DONE"}
    assert codes["sz"]["1"].startswith("position control") and codes["fault"]["0"] == "NONE"
    assert "running total" in notes["missed_ticks"]
    assert "counted from 0" in notes["region"] and "counted from 0" in level_notes["level"]
    phase_rows = events[events["kind"] == b"phase"]
    assert [event_codes["phase"][str(c)] for c in phase_rows["code"]] == [t.decode() for t in phase_rows["text"]]
    assert len(overview) == math.ceil(len(ticks) / OVERVIEW_BUCKET_ROWS)
    assert overview["n_rows"].sum() == len(ticks)
    k = len(overview) // 2
    bucket = ticks[k * OVERVIEW_BUCKET_ROWS:(k + 1) * OVERVIEW_BUCKET_ROWS]
    assert overview["t_start_s"][k] == bucket["t_s"][0] and overview["t_end_s"][k] == bucket["t_s"][-1]
    assert overview["force_measured_N_max"][k] == bucket["force_measured_N"].max()
    assert overview["tsi_z_m_min"][k] == bucket["x_slave_m"][:, 2].min()


def test_session_info_describes_the_rig_the_controller_drives():
    config = load_config()
    spec = dataclasses.replace(config.rig, master="none")  # what the interactive console runs
    info = session_info(config, build_rig(spec), spec)
    assert info.config["rig"]["master"] == "none" and info.rig["master"] == "none"
    assert info.config["control"] == config.control.to_mapping()
    assert info.config["sources"][0].endswith("default.toml")
    assert info.simulated and info.phantom["phantom"]["name"] == "flat" and len(info.ground_truth) == 3
    assert info.calibration["pitch_m"] == 2e-3 and info.calibration["table_height_m"] == 0.0
    assert info.software_version


def test_what_goes_in_comes_out(tmp_path):
    record = level_record(3, 2, 2.5, (0.02, 0.01), tumours_xy_m=((0.02, 0.012),), t_s=4.5, noise=0.05)
    ticks = tick_rows(0, 2500)
    frames = frame_rows(0, 250)
    events = [SzChanged(0.1, 0, Source.MASTER), PhaseChanged(0.2, Phase.SETTLING, 2, 7), LevelRecorded(4.5, record),
              RegionDone(4.6, 3, 7), FaultRaised(5.0, FaultKind.FORCE_CEILING, "force " + "é" * 300),
              Notice(5.1, "tare done"), "a health report the recorder ignores"]
    rec = SessionRecorder(tmp_path / "s.h5", INFO, block_rows=100)
    for start in range(0, 2500, 7):  # the GUI hands over small pieces
        rec.add_ticks(ticks[start:start + 7])
    rec.add_frames(frames)
    rec.add_events(events)
    rec.add_note("tumour suspected near the edge", 5.2)
    status = rec.close()
    assert (status.ticks_written, status.frames_written, status.levels_written) == (2500, 250, 1)
    with open_session(tmp_path / "s.h5") as s:
        assert same_rows(s.tick_rows(0, s.n_ticks), ticks)
        assert same_rows(s.frames(), frames)
        row = s.levels[0]
        for name in ("pressure_pa", "element_force_N", "onset_height_m", "L0_m", "dL_m", "stiffness_pa"):
            assert same_rows(row[name], getattr(record, name)), name
        assert (int(row["region"]), int(row["level"]), float(row["t_s"])) == (3, 2, 4.5)
        assert tuple(row["tsi_position_m"]) == record.tsi_position_m
        assert float(row["indentation_m"]) == record.indentation_m
        got = [(e["kind"], e["code"], e["region"], e["text"]) for e in s.event_dicts()]
    assert got[0] == ("sz", 0, -1, "master")
    assert got[1][:2] == ("phase", int(Phase.SETTLING))
    assert got[2][0] == "level" and got[3] == ("region_done", 7, 3, "")
    assert got[4][:2] == ("fault", int(FaultKind.FORCE_CEILING))
    assert got[4][3].startswith("force é") and len(got[4][3].encode()) <= 240  # cut at a character boundary
    assert got[5] == ("notice", 0, -1, "tare done")
    assert got[6] == ("note", 0, -1, "tumour suspected near the edge")
    assert got[-1][0] == "closed"


def test_lost_rows_are_counted_and_marked(tmp_path):
    rec = SessionRecorder(tmp_path / "s.h5", INFO)
    rec.add_ticks(tick_rows(0, 1000))
    rec.add_ticks(tick_rows(1300, 700))  # 300 rows overwritten in the ring before the GUI read them
    status = rec.close()
    assert status.rows_lost == 300 and status.ticks_written == 1700
    with open_session(tmp_path / "s.h5") as s:
        lost = [e for e in s.event_dicts() if e["kind"] == EventKind.ROWS_LOST]
        assert lost == [dict(lost[0], value=300.0, t_s=1.3)]
        assert s.rows_lost == 300 and any("300 tick rows were lost" in w for w in s.warnings)


def test_producer_calls_never_raise_once_stopped(tmp_path):
    rec = SessionRecorder(tmp_path / "s.h5", INFO)
    rec.close()
    rec.add_ticks(tick_rows(0, 10))
    rec.add_frames(frame_rows(0, 2))
    rec.add_events([Notice(0.0, "late")])
    rec.add_note("late", 0.0)
    assert rec.status().rows_dropped == 14 and not rec.recording
    assert rec.flush() is False
    rec.close()  # twice is fine


def test_an_overfull_queue_drops_and_counts_instead_of_growing(tmp_path):
    rec = SessionRecorder(tmp_path / "s.h5", INFO, max_queued_bytes=TICK_DTYPE.itemsize * 50)
    rec.add_ticks(tick_rows(0, 100))  # more than the whole budget: refused outright
    status = rec.close()
    assert status.rows_dropped == 100 and status.ticks_written == 0


def test_wrong_rows_are_a_programming_error(tmp_path):
    with SessionRecorder(tmp_path / "s.h5", INFO) as rec:
        with pytest.raises(TypeError, match="add_ticks takes rows of control.telemetry's dtype"):
            rec.add_ticks(frame_rows(0, 3))


# ---- where files go, and when they cannot be made ------------------------------------------------------


def test_sessions_folder_and_names(tmp_path, monkeypatch):
    monkeypatch.setenv("PALPATION_DATA_DIR", str(tmp_path / "data"))
    assert sessions_dir() == tmp_path / "data" / "sessions"
    when = datetime(2024, 5, 1, 14, 3, 22)
    first = new_session_path(now=when)
    assert first == tmp_path / "data" / "sessions" / "session-2024-05-01_14-03-22.h5"
    SessionRecorder(first, INFO).close()
    assert new_session_path(now=when).name == "session-2024-05-01_14-03-22-2.h5"
    with pytest.raises(RecorderError, match="already exists"):
        SessionRecorder(first, INFO)


def test_sessions_folder_defaults_to_the_platform_data_folder(monkeypatch):
    import platformdirs

    monkeypatch.delenv("PALPATION_DATA_DIR")
    assert sessions_dir() == Path(platformdirs.user_data_dir("palpation-console")) / "sessions"


def test_unusable_folder_is_refused_with_a_message(tmp_path):
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(RecorderError, match="cannot create the session folder"):
        SessionRecorder(tmp_path / "a_file" / "s.h5", INFO)


_Usage = namedtuple("_Usage", "total used free")


def test_refuses_to_start_on_a_nearly_full_disk(tmp_path, monkeypatch):
    monkeypatch.setattr(recorder_module.shutil, "disk_usage", lambda _p: _Usage(10**9, 10**9 - 5 * 2**20, 5 * 2**20))
    with pytest.raises(RecorderError, match="only 5 MB free"):
        SessionRecorder(tmp_path / "s.h5", INFO, min_free_bytes=100 * 2**20)
    assert not (tmp_path / "s.h5").exists()


def test_a_filling_disk_stops_recording_cleanly_and_keeps_the_data(tmp_path, monkeypatch):
    free = [10**9]
    monkeypatch.setattr(recorder_module.shutil, "disk_usage", lambda _p: _Usage(10**10, 0, free[0]))
    messages = []
    rec = SessionRecorder(tmp_path / "s.h5", INFO, min_free_bytes=100 * 2**20, on_problem=messages.append)
    rec.add_ticks(tick_rows(0, 3000))
    rec.add_events([LevelRecorded(2.0, level_record(0, 0, 1.0, (0.01, 0.015)))])
    assert rec.flush()
    free[0] = 20 * 2**20  # another program filled the disk
    rec.add_ticks(tick_rows(3000, 500))
    assert rec.flush() is False
    assert len(messages) == 1 and messages[0] == rec.problem
    assert "only 20 MB left" in rec.problem and str(tmp_path / "s.h5") in rec.problem
    assert "controller is unaffected" in rec.problem
    rec.add_ticks(tick_rows(3500, 100))  # the control side goes on; nothing more is written
    status = rec.close()
    assert not status.recording and status.rows_dropped == 100
    with h5py.File(tmp_path / "s.h5", "r") as f:  # closed cleanly, not merely recoverable
        assert len(f["stream/ticks"]) == 3500 and len(f["levels"]) == 1
    with open_session(tmp_path / "s.h5") as s:
        assert not s.recovered and any("only 20 MB left" in w for w in s.warnings)


# ---- real failures, in a process of their own ------------------------------------------------------------


def test_kill_9_while_recording_loses_at_most_a_second(tmp_path):
    path = tmp_path / "killed.h5"
    with subprocess.Popen([sys.executable, "-m", "tests.session.crash_child", "kill", str(path)], cwd=REPO,
                          stdout=subprocess.PIPE, text=True) as child:
        try:
            last = None
            for line in child.stdout:
                last = line.split()
                if int(last[1]) >= 2500:  # 2.5 s of data handed to the recorder
                    break
            child.send_signal(signal.SIGKILL)
            rest = child.stdout.read()
        finally:
            child.kill()
            child.wait(10)
    assert child.returncode == -signal.SIGKILL
    reported = [line.split() for line in rest.splitlines() if line.startswith("fed ")] or [last]
    fed_ticks, fed_levels = int(reported[-1][1]), int(reported[-1][2])
    with pytest.raises(OSError):
        h5py.File(path, "r").close()  # plain HDF5 refuses it: the file is still marked open for writing
    with open_session(path) as s:
        assert s.recovered and "did not end cleanly" in s.warnings[0]
        ticks = s.tick_rows(0, s.n_ticks)
        assert same_rows(ticks, tick_rows(0, s.n_ticks))  # intact, in order, no torn rows
        assert fed_ticks - s.n_ticks <= 1000, f"lost {fed_ticks - s.n_ticks} ms of the stream"
        assert fed_levels - 2 <= len(s.levels) <= fed_levels
        assert list(s.levels["level"]) == [k % 7 for k in range(len(s.levels))]
        assert s.overview()["n_rows"].sum() == s.n_ticks
        assert not s.closed_cleanly


def test_a_failing_write_stops_recording_with_a_message_and_keeps_the_data(tmp_path):
    """The process's file-size limit makes the writes fail the way a full disk does."""
    path = tmp_path / "limited.h5"
    done = subprocess.run([sys.executable, "-m", "tests.session.crash_child", "fsize", str(path), "4000000"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["problem"].startswith("Recording stopped: the file reached the largest size this system allows")
    assert str(path) in report["problem"] and "kept in that file" in report["problem"]
    assert report["calls_after"] == 100 and not report["recording"]  # the producer carried on, unaffected
    assert report["rows_dropped"] > 0
    with open_session(path) as s:  # what reached the disk before the failure is all there and intact
        assert s.recovered and "truncated" in s.warnings[0]
        assert s.n_ticks > 8000
        assert same_rows(s.tick_rows(0, s.n_ticks), tick_rows(0, s.n_ticks))
        assert len(s.levels) > 20 and np.array_equal(s.levels["seq"], np.arange(1, len(s.levels) + 1))


def test_a_recorder_nobody_closed_is_written_out_when_the_process_exits(tmp_path):
    path = tmp_path / "forgotten.h5"
    done = subprocess.run([sys.executable, "-m", "tests.session.crash_child", "forget", str(path)], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    with open_session(path) as s:
        assert s.closed_cleanly and not s.recovered and s.n_ticks == 5000


@pytest.mark.parametrize("error, why", [
    (OSError(errno.ENOSPC, "No space left on device"), "the disk is full"),
    (RuntimeError("Can't write data (file write failed: errno = 28, error message = 'No space left')"),
     "the disk is full"),
    (RuntimeError("Can't write data (file write failed: errno = 122, error message = 'Disk quota exceeded')"),
     "the disk quota is exceeded"),
    (RuntimeError("Can't write data (file write failed: errno = 5, error message = 'I/O error')"),
     "input/output error"),
    (RuntimeError("Can't write data (something else)\nsecond line"),
     "writing failed (Can't write data (something else))"),
])
def test_write_errors_are_explained(error, why):
    message = recorder_module._describe_write_error(error, Path("/data/s.h5"))
    assert message.startswith("Recording stopped: ") and why in message and "/data/s.h5" in message


def test_what_was_queued_when_the_writer_failed_is_counted_a_row_for_a_row(tmp_path):
    import errno
    import threading

    rec = SessionRecorder(tmp_path / "s.h5", INFO)
    entered, gate = threading.Event(), threading.Event()

    def failing_take(item):  # the disk goes while the writer holds one block
        entered.set()
        gate.wait(10)
        raise OSError(errno.EIO, "Input/output error")

    rec._take = failing_take
    rec.add_ticks(tick_rows(0, 10))
    assert entered.wait(10)
    rec.add_controller_lost("the controller process was killed")  # queued behind the block: one row each
    rec.add_note("queued too", 0.0)
    gate.set()
    status = rec.close()
    assert status.problem and status.rows_dropped == 2
