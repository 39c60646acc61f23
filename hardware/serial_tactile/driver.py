"""The TSI wire format: pure protocol code (framing, CRC, parsing), no I/O.

One binary frame per tactile sample, the same bytes over a serial line and over a USB endpoint.
Little-endian; for the 4 x 15 array a frame is 136 bytes:

======  =========  ==========================================================================
offset  size       field
======  =========  ==========================================================================
0       2          sync word ``A5 5A``
2       1          format version, 1
3       1          flags: bit 0 = the device dropped frames before this one (its buffer
                   overran); the other bits are reserved and sent as 0
4       1          rows (4, along x)
5       1          cols (15, along y)
6       4          seq: u32 frame counter, +1 per sampled frame, wraps to 0
10      4          device_time_us: u32 sampling instant on the device's clock in µs (wraps
                   every 71.6 min)
14      2 N        counts: N = rows * cols u16 raw converter readings, row-major
                   (element (i, j) at index i * cols + j)
14+2N   2          CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final
                   XOR) of bytes 2 .. 13+2N (everything after the sync word), little-endian
======  =========  ==========================================================================

:class:`FrameParser` turns an arbitrary byte stream (chunks cut anywhere) into frames. It hunts for
the sync word, checks the header and the CRC, and after any damage resynchronises on the next sync
word, so garbage, a truncated frame or a flipped bit costs the damaged frame and nothing else.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass

import numpy as np

SYNC = b"\xa5\x5a"
VERSION = 1
FLAG_OVERRUN = 0x01
HEADER = struct.Struct("<2sBBBBII")  # sync, version, flags, rows, cols, seq, device_time_us
CRC = struct.Struct("<H")
HEADER_SIZE = HEADER.size  # 14
U32 = 1 << 32


def frame_size(rows: int, cols: int) -> int:
    return HEADER_SIZE + 2 * rows * cols + CRC.size


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE (binascii's crc_hqx is this CRC, computed in C)."""
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True, slots=True)
class RawFrame:
    """One frame as the device sent it: counters on the device's clock, uncalibrated counts."""

    seq: int  # u32, as sent
    device_time_us: int  # u32, as sent
    flags: int
    counts: np.ndarray  # (rows, cols) uint16

    @property
    def overrun(self) -> bool:
        return bool(self.flags & FLAG_OVERRUN)


def encode_frame(seq: int, device_time_us: int, counts: np.ndarray, flags: int = 0) -> bytes:
    """The bytes a device sends for one frame (``seq`` and the time are taken modulo 2**32)."""
    counts = np.asarray(counts)
    if counts.ndim != 2:
        raise ValueError(f"counts must be a (rows, cols) array, got shape {counts.shape}")
    rows, cols = counts.shape
    if not (0 < rows < 256 and 0 < cols < 256):
        raise ValueError(f"a frame carries 1..255 rows and columns, got {rows} x {cols}")
    if counts.size and (counts.min() < 0 or counts.max() > 0xFFFF):
        raise ValueError("counts must fit in 16 bits (0..65535)")
    if not 0 <= flags < 256:
        raise ValueError(f"flags must be one byte, got {flags}")
    body = HEADER.pack(SYNC, VERSION, flags, rows, cols, seq % U32, device_time_us % U32)
    body += np.ascontiguousarray(counts, dtype="<u2").tobytes()
    return body + CRC.pack(crc16(body[2:]))


class FrameParser:
    """Frames out of a byte stream of one array shape, with counters of everything it threw away.

    Counters (cumulative): ``frames``; ``crc_errors`` (a whole frame whose CRC did not match);
    ``truncated`` (a frame cut short by the start of the next one, or left unfinished when the link
    was reset); ``header_errors`` (a sync word followed by an unknown version or another array
    shape: :attr:`last_header_problem` says which); ``garbage_bytes`` (bytes skipped while hunting for
    a sync word, including the remains of damaged frames).
    """

    def __init__(self, rows: int = 4, cols: int = 15):
        self.rows, self.cols = rows, cols
        self.size = frame_size(rows, cols)
        self._n = rows * cols
        self._buf = bytearray()
        self.frames = 0
        self.crc_errors = 0
        self.truncated = 0
        self.header_errors = 0
        self.garbage_bytes = 0
        self.last_header_problem = ""

    @property
    def pending_bytes(self) -> int:
        return len(self._buf)

    def reset(self) -> None:
        """Drop a partial frame (the link was reset: its rest will never come)."""
        if len(self._buf) >= len(SYNC) and self._buf.startswith(SYNC):
            self.truncated += 1
        else:
            self.garbage_bytes += len(self._buf)
        self._buf.clear()

    def feed(self, data: bytes | bytearray | memoryview) -> list[RawFrame]:
        buf = self._buf
        buf += data
        out: list[RawFrame] = []
        size = self.size
        pos = 0
        end = len(buf)
        while True:
            i = buf.find(SYNC, pos)
            if i < 0:
                # a trailing first sync byte may be the start of the next frame
                keep = 1 if end > pos and buf[end - 1] == SYNC[0] else 0
                self.garbage_bytes += end - pos - keep
                pos = end - keep
                break
            self.garbage_bytes += i - pos
            pos = i
            if end - i < HEADER_SIZE:
                break
            _, version, flags, rows, cols, seq, t_us = HEADER.unpack_from(buf, i)
            if version != VERSION or rows != self.rows or cols != self.cols:
                self.header_errors += 1
                self.last_header_problem = (
                    f"format version {version}, {rows} x {cols} elements (expected version {VERSION}, "
                    f"{self.rows} x {self.cols})")
                self.garbage_bytes += 1
                pos = i + 1
                continue
            if end - i < size:
                break
            (crc,) = CRC.unpack_from(buf, i + size - CRC.size)
            if crc != crc16(memoryview(buf)[i + 2:i + size - CRC.size]):
                nxt = buf.find(SYNC, i + 2, i + size)
                if nxt >= 0:
                    self.truncated += 1
                else:
                    self.crc_errors += 1
                self.garbage_bytes += 1
                pos = i + 1
                continue
            counts = np.frombuffer(bytes(buf[i + HEADER_SIZE:i + HEADER_SIZE + 2 * self._n]), dtype="<u2")
            out.append(RawFrame(seq, t_us, flags, counts.reshape(self.rows, self.cols)))
            self.frames += 1
            pos = i + size
        del buf[:pos]
        return out
