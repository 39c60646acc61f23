"""The TSI wire format, the byte-stream parser, the device clock mapping and the calibration files."""

import binascii

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hardware.interfaces import TactileConstraints
from hardware.serial_tactile.calibration import (
    Calibration,
    CalibrationError,
    equilibrate,
    load_equilibration,
    save_equilibration,
)
from hardware.serial_tactile.clock import DeviceClock
from hardware.serial_tactile.driver import FLAG_OVERRUN, SYNC, FrameParser, crc16, encode_frame, frame_size
from hardware.serial_tactile.stream import TactileStream

RNG = np.random.default_rng(7)


def counts(k: int = 0) -> np.ndarray:
    return (np.arange(60, dtype=np.uint16).reshape(4, 15) * 11 + k) % 4096


def frames(n: int, start: int = 0) -> list[bytes]:
    return [encode_frame(start + k, 1000 * (start + k), counts(k)) for k in range(n)]


def test_frame_layout_is_the_documented_one():
    data = encode_frame(0x01020304, 0xA0B0C0D0, counts(), flags=FLAG_OVERRUN)
    assert len(data) == frame_size(4, 15) == 136
    assert data[:2] == SYNC and data[2] == 1 and data[3] == FLAG_OVERRUN and data[4:6] == bytes([4, 15])
    assert data[6:10] == bytes([4, 3, 2, 1]) and data[10:14] == bytes([0xD0, 0xC0, 0xB0, 0xA0])
    assert np.array_equal(np.frombuffer(data[14:134], "<u2").reshape(4, 15), counts())
    assert int.from_bytes(data[134:], "little") == crc16(data[2:134])


def test_crc_is_ccitt_false():
    # the standard check value of CRC-16/CCITT-FALSE
    assert crc16(b"123456789") == 0x29B1
    assert crc16(b"123456789") == binascii.crc_hqx(b"123456789", 0xFFFF)


def test_encoder_refuses_what_the_format_cannot_carry():
    with pytest.raises(ValueError, match="16 bits"):
        encode_frame(0, 0, np.full((4, 15), 70000))
    with pytest.raises(ValueError, match="rows, cols"):
        encode_frame(0, 0, np.zeros(60))


def test_parser_reads_back_every_field():
    parser = FrameParser()
    (raw,) = parser.feed(encode_frame(5, 123456, counts(3), flags=FLAG_OVERRUN))
    assert (raw.seq, raw.device_time_us, raw.overrun) == (5, 123456, True)
    assert np.array_equal(raw.counts, counts(3))
    assert parser.pending_bytes == 0


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(min_value=1, max_value=200), min_size=1, max_size=40))
def test_frames_cut_anywhere_come_out_whole(cuts):
    stream = b"".join(frames(5))
    parser, out, pos = FrameParser(), [], 0
    for c in cuts + [len(stream)]:
        out += parser.feed(stream[pos:pos + c])
        pos += c
    assert [f.seq for f in out] == [0, 1, 2, 3, 4]
    assert parser.crc_errors == parser.truncated == parser.garbage_bytes == 0


def test_resynchronises_after_garbage_and_counts_it():
    garbage = bytes(RNG.integers(0, 256, 300, dtype=np.uint8)).replace(SYNC, b"xx") + SYNC[:1]
    parser = FrameParser()
    out = parser.feed(frames(1)[0] + garbage + b"".join(frames(2, start=1)))
    assert [f.seq for f in out] == [0, 1, 2]
    assert parser.garbage_bytes == len(garbage)
    assert parser.crc_errors == parser.truncated == 0


def test_a_flipped_bit_costs_that_frame_only():
    a, b, c = frames(3)
    damaged = bytearray(b)
    damaged[40] ^= 0x10
    parser = FrameParser()
    out = parser.feed(a + bytes(damaged) + c)
    assert [f.seq for f in out] == [0, 2]
    assert parser.crc_errors == 1 and parser.truncated == 0


def test_a_truncated_frame_is_told_apart_from_a_corrupt_one():
    a, b, c = frames(3)
    parser = FrameParser()
    out = parser.feed(a + b[:70] + c)
    assert [f.seq for f in out] == [0, 2]
    assert parser.truncated == 1 and parser.crc_errors == 0


def test_another_format_or_shape_is_reported_not_parsed():
    parser = FrameParser()
    other = encode_frame(0, 0, np.zeros((8, 16), dtype=np.uint16))
    out = parser.feed(other + frames(1)[0])
    assert [f.seq for f in out] == [0]
    assert parser.header_errors == 1 and "8 x 16" in parser.last_header_problem


def test_reset_drops_a_partial_frame_as_truncated():
    parser = FrameParser()
    parser.feed(frames(1)[0][:50])
    parser.reset()
    assert parser.truncated == 1 and parser.pending_bytes == 0
    assert [f.seq for f in parser.feed(frames(1, start=9)[0])] == [9]


# ---- device clock ------------------------------------------------------------------------------------


def test_clock_unwraps_the_32_bit_microsecond_counter():
    clock = DeviceClock()
    start = (1 << 32) - 5000
    assert clock.unwrap(start) == start
    assert clock.unwrap(1000) == (1 << 32) + 1000  # 6 ms later, across the wrap


def test_clock_maps_to_the_earliest_possible_arrival_and_follows_drift():
    clock = DeviceClock(window_s=1.0)
    rng = np.random.default_rng(1)
    offset, drift, latency = 123.0, 80e-6, 0.002
    errors = []
    for k in range(3000):  # 30 s at 100 frames/s
        t_true = 10.0 + k * 0.01
        device_us = round((t_true * (1 + drift) + offset) * 1e6) % (1 << 32)
        rx = t_true + latency + rng.exponential(0.001)
        mapped = clock.map(device_us, rx)
        assert mapped <= rx
        errors.append(mapped - (t_true + latency))
    steady = np.array(errors[200:])
    # never later than the minimum latency allows, and within 0.3 ms of it despite 80 ppm of drift
    assert steady.max() < 1e-4 and steady.min() > -3e-4


def test_clock_mapping_never_goes_back_in_time():
    clock = DeviceClock(window_s=0.05)
    mapped = [clock.map(k * 10_000, 1.0 + k * 0.01 + (0.02 if k == 5 else 0.0)) for k in range(20)]
    assert all(b >= a for a, b in zip(mapped, mapped[1:]))


# ---- the shared stream -------------------------------------------------------------------------------


def make_stream(tare=True):
    s = TactileStream(TactileConstraints(), Calibration.uniform(10.0, 100.0), tare_on_open=tare)
    s.start()
    return s


def test_stream_calibrates_tares_and_counts_gaps_duplicates_and_restarts():
    s = make_stream()
    base = np.full((4, 15), 150, dtype=np.uint16)
    s.feed(encode_frame(10, 0, base), 1.0)
    assert np.allclose(s.latest.pressure_pa, 0.0)  # the first frame is the zero
    s.feed(encode_frame(11, 10_000, base + 20), 1.01)
    assert np.allclose(s.latest.pressure_pa, 200.0)  # 20 counts at 10 Pa per count
    s.feed(encode_frame(14, 40_000, base), 1.04)
    s.feed(encode_frame(14, 40_000, base), 1.041)
    assert (s.frames_lost, s.duplicates) == (2, 1)
    seq_before = s.latest.seq
    s.feed(encode_frame(0, 5, base), 1.05)  # the device restarted: its counter and clock start over
    assert s.device_restarts == 1 and s.latest.seq == seq_before + 1
    assert s.latest.t_s <= 1.05


def test_stream_tare_survives_a_reconnection():
    s = make_stream()
    s.feed(encode_frame(0, 0, np.full((4, 15), 100, dtype=np.uint16)), 1.0)
    s.link_reset()
    s.feed(encode_frame(1, 10_000, np.full((4, 15), 130, dtype=np.uint16)), 1.2)
    assert np.allclose(s.latest.pressure_pa, 300.0)  # still zeroed at the first connection's frame


# ---- calibration files -------------------------------------------------------------------------------


def test_calibration_round_trips_through_its_file(tmp_path):
    gain = 20.0 + RNG.random((4, 15))
    offset = RNG.integers(20, 60, (4, 15)).astype(float)
    cal = Calibration(gain, offset, np.ones((4, 15)), device='TSI "7"')
    cal.save(tmp_path / "cal.toml")
    back = Calibration.load(tmp_path / "cal.toml")
    assert np.array_equal(back.gain_pa_per_count, gain) and np.array_equal(back.offset_counts, offset)
    assert back.device == 'TSI "7"'
    p = RNG.random((4, 15)) * 50e3
    assert np.allclose(back.pressure_pa(cal.counts_for(p)), p, atol=gain.max())


@pytest.mark.parametrize("text, problem", [
    ('format = "x"\nversion = 1\nrows = 4\ncols = 15\ngain_pa_per_count = 1.0', "not a TSI calibration file"),
    ('format = "palpation-tsi-calibration"\nversion = 9\nrows = 4\ncols = 15\ngain_pa_per_count = 1.0',
     "version 9 is not supported"),
    ('format = "palpation-tsi-calibration"\nversion = 1\nrows = 8\ncols = 15\ngain_pa_per_count = 1.0',
     "8 x 15 array"),
    ('format = "palpation-tsi-calibration"\nversion = 1\nrows = 4\ncols = 15', "gain_pa_per_count is missing"),
    ('format = "palpation-tsi-calibration"\nversion = 1\nrows = 4\ncols = 15\ngain_pa_per_count = [1.0, 2.0]',
     "shape"),
    ('format = "palpation-tsi-calibration"\nversion = 1\nrows = 4\ncols = 15\ngain_pa_per_count = -1.0', "> 0"),
    ('format = "palpation-tsi-calibration"\nversion = 1\nrows = 4\ncols = 15\ngain_pa_per_count = 1.0\ngian = 2',
     "unknown key 'gian'"),
    ("not = [toml", "cannot read"),
])
def test_a_bad_calibration_file_is_refused_with_the_reason(tmp_path, text, problem):
    path = tmp_path / "cal.toml"
    path.write_text(text)
    with pytest.raises(CalibrationError, match=problem) as err:
        Calibration.load(path)
    assert str(path) in str(err.value)


def test_equilibration_evens_out_element_sensitivity(tmp_path):
    cal = Calibration.uniform(10.0, 50.0)
    sensitivity = 1.0 + 0.1 * RNG.standard_normal((4, 15))
    loaded = 50.0 + 400.0 * sensitivity  # raw counts under one uniform load, per element
    frames_ = loaded + RNG.normal(0, 0.5, (20, 4, 15))
    factors = equilibrate(frames_, cal)
    save_equilibration(tmp_path / "eq.csv", factors, comment="bladder at 4 kPa\n2024-05-02")
    evened = cal.with_equilibration(load_equilibration(tmp_path / "eq.csv"), "eq.csv")
    p = evened.pressure_pa(loaded)
    assert p.std() / p.mean() < 0.005 < (cal.pressure_pa(loaded).std() / cal.pressure_pa(loaded).mean())


def test_equilibration_refuses_an_unloaded_element_and_bad_files(tmp_path):
    cal = Calibration.uniform(10.0, 50.0)
    loaded = np.full((4, 15), 450.0)
    loaded[2, 7] = 50.0
    with pytest.raises(CalibrationError, match="every element loaded"):
        equilibrate(loaded, cal)
    (tmp_path / "short.csv").write_text("1,1,1\n")
    with pytest.raises(CalibrationError, match="expected 4 rows of 15"):
        load_equilibration(tmp_path / "short.csv")
    (tmp_path / "text.csv").write_text("a,b\n")
    with pytest.raises(CalibrationError, match="line 1"):
        load_equilibration(tmp_path / "text.csv")
    with pytest.raises(CalibrationError, match="faulty"):
        cal.with_equilibration(np.full((4, 15), 3.0))
