"""The UDP packet layout and sequence accounting (pure protocol, no sockets)."""

import math
import struct
import zlib

import numpy as np
import pytest

from hardware.udp import protocol as P

STATE = P.State(P.Status.HOLDING, 41, 12.5, (0.01, 0.02, 0.03), (0.1, 0.2, 0.3), 2.5, 7, 11.0, 12.25)


def test_every_packet_round_trips():
    cmd = P.Command(P.Mode.TRACK, (0.036, 0.015, 0.06), (0.0, 0.001, -0.002))
    header, body = P.unpack(P.pack_command(3, 9, 1.5, cmd))
    assert (header.type, header.session, header.seq, header.t_send_s) == (P.PacketType.COMMAND, 3, 9, 1.5)
    assert body == cmd
    header, body = P.unpack(P.pack_state(3, 10, 2.5, STATE))
    assert header.type == P.PacketType.STATE and body == STATE
    p = np.arange(60, dtype=float).reshape(4, 15) * 100.0
    header, body = P.unpack(P.pack_tactile(3, 11, 3.5, P.Tactile(5, 3.25, p)))
    assert header.type == P.PacketType.TACTILE and body.sensor_seq == 5 and np.array_equal(body.pressure_pa, p)
    header, body = P.unpack(P.pack_ping(3, 12, 4.5))
    assert header.type == P.PacketType.PING and body is None


def test_sizes_are_the_documented_ones():
    assert P.HEADER.size == 20 and P.TRAILER.size == 4
    assert P.PACKET_SIZE == {P.PacketType.COMMAND: 76, P.PacketType.STATE: 116, P.PacketType.TACTILE: 280,
                             P.PacketType.PING: 24}
    data = P.pack_command(0x01020304, 5, 0.0, P.Command(P.Mode.HOLD, (0, 0, 0), (0, 0, 0)))
    assert data[:4] == b"PC\x01\x01" and data[4:8] == bytes([4, 3, 2, 1])
    assert int.from_bytes(data[-4:], "little") == zlib.crc32(data[:-4])


def _reseal(data: bytes) -> bytes:
    return data[:-4] + struct.pack("<I", zlib.crc32(data[:-4]))


@pytest.mark.parametrize("mangle, kind, words", [
    (lambda d: d + bytes(400), "oversize", "larger than any packet"),
    (lambda d: d[:10], "malformed", "shorter than a header"),
    (lambda d: b"XX" + d[2:], "malformed", "bad magic"),
    (lambda d: _reseal(d[:2] + b"\x02" + d[3:]), "malformed", "protocol version 2"),
    (lambda d: _reseal(d[:3] + b"\x09" + d[4:]), "malformed", "unknown packet type 9"),
    (lambda d: _reseal(d[:-4] + b"\x00\x00" + d[-4:]), "malformed", "expected 76"),
    (lambda d: d[:30] + bytes([d[30] ^ 1]) + d[31:], "crc_errors", "bad CRC"),
    (lambda d: _reseal(d[:20] + b"\x07" + d[21:]), "malformed", "unknown command mode 7"),
    (lambda d: _reseal(d[:24] + struct.pack("<d", math.nan) + d[32:]), "invalid_values", "not finite"),
])
def test_a_bad_datagram_is_refused_and_classified(mangle, kind, words):
    good = P.pack_command(1, 1, 0.0, P.Command(P.Mode.TRACK, (0.0, 0.0, 0.05), (0.0, 0.0, 0.0)))
    with pytest.raises(P.PacketError, match=words) as err:
        P.unpack(mangle(good))
    assert err.value.kind == kind


def test_non_finite_state_or_tactile_values_are_refused():
    bad = P.State(P.Status.NONE, 1, 1.0, (0.0, math.inf, 0.0), (0, 0, 0), math.nan, 0, 0.0, 0.0)
    with pytest.raises(P.PacketError, match="slave state"):
        P.unpack(P.pack_state(1, 1, 0.0, bad))
    # the force may be NaN: a slave without a force sensor says so
    no_force = P.State(P.Status.NONE, 1, 1.0, (0.0, 0.0, 0.0), (0, 0, 0), math.nan, 0, 0.0, 0.0)
    assert math.isnan(P.unpack(P.pack_state(1, 1, 0.0, no_force))[1].force_N)
    p = np.zeros((4, 15))
    p[1, 2] = np.nan
    with pytest.raises(P.PacketError, match="tactile pressures"):
        P.unpack(P.pack_tactile(1, 1, 0.0, P.Tactile(0, 0.0, p)))
    p[1, 2] = -np.inf
    with pytest.raises(P.PacketError, match="tactile pressures"):
        P.unpack(P.pack_tactile(1, 1, 0.0, P.Tactile(0, 0.0, p)))


def test_saturated_elements_cross_the_link_flagged():
    p = np.full((4, 15), 5e3)
    saturated = np.zeros((4, 15), bool)
    saturated[2, 7] = True
    _, body = P.unpack(P.pack_tactile(1, 1, 0.0, P.Tactile(0, 0.0, p, saturated)))
    assert np.array_equal(body.saturated, saturated) and body.pressure_pa[2, 7] == np.inf
    assert np.array_equal(body.pressure_pa[~saturated], p[~saturated])


def test_sequence_tracker_accepts_only_news_and_counts_the_rest():
    t = P.SequenceTracker()
    accepted = [s for s in (0, 1, 1, 4, 3, 5, 2, 6) if t.accept(77, s)]
    assert accepted == [0, 1, 4, 5, 6]
    assert (t.duplicates, t.late, t.gaps, t.lost) == (1, 2, 2, 0)  # 2 and 3 came, late; nothing is missing
    assert not t.accept(77, 6) and t.accept(77, 9) and t.lost == 2


def test_sequence_tracker_wraps_and_follows_a_restarted_peer():
    t = P.SequenceTracker()
    assert t.accept(1, 2**32 - 2) and t.accept(1, 2**32 - 1) and t.accept(1, 0) and t.accept(1, 1)
    assert t.gaps == 0 and t.late == 0
    assert t.accept(2, 0) and t.restarts == 1  # a new session starts over instead of looking billions late


def test_status_words():
    assert P.status_text(P.Status.NONE) == "following"
    assert P.status_text(P.Status.HOLDING | P.Status.LINK_TIMEOUT) == "holding, link timeout"
    assert (P.Status.HOLDING).unrequested_hold is False
    assert (P.Status.HOLDING | P.Status.JUMP_REFUSED).unrequested_hold is True
