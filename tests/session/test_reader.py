"""Reading sessions back: the streams, and every kind of bad file giving a message instead of a traceback."""

from __future__ import annotations

import hashlib
import json
import shutil

import h5py
import numpy as np
import pytest

from control.messages import LevelRecorded
from session.format import FORMAT_VERSION, OVERVIEW_BUCKET_ROWS
from session.reader import SessionFileError, open_session
from session.stitch import StitchError, StitchParams, stitch_session
from session.synthetic import level_record, tick_rows
from session.writer import SessionRecorder
from tests.session.test_recorder import INFO


def sha256(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_streams_read_back_at_full_and_overview_resolution(recorded):
    path, status = recorded
    before = sha256(path)
    with open_session(path) as s:
        assert not s.recovered and s.closed_cleanly and s.warnings == []
        assert (s.n_ticks, s.n_frames) == (status.ticks_written, status.frames_written)
        t0, t1 = s.time_span_s()
        assert t0 == 0.0 and t1 == pytest.approx((s.n_ticks - 1) * 1e-3)
        window = s.ticks_between(10.0, 12.5, ["force_measured_N", "x_slave_m"])
        assert window.dtype.names == ("force_measured_N", "x_slave_m")
        assert len(window) == 2501  # every tick of the window, both ends included
        every = s.tick_rows(10000, 12501)
        assert np.array_equal(window["force_measured_N"], every["force_measured_N"])
        overview = s.overview()
        assert overview["n_rows"].sum() == s.n_ticks and len(overview) == -(-s.n_ticks // OVERVIEW_BUCKET_ROWS)
        assert np.nanmax(overview["force_measured_N_max"]) == np.nanmax(s.tick_rows(0, s.n_ticks)["force_measured_N"])
        assert [(r.region, r.outcome, len(r.rows)) for r in s.regions()] == [(0, "done", 3), (1, "done", 3),
                                                                            (2, "done", 3)]
        assert s.phantom_name == "flat" and s.simulated and len(s.ground_truth) == 3
        assert s.pitch_m == 2e-3 and s.element_area_m2 == pytest.approx(4e-6)
        assert len(s.frames(0, 10)) == 10
    assert sha256(path) == before  # read-only


def test_an_overview_missing_its_tail_is_completed_from_the_ticks(tmp_path):
    rec = SessionRecorder(tmp_path / "s.h5", INFO)
    rec.add_ticks(tick_rows(0, 2500))
    rec.close()
    with h5py.File(tmp_path / "s.h5", "r+") as f:  # as if the last buckets never reached the disk
        f["stream/overview"].resize((1,))
    with open_session(tmp_path / "s.h5") as s:
        overview = s.overview()
        assert list(overview["row_start"]) == [0, 1000, 2000] and list(overview["n_rows"]) == [1000, 1000, 500]
        assert overview["t_end_s"][-1] == pytest.approx(2.499)


def test_a_file_from_before_the_io_column_opens_and_reads_it_as_nan(tmp_path):
    rec = SessionRecorder(tmp_path / "old.h5", INFO)
    rec.add_ticks(tick_rows(0, 2500))
    rec.close()
    with h5py.File(tmp_path / "old.h5", "r+") as f:  # the tick table as the first version wrote it
        f.attrs["format_version"] = 1
        ticks = f["stream/ticks"][()]
        old = np.dtype([(n, ticks.dtype[n]) for n in ticks.dtype.names if n != "io_s"])
        del f["stream/ticks"]
        f.create_dataset("stream/ticks", data=np.array(ticks[list(old.names)], dtype=old), maxshape=(None,),
                         chunks=(512,))
    with open_session(tmp_path / "old.h5") as s:
        assert s.n_ticks == 2500
        rows = s.tick_rows(0, 100)
        assert np.isnan(rows["io_s"]).all() and np.allclose(rows["compute_s"], 30e-6)
        window = s.ticks_between(1.0, 1.5, ["io_s", "force_measured_N"])
        assert window.dtype.names == ("io_s", "force_measured_N") and len(window) == 501
        assert np.isnan(window["io_s"]).all()
        assert len(s.overview()) == 3


# ---- bad input ---------------------------------------------------------------------------------------


def expect_problem(path, *fragments):
    with pytest.raises(SessionFileError) as info:
        open_session(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ")
    for fragment in fragments:
        assert fragment in message, message
    return message


def test_missing_empty_and_folder(tmp_path):
    expect_problem(tmp_path / "nope.h5", "no such file")
    (tmp_path / "empty.h5").write_bytes(b"")
    expect_problem(tmp_path / "empty.h5", "empty (0 bytes)")
    expect_problem(tmp_path, "folder, not a session file")


def test_foreign_files(tmp_path):
    (tmp_path / "notes.h5").write_text("Region 1: suspicious lump\n")
    expect_problem(tmp_path / "notes.h5", "not an HDF5 file at all", "b'Region 1'")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["images"] = np.zeros((4, 4))
    expect_problem(tmp_path / "other.h5", "not a Palpation Console session", "no 'format' attribute", "images")
    with h5py.File(tmp_path / "tagged.h5", "w") as f:
        f.attrs["format"] = "some-other-format"
    expect_problem(tmp_path / "tagged.h5", "its format is 'some-other-format'")


def test_newer_format_version(recorded, tmp_path):
    path = tmp_path / "newer.h5"
    shutil.copy(recorded[0], path)
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = FORMAT_VERSION + 1
    expect_problem(path, "newer Palpation Console", f"format version {FORMAT_VERSION + 1}",
                   f"reads up to {FORMAT_VERSION}", "Update")


def test_missing_parts(recorded, tmp_path):
    path = tmp_path / "parts.h5"
    shutil.copy(recorded[0], path)
    with h5py.File(path, "r+") as f:
        del f["levels"]
    expect_problem(path, "damaged", "/levels is missing")
    shutil.copy(recorded[0], path)
    with h5py.File(path, "r+") as f:
        f["meta"].attrs["config_json"] = np.bytes_(b"{not json")
    expect_problem(path, "damaged", "config_json", "not valid JSON")
    with h5py.File(path, "r+") as f:
        f["meta"].attrs["config_json"] = np.bytes_(b"[1, 2]")
    expect_problem(path, "damaged", "'config_json' is not a JSON object")
    shutil.copy(recorded[0], path)
    with h5py.File(path, "r+") as f:
        f["meta"].attrs["ground_truth_json"] = np.bytes_(b'[{"x_m": "twelve"}]')
    expect_problem(path, "damaged", "'ground_truth_json' is not a list of tumours")


@pytest.mark.parametrize("fraction", [0.002, 0.3, 0.9, 0.99, 0.999])
def test_truncated_files(recorded, tmp_path, fraction):
    source = recorded[0]
    path = tmp_path / "cut.h5"
    data = source.read_bytes()
    path.write_bytes(data[:int(len(data) * fraction)])
    try:
        with open_session(path) as s:  # whatever it shows, it says the file was cut short
            assert s.recovered and "truncated" in s.warnings[0]
            stitch_session(s)
            s.overview()
            s.frames()
    except SessionFileError as err:
        assert "truncated" in err.problem


def _rows_before(path, name: str, size: int) -> int:
    """Rows of dataset ``name`` whose chunks all end within the file's first ``size`` bytes, in order."""
    with h5py.File(path, "r") as f:
        ds = f[name]
        rows = 0
        for info in sorted((ds.id.get_chunk_info(i) for i in range(ds.id.get_num_chunks())),
                           key=lambda info: info.chunk_offset):
            if info.byte_offset + info.size > size:
                break
            rows = min(info.chunk_offset[0] + ds.chunks[0], len(ds))
        return rows


def test_a_truncated_file_gives_back_what_lies_in_the_part_that_is_there(recorded, tmp_path):
    source = recorded[0]
    with open_session(source) as whole:
        levels, ticks, frames = whole.levels.copy(), whole.tick_rows(0, whole.n_ticks), whole.frames()
    data = source.read_bytes()
    path = tmp_path / "cut.h5"
    # (cut at 90 %, this recording lost the ticks' chunk index itself, which HDF5 places as the stream grows:
    # none of its ticks can be found then, and the reader says so; cut at 95 % they are all there but the last)
    for fraction, least_levels in ((0.95, 0), (0.999, len(levels) - 1)):
        size = int(len(data) * fraction)
        path.write_bytes(data[:size])
        with open_session(path) as s:
            assert s.recovered and f"{1 - fraction:.1%} of it is missing" in s.warnings[0]
            # every row of the streams' chunks that lie in the part that is there, up to the first that does
            # not (frames are buffered: theirs lie where they were flushed), as recorded (NaN included)
            assert s.n_ticks == _rows_before(source, "stream/ticks", size) > 0.5 * len(ticks)
            assert s.n_frames == _rows_before(source, "stream/frames", size) > 0.5 * len(frames)
            assert s.tick_rows(0, s.n_ticks).tobytes() == ticks[:s.n_ticks].tobytes()
            assert s.frames().tobytes() == frames[:s.n_frames].tobytes()
            assert least_levels <= len(s.levels) and s.levels.tobytes() == levels[:len(s.levels)].tobytes()
            assert any("/levels" in w for w in s.warnings[1:]) == (len(s.levels) < len(levels))
            assert len(stitch_session(s).levels) == len(np.unique(s.levels["force_desired_N"]))
    assert path.read_bytes() == data[:int(len(data) * 0.999)]  # never written to


def test_declared_sizes_are_checked_against_the_file(recorded, tmp_path):
    path = tmp_path / "claims.h5"
    shutil.copy(recorded[0], path)
    with open_session(path) as s:
        n_ticks = s.n_ticks
    with h5py.File(path, "r+") as f:  # a header claiming 10^10 rows in a 2 MB file
        f["stream/ticks"].resize((10**10,))
        f["levels"].resize((10**9,))
    with open_session(path) as s:
        assert s.n_ticks == n_ticks and len(s.levels) == recorded[1].levels_written
        assert any("9,999,9" in w and "not in the file" in w for w in s.warnings)
        t0, t1 = s.time_span_s()
        assert len(s.ticks_between(t0, t1, ["force_measured_N"])) == n_ticks

    shutil.copy(recorded[0], path)
    with h5py.File(path, "r+") as f:  # one row would need HDF5 to allocate a 3 GB chunk
        dtype = f["stream/frames"].dtype
        del f["stream/frames"]
        f.create_dataset("stream/frames", shape=(10,), maxshape=(None,), dtype=dtype, chunks=(2**22,))
    expect_problem(path, "not written by Palpation Console", "/stream/frames is stored in chunks of 3,072 MB")

    shutil.copy(recorded[0], path)
    with h5py.File(path, "r+") as f:  # a stored chunk bigger than its rows could ever be
        ds = f["events"]
        ds.id.write_direct_chunk((0,), bytes(ds.chunks[0] * ds.dtype.itemsize * 2))
    expect_problem(path, "damaged", "a chunk of /events claims")

    shutil.copy(recorded[0], path)
    with h5py.File(path, "r+") as f:
        f["meta"].attrs["rig_json"] = np.bytes_(b"{" + b" " * (17 * 2**20) + b"}")
    expect_problem(path, "/meta attribute 'rig_json' is 17 MB")


def test_positions_and_pitch_that_make_no_sense(recorded, tmp_path):
    path = tmp_path / "places.h5"
    shutil.copy(recorded[0], path)
    with h5py.File(path, "r+") as f:
        levels = f["levels"][()]
        levels["tsi_position_m"][1, 0] = np.nan
        levels["tsi_position_m"][2, 1] = -1000.0
        f["levels"][...] = levels
    with open_session(path) as s:
        assert len(s.levels) == len(levels) - 2 and np.isfinite(s.levels["tsi_position_m"]).all()
        assert any("2 level records with a position" in w for w in s.warnings)
        stitch_session(s)

    shutil.copy(recorded[0], path)
    with h5py.File(path, "r+") as f:
        calibration = json.loads(f["meta"].attrs["calibration_json"])
        calibration["pitch_m"] = 1e-300
        f["meta"].attrs["calibration_json"] = np.bytes_(json.dumps(calibration).encode())
    expect_problem(path, "damaged", "pitch_m must be between 0.1 and 20 mm (got 1e-300)")

    shutil.copy(recorded[0], path)
    with h5py.File(path, "r+") as f:
        f["meta"].attrs["ground_truth_json"] = np.bytes_(b'[{"x_m": NaN, "y_m": 0.01}]')
    expect_problem(path, "'ground_truth_json' is not a list of tumours")


def test_areas_spread_over_the_whole_frame_are_refused_before_memory_is_spent(recorded, tmp_path):
    path = tmp_path / "spread.h5"
    shutil.copy(recorded[0], path)
    with h5py.File(path, "r+") as f:  # 2 m apart, every level its own force: 4 million cells per level map
        levels = f["levels"][()]
        levels["tsi_position_m"][0, :2] = -0.99
        levels["tsi_position_m"][-1, :2] = 0.99
        levels["force_desired_N"] = np.arange(len(levels)) + 1.0
        f["levels"][...] = levels
    with open_session(path) as s:
        with pytest.raises(StitchError, match="exceed the 20,000,000 cells a stitch may use; choose larger cells"):
            stitch_session(s)
        assert len(stitch_session(s, StitchParams(cell_m=5e-3)).levels) == len(levels)


@pytest.mark.parametrize("fraction", [0.0003, 0.05, 0.3, 0.5, 0.8, 0.97])
@pytest.mark.parametrize("kind", ["zeros", "noise"])
def test_corrupt_files_never_raise_anything_else(recorded, tmp_path, fraction, kind):
    path = tmp_path / "bad.h5"
    shutil.copy(recorded[0], path)
    size = path.stat().st_size
    junk = bytes(2048) if kind == "zeros" else np.random.default_rng(int(fraction * 1e4)).bytes(2048)
    with open(path, "r+b") as fh:
        fh.seek(int(size * fraction))
        fh.write(junk)
    try:
        with open_session(path) as s:
            stitch_session(s)
            s.overview()
            t0, t1 = s.time_span_s()
            for a in np.linspace(t0, t1, 8):
                s.ticks_between(a, a + 2.0, ["force_measured_N"])
            s.frames()
    except SessionFileError as err:
        assert err.problem.startswith("the file is")


def _drop_columns(path, table: str, names: set[str], version: int | None) -> None:
    with h5py.File(path, "r+") as f:
        if version is not None:
            f.attrs["format_version"] = version
        rows = f[table][()]
        kept = np.dtype([(n, rows.dtype[n]) for n in rows.dtype.names if n not in names])
        del f[table]
        f.create_dataset(table, data=np.array(rows[list(kept.names)], dtype=kept), maxshape=(None,), chunks=(1,))


def test_a_version_1_file_opens_without_the_levels_scatter_and_a_version_2_file_must_have_it(tmp_path):
    rec = SessionRecorder(tmp_path / "v1.h5", INFO)
    rec.add_events([LevelRecorded(1.0, level_record(0, 0, 1.0, (0.004, 0.015)))])
    rec.close()
    shutil.copy(tmp_path / "v1.h5", tmp_path / "v2.h5")
    _drop_columns(tmp_path / "v1.h5", "levels", {"pressure_std_pa", "window_frames"}, version=1)
    with open_session(tmp_path / "v1.h5") as s:
        assert s.format_version == 1 and len(s.levels) == 1
        assert np.isnan(s.levels["pressure_std_pa"]).all() and s.levels["window_frames"][0] == -1
        assert np.allclose(s.levels["pressure_pa"], level_record(0, 0, 1.0, (0.004, 0.015)).pressure_pa)
    _drop_columns(tmp_path / "v2.h5", "levels", {"window_frames"}, version=None)
    expect_problem(tmp_path / "v2.h5", "damaged", "/levels", "window_frames")


def test_numbers_no_integer_holds_are_damage_not_an_overflow(tmp_path):
    path = tmp_path / "s.h5"
    rec = SessionRecorder(path, INFO)
    rec.add_ticks(tick_rows(0, 100))
    rec.add_ticks(tick_rows(150, 100))  # 50 rows lost, twice
    rec.add_ticks(tick_rows(300, 100))
    rec.close()
    with h5py.File(path, "r+") as f:
        events = f["events"][()]
        lost = np.flatnonzero(events["kind"] == b"rows_lost")
        assert len(lost) == 2
        events["value"][lost[1]] = np.inf
        f["events"][...] = events
    with open_session(path) as s:
        assert s.rows_lost == 50
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = np.inf
    expect_problem(path, "no readable 'format_version' attribute")
