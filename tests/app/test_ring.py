"""The shared-memory ring: never a torn row, every lost row counted, nothing left in /dev/shm."""

import multiprocessing as mp
import os
import pickle
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.ring import NAME_PREFIX, RingError, SharedRing
from control.telemetry import FRAME_DTYPE, TICK_DTYPE, empty_frame, empty_tick


def own_segments() -> set[str]:
    shm = Path("/dev/shm")
    return {p.name for p in shm.glob(f"{NAME_PREFIX}{os.getpid()}_*")} if shm.is_dir() else set()


@pytest.fixture(autouse=True)
def no_shared_memory_leak():
    before = own_segments()
    yield
    assert own_segments() == before, "a test left shared memory behind"


def frame_row(i: int) -> np.ndarray:
    """A FRAME_DTYPE row whose every field is a function of i, so a torn copy is detectable."""
    row = empty_frame()
    row["tick"] = i
    row["sensor_seq"] = i
    row["t_s"] = i * 1e-3
    row["tsi_position_m"] = (i, -i, 2 * i)
    row["pressure_pa"] = np.float32(i % 1_000_003)
    row["dL_m"] = np.float32(-(i % 1_000_003))
    row["stiffness_pa"] = np.arange(60, dtype=np.float32).reshape(4, 15) + np.float32(i % 65_521)
    return row


def consistent(rows: np.ndarray) -> np.ndarray:
    i = rows["tick"]
    ok = (rows["sensor_seq"] == i) & (rows["t_s"] == i * 1e-3)
    ok &= (rows["tsi_position_m"] == np.stack([i, -i, 2 * i], axis=1)).all(axis=1)
    p = (i % 1_000_003).astype(np.float32)
    ok &= (rows["pressure_pa"] == p[:, None, None]).all(axis=(1, 2))
    ok &= (rows["dL_m"] == -p[:, None, None]).all(axis=(1, 2))
    s = np.arange(60, dtype=np.float32).reshape(4, 15)[None] + (i % 65_521).astype(np.float32)[:, None, None]
    ok &= (rows["stiffness_pa"] == s).all(axis=(1, 2))
    return ok


def hammer(handle, n_rows: int, ready) -> None:
    """Writer process: n_rows consistent rows as fast as it can."""
    ring = handle.attach()
    ready.set()
    rows = [frame_row(i) for i in range(min(n_rows, 4096))]
    for i in range(n_rows):
        ring.write(rows[i] if i < len(rows) else frame_row(i))
    ring.close()


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    capacity=st.integers(1, 64),
    n_rows=st.integers(2_000, 30_000),
    max_rows=st.one_of(st.none(), st.integers(1, 40)),
)
def test_reader_never_returns_a_torn_row_and_accounts_for_every_row(capacity, n_rows, max_rows):
    ctx = mp.get_context("spawn")
    with SharedRing.create(FRAME_DTYPE, capacity) as ring:
        reader = SharedRing.attach(ring.name, FRAME_DTYPE, capacity)
        ready = ctx.Event()
        writer = ctx.Process(target=hammer, args=(ring.handle, n_rows, ready))
        writer.start()
        try:
            assert ready.wait(30), "writer process did not start"
            cursor = returned = lost_total = 0
            last_index = -1
            while cursor < n_rows:
                rows, new_cursor, lost = reader.read_since(cursor, max_rows)
                assert consistent(rows).all(), "torn row returned"
                if len(rows):
                    assert rows["tick"][0] > last_index and np.all(np.diff(rows["tick"]) > 0)
                    assert rows["tick"][0] >= cursor and rows["tick"][-1] < new_cursor
                    last_index = int(rows["tick"][-1])
                returned += len(rows)
                lost_total += lost
                cursor = new_cursor
                if not writer.is_alive() and ring.write_count == cursor:
                    break
            writer.join(30)
            assert writer.exitcode == 0
            assert cursor == n_rows == ring.write_count
            assert returned + lost_total == n_rows
            assert consistent(ring.latest()[None]).all() and int(ring.latest()["tick"]) == n_rows - 1
        finally:
            if writer.is_alive():
                writer.kill()
                writer.join()
            reader.close()


def test_rows_wrap_around_and_lost_rows_are_counted():
    with SharedRing.create(TICK_DTYPE, 8) as ring:
        row = empty_tick()
        for i in range(20):
            row["tick"] = i
            ring.write(row)
        rows, cursor, lost = ring.read_since(0)
        assert list(rows["tick"]) == list(range(12, 20))
        assert (cursor, lost) == (20, 12)
        rows, cursor, lost = ring.read_since(cursor)
        assert len(rows) == 0 and (cursor, lost) == (20, 0)


def test_max_rows_returns_the_oldest_first_and_stops_the_cursor_after_them():
    with SharedRing.create(TICK_DTYPE, 16) as ring:
        for i in range(10):
            ring.write(frame_tick(i))
        rows, cursor, lost = ring.read_since(2, max_rows=3)
        assert list(rows["tick"]) == [2, 3, 4] and cursor == 5 and lost == 0


def frame_tick(i: int) -> np.ndarray:
    row = empty_tick()
    row["tick"] = i
    return row


def test_a_row_being_written_is_skipped_and_counted_as_lost():
    with SharedRing.create(TICK_DTYPE, 4) as ring:
        for i in range(4):
            ring.write(frame_tick(i))
        # Freeze the writer half-way through overwriting slot 1 (row 1 -> row 5): odd sequence word.
        ring._seq[1] = 2 * 1 + 1
        rows, cursor, lost = ring.read_since(0)
        assert list(rows["tick"]) == [0, 2, 3] and cursor == 4 and lost == 1


def test_latest_is_none_before_the_first_row_then_a_copy_of_the_newest():
    with SharedRing.create(TICK_DTYPE, 4) as ring:
        assert ring.latest() is None
        for i in range(6):
            ring.write(frame_tick(i))
        latest = ring.latest()
        assert latest.shape == () and latest.dtype == TICK_DTYPE and int(latest["tick"]) == 5
        ring.write(frame_tick(6))
        assert int(latest["tick"]) == 5  # a copy, not a view into the ring


def test_handle_is_picklable_and_attaches_to_the_same_rows():
    with SharedRing.create(TICK_DTYPE, 4) as ring:
        ring.write(frame_tick(42))
        other = pickle.loads(pickle.dumps(ring.handle)).attach()
        try:
            assert int(other.latest()["tick"]) == 42
            with pytest.raises(RingError, match="only the process that created"):
                other.unlink()
        finally:
            other.close()
            other.close()


def test_attach_refuses_missing_or_mismatched_segments():
    with pytest.raises(RingError, match="does not exist"):
        SharedRing.attach(f"{NAME_PREFIX}no_such_ring", TICK_DTYPE, 4)
    with SharedRing.create(TICK_DTYPE, 4) as ring:
        with pytest.raises(RingError, match="holds 4 rows of .* expected 2 rows"):
            SharedRing.attach(ring.name, TICK_DTYPE, 2)
        with pytest.raises(RingError, match="too small"):
            SharedRing.attach(ring.name, FRAME_DTYPE, 4)


def test_bad_arguments_get_clear_errors():
    with pytest.raises(ValueError, match="capacity must be a positive integer"):
        SharedRing.create(TICK_DTYPE, 0)
    with SharedRing.create(TICK_DTYPE, 4) as ring:
        with pytest.raises(ValueError, match="ahead of the writer"):
            ring.read_since(1)
        with pytest.raises(ValueError, match=">= 0"):
            ring.read_since(-1)


def test_unlink_removes_the_segment_and_is_idempotent():
    ring = SharedRing.create(FRAME_DTYPE, 4)
    assert ring.name in own_segments()
    ring.unlink()
    ring.unlink()
    assert ring.name not in own_segments()
    assert ring.closed
