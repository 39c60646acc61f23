"""`palpation-console stitch`: the exports, and its answers to bad input."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from PySide6 import QtGui

from app.session_commands import stitch_main
from session.reader import open_session
from session.stitch import StitchParams, stitch_session
from tests.session.test_model_depth import _reference


def test_every_export(recorded, reference_recorded, tmp_path, capsys, qapp):
    path = recorded[0]
    out = {name: tmp_path / name for name in ("maps.png", "maps.csv", "maps.json", "tumours.json", "report.pdf",
                                             "report.png", "reference.json")}
    # the lab's way: palpate tumour-free tissue once, save it as the reference, analyse sessions against it
    assert stitch_main([str(reference_recorded), "--physics", "none", "--save-reference",
                        str(out["reference.json"])]) == 0
    assert f"reference palpation: {out['reference.json']}" in capsys.readouterr().out
    analysis = ["--physics", "none", "--reference", str(out["reference.json"])]
    code = stitch_main([str(path), "-o", str(out["maps.png"]), "--csv", str(out["maps.csv"]),
                        "--json", str(out["maps.json"]), "--tumours", str(out["tumours.json"]),
                        "--report", str(out["report.pdf"]), "--cell-mm", "2", "--fit-radius-mm", "5",
                        "--blob-widths-mm", "2,4", "--depth-model-error", "0.3",
                        "--depth-scale-error", "0.1", "--depth-law-spread", "0.25", *analysis])
    assert code == 0
    printed = capsys.readouterr().out
    assert "3 regions, 9 recorded levels (forces 0.5, 1, 1.5 N)" in printed
    assert "baseline reference palpation (reference palpation reference.h5" in printed
    assert "truth 3 (60, 15) mm, 10.0 mm deep, stiffness map: not palpated" in printed
    assert stitch_main([str(path), "--report", str(out["report.png"]), *analysis]) == 0

    for name in ("maps.png", "report.png"):
        image = QtGui.QImage(str(out[name]))
        assert not image.isNull() and image.width() > 400 and image.height() > 400
    assert out["report.pdf"].read_bytes().startswith(b"%PDF")

    with open_session(path) as s:
        stitched = stitch_session(s, StitchParams(cell_m=2e-3))
    with open(out["maps.csv"], newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == sum(int(np.count_nonzero(lm.coverage > 0)) for lm in stitched.levels)
    assert sorted({float(r["force_N"]) for r in rows}) == [0.5, 1.0, 1.5]
    first = rows[0]
    lm = stitched.levels[0]
    cell = stitched.grid.cell_of(float(first["x_m"]), float(first["y_m"]))
    assert float(first["pressure_pa"]) == pytest.approx(lm.pressure_pa[cell], rel=1e-5)
    assert {"stiffness_contrast", "force_contrast"} <= set(first)

    maps = json.loads(out["maps.json"].read_text())
    assert maps["format"] == "palpation-console-maps" and maps["grid"]["cell_m"] == 2e-3
    assert len(maps["levels"]) == 3 and maps["levels"][2]["force_N"] == 1.5
    assert len(maps["levels"][2]["stiffness_contrast"]) == stitched.grid.nx
    stiffness = maps["levels"][2]["stiffness_pa"]
    assert len(stiffness) == stitched.grid.nx and len(stiffness[0]) == stitched.grid.ny
    gap = stitched.grid.cell_of(0.028, 0.015)  # between the second and the third area
    assert stiffness[gap[0]][gap[1]] is None  # NaN is written as null

    tumours = json.loads(out["tumours.json"].read_text())
    assert tumours["format"] == "palpation-console-tumours"
    assert {t["source"] for t in tumours["tumours"]} == {"stiffness", "force"}
    for t in tumours["tumours"]:
        assert set(t) >= {"x_m", "y_m", "depth_m", "first_level_N", "source", "score", "contrast", "depth_model_m",
                          "depth_low_m", "depth_high_m"}
        assert t["first_level_N"] == 0.5 and 1e-3 < t["depth_m"] < 5e-3
    assert len(tumours["comparison"]) == 6 and tumours["false_positives"] == {"stiffness": 0, "force": 0}
    params = tumours["params"]
    keys = ("cell_m", "false_alarm_per_area", "accuracy", "merge_radius_m", "fit_radius_m", "depth_model_error",
            "depth_scale_error", "depth_law_spread")
    assert pytest.approx([params[k] for k in keys]) == [2e-3, 0.001, 0.02, 4e-3, 5e-3, 0.3, 0.1, 0.25]
    assert params["kernel_widths_m"] == pytest.approx([2e-3, 4e-3]) and params["l0_source"] == "element"


def test_stitch_tells_each_finite_element_solve_on_the_terminal(recorded, reference_recorded, tmp_path, capsys,
                                                               monkeypatch, solves):
    monkeypatch.setenv("COLUMNS", "200")  # each line in full
    _reference(reference_recorded).save(tmp_path / "reference.json")
    assert stitch_main([str(recorded[0]), "--physics", "none", "--reference", str(tmp_path / "reference.json")]) == 0
    lines = capsys.readouterr().err.split("\r")
    said = [line for line in lines if "% finite-element solve " in line]
    assert solves.started > 1 and len(said) == solves.started
    assert "% finite-element solve 1: sphere " in said[0] and "; depth model, stiffness map: " in said[0]
    assert lines[-1].startswith("[" + "#" * 30 + "] 100% analysed") and lines[-1].endswith("\n")


def test_bad_files_and_options_get_one_line_and_exit_code_2(recorded, tmp_path, capsys):
    (tmp_path / "notes.h5").write_text("not a session")
    assert stitch_main([str(tmp_path / "notes.h5")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "not an HDF5 file" in err and "Traceback" not in err
    # issue 50: a file cut short before its levels said "--physics rebuilt: ...", an option never given, and
    # not that the file was truncated
    data = recorded[0].read_bytes()
    (tmp_path / "cut.h5").write_bytes(data[:int(len(data) * 0.011)])
    assert stitch_main([str(tmp_path / "cut.h5")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: The file is truncated") and "missing" in err and "--physics" not in err
    assert "no recorded level" in err and err.count("\n") == 1
    assert stitch_main([str(recorded[0]), "--cell-mm", "0"]) == 2
    assert "cell size must be between 0.1 and 20 mm" in capsys.readouterr().err
    assert stitch_main([str(recorded[0]), "--l0", "fixed"]) == 2
    assert capsys.readouterr().err == "error: --l0 fixed needs --l0-mm, the tissue thickness in mm\n"
    assert stitch_main([str(recorded[0]), "--l0", "fixed", "--l0-mm", "-3"]) == 2
    assert "needs a tissue thickness" in capsys.readouterr().err
    assert stitch_main([str(recorded[0]), "--l0", "guess"]) == 2  # argparse's own message
    assert "invalid choice: 'guess'" in capsys.readouterr().err
    assert stitch_main(["--help"]) == 0
    assert "--false-alarm" in capsys.readouterr().out
    assert stitch_main([str(recorded[0]), "--false-alarm", "2"]) == 2
    assert "false-alarm rate per area must be within [1e-6, 0.5]" in capsys.readouterr().err
    for option, value, said in (("--merge-radius-mm", "0", "merge radius must be within (0, 50] mm, got 0 mm"),
                                ("--blob-widths-mm", "30", "blob widths must be one or more within [0.5, 20] mm, "
                                                           "got 30"),
                                ("--depth-model-error", "nan", "depth model error must be a relative error"),
                                ("--depth-scale-error", "-0.1", "depth scale error must be a relative error within "
                                                                "[0, 2], got -0.1"),
                                ("--depth-law-spread", "1.5", "depth law spread must be a relative error within "
                                                              "[0, 1], got 1.5"),
                                ("--blob-widths-mm", "2,x", "'2,x' is not a comma-separated list of widths in mm")):
        assert stitch_main([str(recorded[0]), option, value]) == 2
        err = capsys.readouterr().err
        assert said in err.strip().splitlines()[-1] and "Traceback" not in err  # argparse's usage may come first
    (tmp_path / "ref.json").write_text("{}")
    # without physics: the reference is read after the flat field's physics, whose rebuilt tissue (tens of
    # seconds on a cold cache) plays no part in refusing it
    assert stitch_main([str(recorded[0]), "--physics", "none", "--reference", str(tmp_path / "ref.json")]) == 2
    assert "not a Palpation Console reference palpation" in capsys.readouterr().err


def test_an_output_that_cannot_be_written_is_refused_before_the_analysis(recorded, tmp_path, capsys, monkeypatch):
    import app.session_commands as commands

    monkeypatch.setattr(commands, "analyse", lambda *_: pytest.fail("analysed before the outputs were checked"))
    missing = tmp_path / "no" / "such" / "folder"
    for option, name in (("--tumours", "t.json"), ("-o", "maps.png"), ("--report", "r.pdf"), ("--csv", "m.csv"),
                         ("--save-reference", "ref.json")):
        assert stitch_main([str(recorded[0]), option, str(missing / name)]) == 1
        assert capsys.readouterr().err == f"error: {option} {missing / name}: the folder {missing} does not exist\n"
    assert stitch_main([str(recorded[0]), "--report", str(tmp_path / "r.docx")]) == 1
    assert capsys.readouterr().err == f"error: --report {tmp_path / 'r.docx'}: name it .pdf or .png (the suffix " \
                                      "decides what is written)\n"
    assert stitch_main([str(recorded[0]), "-o", str(tmp_path / "maps.jpg")]) == 1
    assert "name it .png" in capsys.readouterr().err


def test_an_output_that_fails_while_written_is_reported(recorded, tmp_path, capsys, qapp):
    (tmp_path / "taken.png").mkdir()  # a folder where the picture should go
    assert stitch_main([str(recorded[0]), "--physics", "none", "-o", str(tmp_path / "taken.png")]) == 1
    assert "Qt could not save the image" in capsys.readouterr().err


def test_part_of_a_tissue_is_analysed_with_where_it_ends_not_known(recorded, tmp_path):
    out = tmp_path / "maps.json"
    assert stitch_main([str(recorded[0]), "--physics", "partial", "--no-depth-model", "--json", str(out)]) == 0
    flat_field = json.loads(out.read_text())["flat_field"]
    assert "rebuilt from the session" in flat_field and "where the tissue ends not known" in flat_field


def test_stitch_shows_on_the_terminal_how_far_the_tissue_rebuild_is(recorded, capsys, monkeypatch):
    """issue 50: the first stitch of a session printed nothing for about 30 s while its tissue was rebuilt."""
    def rebuilt(session, name, progress=None):
        progress(0.5, "condensing the rebuilt block")
        progress(1.0, "tissue model ready")

    monkeypatch.setattr("app.session_commands.physics_for", rebuilt)
    assert stitch_main([str(recorded[0]), "--no-depth-model"]) == 0
    err = capsys.readouterr().err
    assert "100% tissue model ready" in err and "[" + "#" * 30 + "]" in err
