"""A session's recorded streams as tidy tables: one observation per row, one variable per column.

What pandas, R or a spreadsheet expects of the three streams of a session file (docs/session-format.md):

* ``ticks``: one row per 1 kHz control period; each 3-vector becomes three columns (``x_slave_m_x``, ...).
* ``frames``: one row per tactile frame and element (``row`` along the tissue's x, ``col`` along y, as the
  face's arrays), the frame's own columns repeated on each of its 60 rows.
* ``levels``: one row per recorded force level and element, likewise.

Each table gains ``utc_ns`` after ``t_s``: UTC at that loop time, in ns since the epoch, through the pairs of
clocks the session stores (:meth:`session.reader.Session.utc_ns`).

Tables are produced in pieces of at most ``CHUNK_ROWS`` rows, so an hour-long session (3.6 million ticks,
21 million frame rows) is written in bounded memory. Columns keep the file's units (SI) and types.
"""

from __future__ import annotations

import contextlib
import csv
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

TABLES = ("ticks", "frames", "levels")
CHUNK_ROWS = 200_000


class TableError(RuntimeError):
    """A table could not be written; the message names the file and why."""



@contextlib.contextmanager
def written_whole(path: Path, error: type[Exception]) -> Iterator[Path]:
    """A file beside ``path`` to write, renamed onto it when the block ends: never a half-written export under
    the final name. A disk's error becomes ``error`` (one line); any failure (a damaged session found half-way,
    an interrupt) removes the partial file."""
    partial = path.with_name(path.name + ".partial")
    try:
        yield partial
        os.replace(partial, path)
    except OSError as err:
        partial.unlink(missing_ok=True)
        raise error(f"cannot write {path}: {err.strerror or err}") from None
    except BaseException:
        partial.unlink(missing_ok=True)
        raise

def _flat_columns(rows: np.ndarray, names: list[str], session) -> dict[str, np.ndarray]:
    """Scalar fields as they are, with UTC after the loop time, 3-vectors as three columns; per-element fields
    are left to the caller."""
    columns = {}
    for name in names:
        values = rows[name]
        if name == "t_s":
            columns[name] = values
            columns["utc_ns"] = session.utc_ns(values)
        elif values.ndim == 1:
            columns[name] = values
        else:
            for k, axis in enumerate("xyz"):
                columns[f"{name}_{axis}"] = values[:, k]
    return columns


def _per_element(rows: np.ndarray) -> tuple[list[str], list[str]]:
    """(the fields with one value per row, the fields with one per element) of a structured array."""
    whole, element = [], []
    for name in rows.dtype.names:
        (element if rows.dtype[name].ndim == 2 else whole).append(name)
    return whole, element


def _long(rows: np.ndarray, session) -> dict[str, np.ndarray]:
    """``rows`` with an element grid per field as one row per element (row-major over the face)."""
    whole, element = _per_element(rows)
    shape = rows.dtype[element[0]].shape
    per_row = shape[0] * shape[1]
    columns = {name: np.repeat(values, per_row) for name, values in _flat_columns(rows, whole, session).items()}
    grid_row, grid_col = np.indices(shape)
    columns["row"] = np.tile(grid_row.ravel(), len(rows)).astype(np.int16)
    columns["col"] = np.tile(grid_col.ravel(), len(rows)).astype(np.int16)
    for name in element:
        columns[name] = rows[name].reshape(len(rows), per_row).ravel()
    return columns


def table_chunks(session, name: str, chunk_rows: int = CHUNK_ROWS) -> Iterator[dict[str, np.ndarray]]:
    """The table ``name`` (one of :data:`TABLES`) of an open session, as column dictionaries of at most
    about ``chunk_rows`` rows each (at least one, possibly empty, so the columns are always known)."""
    if name == "ticks":
        step = max(1, chunk_rows)
        start = 0
        while True:
            rows = session.tick_rows(start, start + step)
            yield _flat_columns(rows, list(rows.dtype.names), session)
            start += step
            if start >= session.n_ticks:
                return
    if name == "frames":
        step = max(1, chunk_rows // 60)
        start = 0
        while True:
            yield _long(session.frames(start, start + step), session)
            start += step
            if start >= session.n_frames:
                return
    if name == "levels":
        levels = session.levels
        step = max(1, chunk_rows // 60)
        for start in range(0, max(len(levels), 1), step):
            yield _long(levels[start:start + step], session)
        return
    raise ValueError(f"unknown table {name!r} (known: {', '.join(TABLES)})")


def _formats(columns: dict[str, np.ndarray]) -> list[str]:
    """Each column's text form: integers whole, float32 in the 9 digits that give it back, float64 in 17."""
    out = []
    for values in columns.values():
        if values.dtype.kind in "iub":
            out.append("%d")
        elif values.dtype == np.float32:
            out.append("%.9g")
        else:
            out.append("%.17g")
    return out


def write_csv(session, folder: Path, tables: tuple[str, ...] = TABLES) -> list[Path]:
    """Each table as ``folder/<session stem>-<table>.csv``, with a header row; NaN written as ``nan``
    (pandas reads it back as NaN). Returns the paths written."""
    return _write(session, folder, tables, ".csv", _write_csv_table)


def write_parquet(session, folder: Path, tables: tuple[str, ...] = TABLES) -> list[Path]:
    """Each table as ``folder/<session stem>-<table>.parquet`` (needs pyarrow: ``pip install
    'palpation-console[parquet]'``)."""
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        raise TableError("Parquet needs pyarrow, which is not installed: pip install "
                         "'palpation-console[parquet]' (or write CSV)") from None
    return _write(session, folder, tables, ".parquet", _write_parquet_table)


def _write(session, folder: Path, tables, suffix: str, writer) -> list[Path]:
    if not folder.is_dir():
        raise TableError(f"{folder}: no such folder")
    written = []
    for name in tables:
        path = folder / f"{session.path.stem}-{name}{suffix}"
        with written_whole(path, TableError) as partial:
            writer(table_chunks(session, name), partial)
        written.append(path)
    return written


def _write_csv_table(chunks: Iterator[dict[str, np.ndarray]], path: Path) -> None:
    with open(path, "w", newline="", encoding="utf-8") as out:
        header = False
        for columns in chunks:
            if not header:
                csv.writer(out).writerow(columns)
                header = True
            if len(next(iter(columns.values()))):
                np.savetxt(out, np.column_stack([v.astype(object) if v.dtype.kind in "iub" else v
                                                 for v in columns.values()]),
                           fmt=_formats(columns), delimiter=",")


def _write_parquet_table(chunks: Iterator[dict[str, np.ndarray]], path: Path) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    writer = None
    try:
        for columns in chunks:
            table = pa.table(columns)
            if writer is None:
                writer = pq.ParquetWriter(str(path), table.schema)
            writer.write_table(table)
    finally:
        if writer is not None:
            writer.close()
