"""docs/session-format.md against session/format.py: the page's layout tables say what the code writes.

The part of the page between the two ``checked layout`` markers is read as tables and compared with the
code, in both directions:

* every dataset of :data:`session.format.TABLES` has a table with one row per column of its dtype, in the
  dtype's order, each with the type, shape and unit the dtype gives (the unit is read off the column's
  name, which carries it) and a description that is not empty; a column the page names and the dtype does
  not is an error too;
* the attribute table lists exactly the attributes a file written by :class:`session.writer.SessionRecorder`
  carries, object by object, and each of them is named in format.py's docstring (the one place the layout
  is defined);
* the event kinds are exactly :class:`session.format.EventKind`'s, the coded columns' codes are those of
  :data:`session.format.TICK_CODES`, the added columns and datasets those of
  :data:`session.format.ADDED_COLUMNS` and :data:`session.format.ADDED_TABLES`;
* nothing in backticks there names something the code does not have.

So adding a column to a dtype, an attribute to the writer, or an event kind, without adding it to the page,
fails here. ``python -m tests.session.test_format_doc`` prints the tables as the code has them now (with the
descriptions to fill in) to paste into the page.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import h5py
import numpy as np

import session.format as fmt
from control import telemetry
from session.info import SessionInfo
from session.writer import SessionRecorder

REPO = Path(__file__).resolve().parents[2]
PAGE = REPO / "docs" / "session-format.md"
BEGIN = "<!-- checked layout: begin -->"
END = "<!-- checked layout: end -->"

# Field names carry their units (control/telemetry.py); the longest matching suffix wins.
UNITS = (("_m_s", "m/s"), ("_m2", "m²"), ("_pa", "Pa"), ("_hz", "Hz"), ("_N", "N"), ("_ns", "ns"), ("_s", "s"),
         ("_m", "m"))
NO_UNIT = "—"
SCALAR = "—"


def unit_of(name: str) -> str:
    base = re.sub(r"_(min|max)$", "", name)  # overview columns: <channel>_min, <channel>_max
    for suffix, unit in UNITS:
        if base.endswith(suffix):
            return unit
    return NO_UNIT


def type_of(dtype: np.dtype) -> str:
    base = dtype.base
    if base.kind == "S":
        return f"bytes ({base.itemsize})"
    return base.name


def shape_of(dtype: np.dtype) -> str:
    return " × ".join(str(n) for n in dtype.shape) if dtype.shape else SCALAR


def expected_columns(dtype: np.dtype) -> list[tuple[str, str, str, str]]:
    """(name, type, shape, unit) of every column of a table's dtype, in order."""
    return [(name, type_of(dtype[name]), shape_of(dtype[name]), unit_of(name)) for name in dtype.names]


def codes_text(codes: dict[str, str]) -> str:
    return ", ".join(f"{code} {name}" for code, name in codes.items())


def written_attributes(folder: Path) -> dict[str, set[str]]:
    """Object path -> the attribute names a file written by the recorder carries there."""
    path = folder / "empty.h5"
    recorder = SessionRecorder(path, SessionInfo(config={}, calibration={}), min_free_bytes=0)
    recorder.close()
    found: dict[str, set[str]] = {}
    with h5py.File(path, "r") as f:
        found["/"] = set(f.attrs)

        def visit(name, obj):
            if len(obj.attrs):
                found["/" + name] = set(obj.attrs)

        f.visititems(visit)
    return found


# ---- reading the page ----------------------------------------------------------------------------------


def checked_part() -> str:
    text = PAGE.read_text(encoding="utf-8")
    assert text.count(BEGIN) == 1 and text.count(END) == 1, f"{PAGE.name} must hold {BEGIN} and {END} once each"
    return text.split(BEGIN, 1)[1].split(END, 1)[0]


def tables(part: str) -> dict[str, list[list[str]]]:
    """Heading -> the rows (cells, stripped) of the table under it, header and rule left out."""
    out: dict[str, list[list[str]]] = {}
    heading = None
    for line in part.splitlines():
        if line.startswith("#"):
            heading = line.lstrip("#").strip()
            out[heading] = []
        elif line.startswith("|") and heading is not None:
            out[heading].append([cell.strip() for cell in line.strip().strip("|").split("|")])
    return {h: rows[2:] for h, rows in out.items() if rows}  # rows[0] is the header, rows[1] the rule


def unquote(cell: str) -> str:
    return cell.strip().strip("`")


def table_under(all_tables: dict[str, list[list[str]]], heading_part: str) -> list[list[str]]:
    """The one table whose heading holds ``heading_part``."""
    matches = [rows for heading, rows in all_tables.items() if heading_part in heading]
    assert len(matches) == 1, f"{PAGE.name}: expected one table headed with {heading_part!r}, found {len(matches)}"
    return matches[0]


# ---- the checks ------------------------------------------------------------------------------------------


def test_every_dataset_column_is_on_the_page_as_the_code_has_it():
    all_tables = tables(checked_part())
    for dataset, dtype in fmt.TABLES.items():
        rows = table_under(all_tables, f"`/{dataset}`")
        page = [(unquote(r[0]), r[1], r[2], r[3]) for r in rows]
        expected = expected_columns(dtype)
        skeleton = "\n".join(f"| `{n}` | {t} | {s} | {u} | ... |" for n, t, s, u in expected)
        assert [p[0] for p in page] == [e[0] for e in expected], (
            f"{PAGE.name}, /{dataset}: the columns differ from the code's "
            f"(missing {sorted(set(dtype.names) - {p[0] for p in page})}, "
            f"not in the code {sorted({p[0] for p in page} - set(dtype.names))}); as the code has them:\n{skeleton}")
        assert page == expected, (
            f"{PAGE.name}, /{dataset}: type, shape or unit differ; as the code has them:\n{skeleton}")
        empty = [r[0] for r in rows if len(r) < 5 or not r[4]]
        assert not empty, f"{PAGE.name}, /{dataset}: no description for {empty}"


def test_the_attributes_are_those_a_written_file_carries(tmp_path):
    rows = table_under(tables(checked_part()), "Attributes")
    page: dict[str, set[str]] = {}
    for row in rows:
        page.setdefault(unquote(row[0]), set()).add(unquote(row[1]))
        assert len(row) >= 3 and row[2], f"{PAGE.name}: no description for attribute {row[1]} of {row[0]}"
    written = written_attributes(tmp_path)
    assert page == written, (
        f"{PAGE.name}: the attributes differ from a written file's:\n  page    {page}\n  written {written}")
    docstring = fmt.__doc__
    unnamed = sorted({name for names in written.values() for name in names
                      if not re.search(rf"\b{re.escape(name)}\b", docstring)})
    assert not unnamed, f"session/format.py's docstring (the layout's one definition) does not name {unnamed}"


def test_event_kinds_codes_and_versions_are_the_codes():
    all_tables = tables(checked_part())
    kinds = {unquote(r[0]) for r in table_under(all_tables, "Event kinds")}
    code_kinds = {value for name, value in vars(fmt.EventKind).items() if not name.startswith("_")}
    assert kinds == code_kinds, f"{PAGE.name}: event kinds {sorted(kinds)}, the code's {sorted(code_kinds)}"

    codes = {unquote(r[0]): r[1] for r in table_under(all_tables, "Coded columns")}
    expected = {column: codes_text(values) for column, values in fmt.TICK_CODES.items()}
    assert codes == expected, f"{PAGE.name}: coded columns differ from TICK_CODES; as the code has them:\n" + "\n".join(
        f"| `{c}` | {t} |" for c, t in expected.items())

    added = {("/" + unquote(r[0]).lstrip("/"), unquote(r[1])): int(r[2])
             for r in table_under(all_tables, "Columns added")}
    assert added == {("/" + d, c): v for (d, c), v in fmt.ADDED_COLUMNS.items()}, f"{PAGE.name}: added columns differ"
    added = {"/" + unquote(r[0]).lstrip("/"): int(r[1]) for r in table_under(all_tables, "Datasets added")}
    assert added == {"/" + d: v for d, v in fmt.ADDED_TABLES.items()}, f"{PAGE.name}: added datasets differ"

    part = checked_part()
    assert f"`{fmt.FORMAT_NAME}`, version {fmt.FORMAT_VERSION}" in part, (
        f"{PAGE.name} must say: `{fmt.FORMAT_NAME}`, version {fmt.FORMAT_VERSION}")
    assert f"{fmt.OVERVIEW_BUCKET_ROWS} tick rows" in part, f"{PAGE.name} must give the overview's bucket size"


def test_the_checked_layout_names_nothing_the_code_does_not_have(tmp_path):
    known = {"/", "/meta", "/stream", fmt.FORMAT_NAME}
    known |= {"/" + name for name in fmt.TABLES}
    known |= {column for dtype in fmt.TABLES.values() for column in dtype.names}
    known |= {name for names in written_attributes(tmp_path).values() for name in names}
    known |= {value for name, value in vars(fmt.EventKind).items() if not name.startswith("_")}
    known |= set(fmt.TICK_CODES) | set(vars(fmt)) | set(vars(telemetry))
    known |= {suffix for suffix, _ in UNITS}  # the page explains the naming convention
    unknown = sorted({token for token in re.findall(r"`([^`]+)`", checked_part())
                      if token not in known and not (REPO / token).exists()})
    assert not unknown, (
        f"{PAGE.name} names what session/format.py does not have (or a path that does not exist): {unknown}")


if __name__ == "__main__":  # the tables as the code has them now, descriptions to fill in
    for dataset, dtype in fmt.TABLES.items():
        print(f"\n### `/{dataset}`\n\n| column | type | shape | unit | what it holds |\n|---|---|---|---|---|")
        for n, t, s, u in expected_columns(dtype):
            print(f"| `{n}` | {t} | {s} | {u} | ... |")
    print("\n| column | codes |\n|---|---|")
    for column, values in fmt.TICK_CODES.items():
        print(f"| `{column}` | {codes_text(values)} |")
    sys.exit(0)
