"""A session as tidy tables (issue 50): what pandas, R or a spreadsheet reads, the file's values unchanged."""

from __future__ import annotations

import csv

import numpy as np
import pyarrow.parquet as pq
import pytest

from app.session_commands import export_main
from session.reader import open_session
from session.tables import TABLES, table_chunks


def _csv_columns(path):
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    return {name: [row[k] for row in body] for k, name in enumerate(header)}


def test_csv_tables_hold_every_tick_frame_element_and_level_as_recorded(recorded, tmp_path, capsys):
    path = recorded[0]
    assert export_main([str(path), "--csv", str(tmp_path)]) == 0
    written = capsys.readouterr().out.split()
    assert written == [str(tmp_path / f"{path.stem}-{name}.csv") for name in TABLES]
    with open_session(path) as s:
        ticks, frames, levels = s.tick_rows(0, s.n_ticks), s.frames(), s.levels
    t = _csv_columns(tmp_path / f"{path.stem}-ticks.csv")
    assert len(t["tick"]) == len(ticks) and [int(v) for v in t["tick"]] == ticks["tick"].tolist()
    assert np.array_equal(np.array(t["x_slave_m_z"], float), ticks["x_slave_m"][:, 2], equal_nan=True)
    assert np.array_equal(np.array(t["force_measured_N"], float), ticks["force_measured_N"], equal_nan=True)
    f = _csv_columns(tmp_path / f"{path.stem}-frames.csv")
    assert len(f["row"]) == 60 * len(frames)
    # one row per element, row-major over the face, float32 readings given back exactly
    k = 60 * 3 + 15 * 2 + 7
    assert (int(f["sensor_seq"][k]), int(f["row"][k]), int(f["col"][k])) == (frames["sensor_seq"][3], 2, 7)
    assert np.float32(f["pressure_pa"][k]) == frames["pressure_pa"][3, 2, 7]
    lv = _csv_columns(tmp_path / f"{path.stem}-levels.csv")
    assert len(lv["row"]) == 60 * len(levels) > 0
    assert float(lv["stiffness_pa"][60 + 14]) == pytest.approx(levels["stiffness_pa"][1, 0, 14], rel=1e-15,
                                                                nan_ok=True)
    assert float(lv["force_desired_N"][60]) == levels["force_desired_N"][1]


def test_parquet_tables_are_the_same_columns_typed(recorded, tmp_path, capsys):
    path = recorded[0]
    assert export_main([str(path), "--parquet", str(tmp_path), "--tables", "levels,ticks"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{path.stem}-levels.parquet", f"{path.stem}-ticks.parquet"]
    table = pq.read_table(tmp_path / f"{path.stem}-levels.parquet")
    with open_session(path) as s:
        levels = s.levels
        chunked = [len(c["row"]) for c in table_chunks(s, "frames", chunk_rows=600)]
        assert max(chunked) <= 600 and sum(chunked) == 60 * s.n_frames  # bounded pieces
    assert table.num_rows == 60 * len(levels)
    assert str(table.schema.field("pressure_pa").type) == "double" and str(table.schema.field("row").type) == "int16"
    assert table.column("region").to_pylist()[::60] == levels["region"].tolist()


def test_bad_options_and_files_get_one_line(recorded, tmp_path, capsys):
    assert export_main([str(recorded[0]), "--csv", str(tmp_path / "nowhere")]) == 1
    assert capsys.readouterr().err == f"error: {tmp_path / 'nowhere'}: no such folder\n"
    assert export_main([str(recorded[0]), "--csv", str(tmp_path), "--tables", "ticks,events"]) == 2
    assert "each must be one of ticks, frames, levels" in capsys.readouterr().err
    (tmp_path / "notes.h5").write_text("not a session")
    assert export_main([str(tmp_path / "notes.h5"), "--csv", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert not list(tmp_path.glob("*.csv"))
    assert export_main([str(recorded[0])]) == 2  # --csv or --parquet is required: argparse's own line
    assert "one of the arguments --csv --parquet --mcap is required" in capsys.readouterr().err
