"""The master/slave UDP packet layout: pure protocol code (packing, checking, sequence numbers), no I/O.

Every datagram is one packet, little-endian, no padding::

    header (20 bytes)
      0   2  magic b"PC"
      2   1  version (1)
      3   1  type: 1 COMMAND, 2 STATE, 3 TACTILE, 4 PING
      4   4  session: u32 chosen at random when the sender starts (a restart resets sequence tracking)
      8   4  seq: u32, +1 per packet of this type from this sender, wraps
      12  8  t_send_s: f64, the sender's monotonic clock when it sent the packet
    body (by type, below)
    trailer (4 bytes)
      CRC-32 (zlib) of header + body

    COMMAND  master -> slave, 52-byte body (76-byte packet), at the loop rate
      0   1  mode: 0 HOLD (stop where you are), 1 TRACK (follow the reference)
      1   3  reserved, 0
      4  24  reference position X_r: 3 x f64, m, tissue frame
      28 24  reference velocity: 3 x f64, m/s

    STATE    slave -> master, 92-byte body (116-byte packet), at the slave's rate and in reply to PING
      0   1  status flags: 1 HOLDING, 2 LINK_TIMEOUT, 4 JUMP_REFUSED, 8 ROBOT_FAULT, 16 PING_REPLY,
             32 LIMITED, 64 FORCE_LIMIT, 128 SENSOR_LOST
      1   3  reserved, 0
      4   4  robot_seq: u32 the robot's reading counter
      8   8  t_sample_s: f64, slave clock, when X_s was measured
      16 24  X_s: 3 x f64, m
      40 24  velocity: 3 x f64, m/s
      64  8  force_N: f64 the slave's force measurement along z, NaN when it has none
      72  4  echo_seq: u32 seq of the newest COMMAND (or the PING answered) received
      76  8  echo_t_send_s: f64 its t_send_s (master clock)
      84  8  echo_t_recv_s: f64 when the slave received it (slave clock)

    TACTILE  slave -> master, 256-byte body (280-byte packet): a sensor on the slave side, forwarded
      0   4  sensor_seq: u32
      4   8  t_sample_s: f64 (slave clock, already mapped from the sensor's own clock)
      12  1  rows (4)    13  1  cols (15)    14  2  reserved, 0
      16 240 pressure: rows x cols f32, Pa, row-major, calibrated and tared; +inf marks a saturated
             element (its converter at its limit: the load is unknown); NaN and -inf are refused

    PING     anyone allowed -> slave, empty body (24-byte packet): answered with a STATE (PING_REPLY set)
             that echoes it; it does not count as a command (it neither feeds nor resets the watchdog)

The echo fields give the master the round trip and the clock offset without synchronised clocks (the
NTP calculation: see :class:`hardware.udp.link.LinkClock`).
"""

from __future__ import annotations

import enum
import ipaddress
import math
import struct
import zlib
from dataclasses import dataclass

import numpy as np

MAGIC = b"PC"
VERSION = 1
HEADER = struct.Struct("<2sBBIId")
TRAILER = struct.Struct("<I")
COMMAND_BODY = struct.Struct("<B3x3d3d")
STATE_BODY = struct.Struct("<B3xId3d3ddIdd")
TACTILE_HEAD = struct.Struct("<IdBB2x")
U32 = 1 << 32
ROWS, COLS = 4, 15
TACTILE_BODY_SIZE = TACTILE_HEAD.size + 4 * ROWS * COLS
MAX_PACKET = HEADER.size + TACTILE_BODY_SIZE + TRAILER.size  # the largest packet the protocol defines
RECV_BUFFER = 2048  # anything that fills it is oversize for certain


class PacketType(enum.IntEnum):
    COMMAND = 1
    STATE = 2
    TACTILE = 3
    PING = 4


class Mode(enum.IntEnum):
    HOLD = 0
    TRACK = 1


class Status(enum.IntFlag):
    NONE = 0
    HOLDING = 1  # the robot is holding (commanded or not)
    LINK_TIMEOUT = 2  # commands stopped arriving: the slave latched a hold
    JUMP_REFUSED = 4  # a reference too far from the robot was refused after a latched hold
    ROBOT_FAULT = 8  # the robot behind the slave is not connected
    PING_REPLY = 16  # this state answers a PING
    LIMITED = 32  # the slave cut the newest reference to its own workspace or speed limit
    FORCE_LIMIT = 64  # the slave's own force limit latched: it moves only up, away from the tissue
    SENSOR_LOST = 128  # its own array stopped reading (silent, frozen, or not reading the tissue): only up

    @property
    def unrequested_hold(self) -> bool:
        """The slave is not doing what the master asks (it held on its own, or cannot move)."""
        return bool(self & (Status.LINK_TIMEOUT | Status.JUMP_REFUSED | Status.ROBOT_FAULT | Status.FORCE_LIMIT
                            | Status.SENSOR_LOST))


def status_text(status: Status) -> str:
    """The status flags in words ("following" when the slave does what it is told)."""
    names = [flag.name.lower().replace("_", " ") for flag in Status if flag and flag in status and flag.name]
    return ", ".join(names) or "following"


BODY_SIZE = {PacketType.COMMAND: COMMAND_BODY.size, PacketType.STATE: STATE_BODY.size,
             PacketType.TACTILE: TACTILE_BODY_SIZE, PacketType.PING: 0}
PACKET_SIZE = {t: HEADER.size + n + TRAILER.size for t, n in BODY_SIZE.items()}


class PacketError(ValueError):
    """A datagram that is not a valid packet; ``kind`` is the counter it belongs to."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind = kind  # "oversize" | "malformed" | "crc_errors" | "invalid_values"


@dataclass(frozen=True, slots=True)
class Header:
    type: PacketType
    session: int
    seq: int
    t_send_s: float


@dataclass(frozen=True, slots=True)
class Command:
    mode: Mode
    position_m: tuple[float, float, float]
    velocity_m_s: tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class State:
    status: Status
    robot_seq: int
    t_sample_s: float
    position_m: tuple[float, float, float]
    velocity_m_s: tuple[float, float, float]
    force_N: float
    echo_seq: int
    echo_t_send_s: float
    echo_t_recv_s: float


@dataclass(frozen=True, slots=True)
class Tactile:
    sensor_seq: int
    t_sample_s: float
    pressure_pa: np.ndarray  # (ROWS, COLS) float64; +inf where saturated
    saturated: np.ndarray | None = None  # (ROWS, COLS) bool


def _seal(header: bytes, body: bytes) -> bytes:
    data = header + body
    return data + TRAILER.pack(zlib.crc32(data))


def _header(kind: PacketType, session: int, seq: int, t_send_s: float) -> bytes:
    return HEADER.pack(MAGIC, VERSION, kind, session % U32, seq % U32, t_send_s)


def pack_command(session: int, seq: int, t_send_s: float, cmd: Command) -> bytes:
    return _seal(_header(PacketType.COMMAND, session, seq, t_send_s),
                 COMMAND_BODY.pack(cmd.mode, *cmd.position_m, *cmd.velocity_m_s))


def pack_state(session: int, seq: int, t_send_s: float, st: State) -> bytes:
    return _seal(_header(PacketType.STATE, session, seq, t_send_s),
                 STATE_BODY.pack(int(st.status), st.robot_seq % U32, st.t_sample_s, *st.position_m,
                                 *st.velocity_m_s, st.force_N, st.echo_seq % U32, st.echo_t_send_s,
                                 st.echo_t_recv_s))


def pack_tactile(session: int, seq: int, t_send_s: float, tac: Tactile) -> bytes:
    p = np.asarray(tac.pressure_pa)
    if p.shape != (ROWS, COLS):
        raise ValueError(f"a TACTILE packet carries a {ROWS} x {COLS} array, got shape {p.shape}")
    if tac.saturated is not None and tac.saturated.any():
        p = np.where(tac.saturated, np.inf, p)
    return _seal(_header(PacketType.TACTILE, session, seq, t_send_s),
                 TACTILE_HEAD.pack(tac.sensor_seq % U32, tac.t_sample_s, ROWS, COLS) + p.astype("<f4").tobytes())


def pack_ping(session: int, seq: int, t_send_s: float) -> bytes:
    return _seal(_header(PacketType.PING, session, seq, t_send_s), b"")


def _finite(values, what: str) -> None:
    if not all(math.isfinite(v) for v in values):
        raise PacketError("invalid_values", f"{what} is not finite")


def unpack(data: bytes | bytearray | memoryview) -> tuple[Header, Command | State | Tactile | None]:
    """Check and decode one datagram; raises :class:`PacketError` naming what is wrong with it."""
    n = len(data)
    if n > MAX_PACKET:
        raise PacketError("oversize", f"{n}-byte datagram, larger than any packet ({MAX_PACKET} bytes)")
    if n < HEADER.size + TRAILER.size:
        raise PacketError("malformed", f"{n}-byte datagram, shorter than a header")
    magic, version, kind, session, seq, t_send = HEADER.unpack_from(data, 0)
    if magic != MAGIC:
        raise PacketError("malformed", "not a palpation-console packet (bad magic)")
    if version != VERSION:
        raise PacketError("malformed", f"protocol version {version}, this software speaks {VERSION}")
    try:
        ptype = PacketType(kind)
    except ValueError:
        raise PacketError("malformed", f"unknown packet type {kind}") from None
    if n != PACKET_SIZE[ptype]:
        raise PacketError("malformed", f"{ptype.name} packet of {n} bytes, expected {PACKET_SIZE[ptype]}")
    (crc,) = TRAILER.unpack_from(data, n - TRAILER.size)
    if crc != zlib.crc32(memoryview(data)[: n - TRAILER.size]):
        raise PacketError("crc_errors", f"{ptype.name} packet with a bad CRC")
    _finite((t_send,), "the send time")
    header = Header(ptype, session, seq, t_send)
    off = HEADER.size
    if ptype == PacketType.COMMAND:
        mode, *v = COMMAND_BODY.unpack_from(data, off)
        if mode not in (Mode.HOLD, Mode.TRACK):
            raise PacketError("malformed", f"unknown command mode {mode}")
        _finite(v, "the commanded reference")
        return header, Command(Mode(mode), (v[0], v[1], v[2]), (v[3], v[4], v[5]))
    if ptype == PacketType.STATE:
        (status, robot_seq, t_sample, x0, x1, x2, v0, v1, v2, force, echo_seq, echo_send,
         echo_recv) = STATE_BODY.unpack_from(data, off)
        _finite((t_sample, x0, x1, x2, v0, v1, v2, echo_send, echo_recv), "the slave state")
        return header, State(Status(status), robot_seq, t_sample, (x0, x1, x2), (v0, v1, v2), force,
                             echo_seq, echo_send, echo_recv)
    if ptype == PacketType.TACTILE:
        sensor_seq, t_sample, rows, cols = TACTILE_HEAD.unpack_from(data, off)
        if (rows, cols) != (ROWS, COLS):
            raise PacketError("malformed", f"TACTILE packet for a {rows} x {cols} array, expected {ROWS} x {COLS}")
        p = np.frombuffer(data, dtype="<f4", count=ROWS * COLS, offset=off + TACTILE_HEAD.size)
        _finite((t_sample,), "the tactile sample time")
        p = p.reshape(ROWS, COLS).astype(float)
        saturated = p == np.inf
        if not np.isfinite(p[~saturated]).all():
            raise PacketError("invalid_values", "the tactile pressures are NaN or -inf")
        return header, Tactile(sensor_seq, t_sample, p, saturated)
    return header, None


def is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


class SequenceTracker:
    """Per-stream sequence accounting: accept only packets newer than the newest accepted one.

    ``gaps`` counts sequence numbers skipped when a newer packet arrived; ``late`` the ones that arrived
    after all (reordered) and were dropped as superseded; ``lost`` = gaps - late is what never came.
    A new ``session`` (the peer restarted) starts the count afresh.
    """

    def __init__(self):
        self.session: int | None = None
        self.newest: int | None = None
        self.accepted = 0
        self.duplicates = 0
        self.late = 0
        self.gaps = 0
        self.restarts = 0

    @property
    def lost(self) -> int:
        return max(0, self.gaps - self.late)

    def accept(self, session: int, seq: int) -> bool:
        if session != self.session:
            if self.session is not None:
                self.restarts += 1
            self.session, self.newest = session, None
        if self.newest is not None:
            step = (seq - self.newest) % U32
            if step == 0:
                self.duplicates += 1
                return False
            if step >= U32 // 2:
                self.late += 1
                return False
            self.gaps += step - 1
        self.newest = seq
        self.accepted += 1
        return True
