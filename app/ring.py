"""A single-writer, multi-reader ring of numpy structured rows in shared memory.

The controller process writes one tick row per period; the GUI process (and anything else that attaches)
reads them without locks and without ever slowing the writer down.

Layout of the shared segment::

    header   int64[8]      magic, capacity, itemsize, write_count, (reserved)
    seq      int64[cap]    per-slot sequence word (the seqlock)
    rows     dtype[cap]    the data

Row ``n`` (counted from 0 since the ring was created) lives in slot ``n % cap`` with generation
``g = n // cap``. The writer marks the slot busy (``seq = 2g + 1``), copies the row, marks it complete
(``seq = 2g + 2``) and only then publishes ``write_count = n + 1``. A reader that wants row ``n`` accepts
the copy only if the slot's sequence word read before AND after the copy equals ``2g + 2``; otherwise the
writer lapped it (the row was overwritten) and the row is counted as lost, never returned torn.

Ordering assumption: this relies on stores becoming visible in program order and loads not being
reordered with each other (x86-64's TSO model; the header and sequence words are written through
separate interpreter operations, which compilers cannot reorder). On weakly ordered CPUs (ARM) the same
code works in practice because every step crosses the interpreter, but it is not guaranteed there.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from dataclasses import dataclass
from multiprocessing import shared_memory

import numpy as np

NAME_PREFIX = "palp_"  # every segment this module creates starts with it (tests look for leftovers)

_MAGIC = 0x50414C5052494E47  # "PALPRING"
_HEADER_WORDS = 8
_H_MAGIC, _H_CAPACITY, _H_ITEMSIZE, _H_WRITE_COUNT = 0, 1, 2, 3
_ALIGN = 64  # keep the row block cache-line aligned


class RingError(RuntimeError):
    """The segment does not exist, or does not hold a ring of the expected shape."""


@dataclass(frozen=True)
class RingHandle:
    """What another process needs to attach to a ring (picklable)."""

    name: str
    dtype: np.dtype
    capacity: int

    def attach(self) -> SharedRing:
        return SharedRing.attach(self.name, self.dtype, self.capacity)


def _layout(dtype: np.dtype, capacity: int) -> tuple[int, int]:
    seq_offset = _HEADER_WORDS * 8
    rows_offset = seq_offset + capacity * 8
    rows_offset = (rows_offset + _ALIGN - 1) // _ALIGN * _ALIGN
    return rows_offset, rows_offset + capacity * dtype.itemsize


class SharedRing:
    """Use :meth:`create` in the owning process and :meth:`attach` (or ``handle.attach()``) elsewhere.

    Only one process may call :meth:`write`; any number may read. Readers keep their own cursor (the
    count of rows they have consumed), so several readers never disturb each other.
    """

    def __init__(self, shm: shared_memory.SharedMemory, dtype: np.dtype, capacity: int, owner: bool):
        self._shm = shm
        self._owner = owner
        self._unlinked = False
        self.dtype = dtype
        self.capacity = capacity
        rows_offset, _ = _layout(dtype, capacity)
        self._header = np.ndarray((_HEADER_WORDS,), dtype=np.int64, buffer=shm.buf, offset=0)
        self._seq = np.ndarray((capacity,), dtype=np.int64, buffer=shm.buf, offset=_HEADER_WORDS * 8)
        self._rows = np.ndarray((capacity,), dtype=dtype, buffer=shm.buf, offset=rows_offset)
        # The writer's own count: it never has to read back what it published.
        self._written = int(self._header[_H_WRITE_COUNT])

    # ---- construction ---------------------------------------------------------------------------

    @classmethod
    def create(cls, dtype: np.dtype | type | str, capacity: int) -> SharedRing:
        dtype = np.dtype(dtype)
        if not isinstance(capacity, int | np.integer) or capacity < 1:
            raise ValueError(f"ring capacity must be a positive integer, got {capacity!r}")
        if dtype.itemsize == 0:
            raise ValueError(f"ring dtype {dtype} has no data")
        capacity = int(capacity)
        _, size = _layout(dtype, capacity)
        name = f"{NAME_PREFIX}{os.getpid()}_{secrets.token_hex(4)}"
        shm = shared_memory.SharedMemory(name=name, create=True, size=size)
        ring = cls(shm, dtype, capacity, owner=True)
        ring._seq[:] = 0  # generation 0 complete would be 2: 0 means "never written"
        ring._header[_H_MAGIC] = _MAGIC
        ring._header[_H_CAPACITY] = capacity
        ring._header[_H_ITEMSIZE] = dtype.itemsize
        ring._header[_H_WRITE_COUNT] = 0
        return ring

    @classmethod
    def attach(cls, name: str, dtype: np.dtype | type | str, capacity: int) -> SharedRing:
        dtype = np.dtype(dtype)
        try:
            shm = shared_memory.SharedMemory(name=name, create=False)
        except FileNotFoundError:
            raise RingError(f"shared-memory ring {name!r} does not exist "
                            "(its owner closed it or never created it)") from None
        header = np.ndarray((_HEADER_WORDS,), dtype=np.int64, buffer=shm.buf, offset=0)
        problem = None
        if shm.size < _layout(dtype, capacity)[1]:
            problem = f"is {shm.size} bytes, too small for {capacity} rows of {dtype.itemsize} bytes"
        elif int(header[_H_MAGIC]) != _MAGIC:
            problem = "is not a ring buffer"
        elif int(header[_H_CAPACITY]) != capacity or int(header[_H_ITEMSIZE]) != dtype.itemsize:
            problem = (f"holds {int(header[_H_CAPACITY])} rows of {int(header[_H_ITEMSIZE])} bytes, "
                       f"expected {capacity} rows of {dtype.itemsize} bytes")
        del header
        if problem:
            shm.close()
            raise RingError(f"shared-memory segment {name!r} {problem}")
        return cls(shm, dtype, capacity, owner=False)

    @property
    def name(self) -> str:
        return self._shm.name

    @property
    def handle(self) -> RingHandle:
        return RingHandle(self._shm.name, self.dtype, self.capacity)

    # ---- writer ---------------------------------------------------------------------------------

    def write(self, row) -> None:
        """Append one row (a 0-d structured array, a 1-element view, or a tuple in field order)."""
        n = self._written
        slot = n % self.capacity
        generation = n // self.capacity
        self._seq[slot] = 2 * generation + 1
        self._rows[slot] = row
        self._seq[slot] = 2 * generation + 2
        self._written = n + 1
        self._header[_H_WRITE_COUNT] = n + 1

    # ---- readers --------------------------------------------------------------------------------

    @property
    def write_count(self) -> int:
        """Rows written since the ring was created (the cursor of a reader that is fully caught up)."""
        return int(self._header[_H_WRITE_COUNT])

    def read_since(self, cursor: int, max_rows: int | None = None) -> tuple[np.ndarray, int, int]:
        """Copy the rows written since ``cursor``: ``(rows, new_cursor, n_lost)``.

        ``rows`` holds only complete rows, oldest first. ``n_lost`` counts the rows between ``cursor``
        and ``new_cursor`` that were overwritten before they could be read (the reader fell more than
        ``capacity`` rows behind). With ``max_rows`` the oldest rows are returned first and the cursor
        stops after them, so a reader can catch up in bounded pieces.
        """
        end = self.write_count
        if cursor > end:
            raise ValueError(f"cursor {cursor} is ahead of the writer ({end} rows written)")
        if cursor < 0:
            raise ValueError(f"cursor must be >= 0, got {cursor}")
        lost = 0
        if end - cursor > self.capacity:
            lost = end - self.capacity - cursor
            cursor = end - self.capacity
        if max_rows is not None and end - cursor > max_rows:
            end = cursor + max(0, int(max_rows))
        if end == cursor:
            return np.empty(0, dtype=self.dtype), end, lost
        index = np.arange(cursor, end, dtype=np.int64)
        slots = index % self.capacity
        expected = 2 * (index // self.capacity) + 2
        before = self._seq[slots]  # fancy indexing copies: this is the first read of the seqlock
        rows = self._rows[slots]
        after = self._seq[slots]
        complete = (before == expected) & (after == expected)
        if complete.all():
            return rows, end, lost
        return rows[complete], end, lost + int(np.count_nonzero(~complete))

    def latest(self) -> np.ndarray | None:
        """A copy (0-d array) of the newest complete row, or ``None`` if nothing was written yet."""
        for _ in range(8):
            end = self.write_count
            if end == 0:
                return None
            n = end - 1
            slot = n % self.capacity
            expected = 2 * (n // self.capacity) + 2
            if int(self._seq[slot]) != expected:
                continue  # lapped between reading the count and the slot: look again
            row = self._rows[slot : slot + 1].copy().reshape(())
            if int(self._seq[slot]) == expected:
                return row
        # Only a writer lapping a whole ring between two reads (capacity 1, say) gets here.
        raise RingError(f"ring {self.name!r}: the writer kept overwriting the newest row; cannot read it")

    # ---- lifetime -------------------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._rows is None

    def close(self) -> None:
        """Detach this process's mapping; safe to call twice. The owner should also :meth:`unlink`."""
        if self._rows is None:
            return
        # The numpy views export the mapping's buffer; they must go before the mapping can be closed.
        self._header = self._seq = self._rows = None
        self._shm.close()

    def unlink(self) -> None:
        """Detach and remove the segment from the system (owner only); safe to call twice."""
        if not self._owner:
            raise RingError("only the process that created a ring may unlink it")
        self.close()
        if not self._unlinked:
            self._unlinked = True
            with contextlib.suppress(FileNotFoundError):  # the resource tracker removed it after a crash
                self._shm.unlink()

    def __enter__(self) -> SharedRing:
        return self

    def __exit__(self, *exc) -> None:
        if self._owner:
            self.unlink()
        else:
            self.close()

    def __repr__(self) -> str:
        state = "closed" if self.closed else f"{self.write_count} written"
        return f"SharedRing({self.name!r}, capacity={self.capacity}, {state})"
