"""The validation study: seeded draws, one code path on local processes and on Dask, honest scoring."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PySide6 import QtGui

from app.study import (
    ACCURACY_KEYS,
    DaskExecutor,
    LocalExecutor,
    _abort_reasons,
    _areas_started,
    analysis_options,
    kept_cases,
    reanalyse_study,
    run_study,
    study_cases,
    study_document,
    study_main,
)
from control.messages import LevelRecorded, RegionAborted, RegionDone
from session.reader import open_session
from session.scoring import score
from session.synthetic import level_record
from session.writer import SessionRecorder
from tests.session.test_recorder import INFO
from tissue.generator import StudyDistribution
from tissue.phantom import parse_phantom
from widgets.study_plot import render_study_png

# small, soft-tissue-free-of-surprises phantoms on the fast spring-bed tissue: what is tested here is the
# harness (draws, executors, scoring), not the detector, which `make study` measures
TINY = StudyDistribution(length_m=(0.024, 0.024), thickness_m=(0.025, 0.025), surface_odds=(1.0, 0.0, 0.0),
                         tumours=(1, 1), depth_m=(1e-3, 3e-3), diameter_m=(8e-3, 10e-3))
# two 8 mm areas long, not three, where what is checked is the harness's plumbing and not what is found (two
# areas do not find s2-0000's tumour): most of a case's time is the scripted operator's, area by area
SHORT = replace(TINY, length_m=(0.016, 0.016))
# the scripted operator travels between areas just over the block (the study raises it to clear the phantom),
# not at the default 45 mm, where the climb there and back is no part of what a test checks
LOW_TRAVEL = {"sim": {"operator": {"travel_height_m": 0.030}}}


NO_PHYSICS = analysis_options(physics="none")
# without the depth model's sphere solves too (8 s a case): where the test is about something else
DETECTION_ONLY = analysis_options(physics="none", no_depth_model=True)


def tiny_cases(n: int, seed: int, world: str = "ideal", calibrated: bool = False, dist: StudyDistribution = TINY):
    return study_cases(n, seed, dist=dist, tissue="winkler", force_max_N=2.0, world=world, calibrated=calibrated)


def test_the_same_seed_gives_the_same_study_and_another_seed_another():
    cases = study_cases(20, 11)
    assert [c.phantom for c in cases] == [c.phantom for c in study_cases(20, 11)]
    assert [c.phantom for c in cases] != [c.phantom for c in study_cases(20, 12)]
    kinds = set()
    for case in cases:
        phantom = parse_phantom(case.phantom, case.name)  # valid by construction
        assert 0 <= len(phantom.inclusions) <= 3 and 4.0 <= case.force_max_N <= 8.0
        for inc in case.phantom["phantom"]["inclusions"]:
            assert 1e-3 <= inc["depth_m"] <= 12e-3 and 5e-3 <= inc["diameter_m"] <= 12e-3
        kinds.add(case.phantom["phantom"]["description"].split(",")[1].strip())
    assert kinds == {"flat surface", "sloped surface", "bumpy surface"}



def test_the_realistic_world_palpates_the_same_phantoms_under_conditions_drawn_for_each():
    """issue 48: law, sides, friction, micro-relief and probe tilt drawn per phantom, the phantoms and seeds the ideal
    world's, the paper's phantoms left free on the table; a kept case is told as the paper's by its content."""
    from app.study import _without_conditions

    ideal, real = study_cases(12, 3, paper=True), study_cases(12, 3, paper=True, world="realistic")
    assert [(c.name, c.rig_seed, c.sensor_seed, c.force_max_N) for c in ideal] == \
        [(c.name, c.rig_seed, c.sensor_seed, c.force_max_N) for c in real]
    assert [_without_conditions(c.phantom) for c in real] == [c.phantom for c in ideal]
    assert all(not c.conditions for c in ideal)
    for case in real:
        phantom = parse_phantom(case.phantom, case.name)
        assert phantom.material.law == "yeoh" and phantom.surface[-1].kind == "relief"
        assert phantom.sides == case.conditions["sides"]
        assert phantom.face_friction == case.conditions["face_friction"] > 0
        assert all(abs(a) <= 1.5 for a in case.conditions["probe_tilt_deg"])
    assert {c.conditions["sides"] for c in real if not c.paper} == {"free", "mould"}
    assert all(c.conditions["sides"] == "free" for c in real if c.paper)
    assert [c.conditions for c in real] == [c.conditions for c in study_cases(12, 3, paper=True, world="realistic")]


def _without_timings(results) -> str:
    """The results as comparable text (NaN included), without what depends on the machine or the folder, or
    on the palpation's truth (how far a calibration was from the array's pattern)."""
    return json.dumps([{k: v for k, v in r.items() if not k.endswith("_s")
                        and k not in ("session", "session_here", "calibration_error_max")} for r in results],
                      sort_keys=True)


def test_local_processes_and_a_dask_cluster_run_the_same_study(tmp_path, monkeypatch):
    """The Dask cluster's worker is a process of its own in a folder of its own, as on a real cluster: the
    study's relative output folder once reached it as it was, and the cases' files landed on its side."""
    distributed = pytest.importorskip("distributed")
    cases = tiny_cases(1, seed=3, dist=SHORT)
    local = LocalExecutor(workers=1)
    try:
        local_results, _ = run_study(cases, local, tmp_path / "local", keep_sessions=False, settings=LOW_TRAVEL,
                                     analysis=DETECTION_ONLY)
    finally:
        local.close()
    (tmp_path / "client").mkdir()
    (tmp_path / "worker").mkdir()
    monkeypatch.chdir(tmp_path / "client")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                                  host="127.0.0.1") as cluster, distributed.Client(cluster) as client:
        client.run(os.chdir, str(tmp_path / "worker"))
        dask = DaskExecutor(client)
        try:
            dask_results, _ = run_study(cases, dask, Path("dask"), keep_sessions=True, settings=LOW_TRAVEL,
                                        analysis=DETECTION_ONLY)
        finally:
            dask.close()
    assert [r["name"] for r in local_results] == [c.name for c in cases]
    assert "error" not in local_results[0], local_results[0].get("error")
    assert local_results[0]["regions_aborted"] == {}  # every tiny area's ramp ends done
    assert _without_timings(local_results) == _without_timings(dask_results)
    kept = tmp_path / "client" / "dask" / cases[0].name
    assert kept.with_suffix(".h5").exists() and kept.with_suffix(".toml").exists()
    assert dask_results[0]["session_here"] and not (tmp_path / "worker" / "dask").exists()
    assert not (tmp_path / "local" / f"{cases[0].name}.h5").exists()
    doc = study_document(cases, local_results, 1.0, 3, 1, "local")
    assert set(ACCURACY_KEYS) <= set(doc) and doc["phantoms"] == 1 and doc["study_wall_s"] == 1.0


def test_a_case_counts_its_aborted_areas_by_the_controllers_reason(tmp_path):
    rec = SessionRecorder(tmp_path / "s.h5", INFO)
    ceiling = "Pressure ceiling exceeded: one element read 95.1 kPa, above the 95.0 kPa limit"
    rec.add_events([LevelRecorded(1.0, level_record(0, 0, 1.0, (0.004, 0.015))), RegionAborted(1.5, 0, ceiling),
                    LevelRecorded(2.0, level_record(1, 0, 1.0, (0.012, 0.015))), RegionDone(2.5, 1, 1),
                    LevelRecorded(3.0, level_record(2, 0, 1.0, (0.020, 0.015))), RegionAborted(3.5, 2, ceiling),
                    RegionAborted(4.0, 3, "switched to position control by the operator")])
    rec.close()
    with open_session(tmp_path / "s.h5") as session:
        assert _abort_reasons(session) == {"Pressure ceiling exceeded": 2,
                                           "switched to position control by the operator": 1}
        assert _areas_started(session) == 4  # the last ended before its first level


class _LastFirst:
    """An executor that finishes its cases in the reverse of the order given, here in this process."""

    def run(self, fn, items, *args):
        return reversed([fn(item, *args) for item in items])

    def close(self):
        pass


def test_results_come_back_in_the_order_of_the_cases_whatever_order_they_finish_in(tmp_path):
    cases = [type(c)(c.name, {"phantom": {"name": "x"}}, 0, 0, tissue="winkler") for c in tiny_cases(3, seed=4)]
    results, _ = run_study(cases, _LastFirst(), tmp_path, analysis=NO_PHYSICS)
    assert [r["name"] for r in results] == [c.name for c in cases]


def test_a_case_that_cannot_run_is_reported_not_fatal(tmp_path):
    case = tiny_cases(1, seed=4)[0]
    broken = type(case)(case.name, {"phantom": {"name": "x"}}, 0, 0, tissue="winkler")
    local = LocalExecutor(workers=1)
    try:
        [result], _ = run_study([broken], local, tmp_path, analysis=NO_PHYSICS)
    finally:
        local.close()
    assert result["error"].startswith("PhantomError") and "\n" not in result["error"]
    assert score([result])["failed_cases"] == 1


def test_the_operator_moves_between_areas_over_a_phantom_taller_than_its_travel_height(tmp_path):
    """A block 42 mm thick: its areas' approach (surface + clearance) stands over the default 45 mm travel
    height, which refused the case before the study raised it over the phantom."""
    import copy

    case = tiny_cases(1, seed=4, dist=SHORT)[0]
    phantom = copy.deepcopy(case.phantom)
    phantom["phantom"]["thickness_m"] = 0.042  # its tumour drawn by depth under the surface, kept
    [result], _ = run_study([replace(case, phantom=phantom)], _LastFirst(), tmp_path, analysis=DETECTION_ONLY)
    assert "error" not in result
    assert result["regions_done"] == result["regions"] > 0


def test_the_command_writes_json_and_plot_and_refuses_nonsense(tmp_path, capsys, monkeypatch, qapp):
    assert study_main(["--phantoms", "0"]) == 2
    assert "nothing to run" in capsys.readouterr().err
    assert study_main(["--phantoms", "-3"]) == 2
    assert "--phantoms must be within" in capsys.readouterr().err
    monkeypatch.setattr("app.study.study_cases", lambda n, seed, paper, **options: tiny_cases(n, seed, **options))
    out = tmp_path / "s"
    assert study_main(["-n", "1", "--seed", "2", "--workers", "1", "--out", str(out), "--no-sessions",
                       "--physics", "none"]) == 0
    printed = capsys.readouterr().out
    assert "stiffness map: 1 tumours in 1 phantoms" in printed and "[1/1] s2-0000" in printed
    assert re.search(r"flat +1 +1 +1 +100\.0 % +0\.00\n", printed)  # by surface: found, no false positive
    doc = json.loads((out / "study.json").read_text())
    assert set(ACCURACY_KEYS) | {"study_wall_s", "maps", "cases"} <= set(doc)
    found = [m for m in doc["cases"][0]["matches"] if m["found"] and m["source"] == "stiffness"]
    assert found and all(m["depth_low_m"] <= m["depth_model_m"] <= m["depth_high_m"] for m in found)
    assert (out / "study.png").read_bytes().startswith(b"\x89PNG")


def test_the_phantoms_are_palpated_with_the_configuration_given(tmp_path, capsys, monkeypatch, qapp):
    """issue 13: `study --config FILE` (or `--config FILE study`): the lab's ramp, not the defaults."""
    from app.cli import main
    from session.reader import open_session

    monkeypatch.setattr("app.study.study_cases",
                        lambda n, seed, paper, **options: tiny_cases(n, seed, dist=SHORT, **options))
    config = tmp_path / "fine-ramp.toml"
    config.write_text("[control.ramp]\nforce_min_N = 0.5\nforce_step_N = 0.5\n")
    out = tmp_path / "s"
    assert main(["--config", str(config), "study", "-n", "1", "--seed", "2", "--workers", "1",
                 "--out", str(out), "--physics", "none", "--no-depth-model", "--world", "realistic"]) == 0
    doc = json.loads((out / "study.json").read_text())
    assert doc["config"] == str(config) and doc["world"] == "realistic"
    with open_session(doc["cases"][0]["session"]) as session:
        assert sorted(set(np.round(session.levels["force_desired_N"], 3))) == [0.5, 1.0, 1.5, 2.0]
        # the realistic world's array (issue 48), as the session recorded it
        from hardware.sim.settings import SimSettings

        sensor = SimSettings.from_mapping(session.config["sim"]).sensor
        assert sensor.model == "realistic" and sensor.gain_spread == 0.07 and sensor.press_offset_m > 0
        # and the conditions drawn for the phantom: its law, sides and relief, the probe's tilt
        conditions = doc["cases"][0]["conditions"]
        assert session.phantom["phantom"]["material"]["law"] == "yeoh"
        assert session.phantom["phantom"]["sides"] == conditions["sides"]
        assert session.phantom["phantom"]["face_friction"] == conditions["face_friction"] > 0
        assert session.phantom["phantom"]["surface"][-1]["rms_m"] == conditions["relief_rms_m"]
        assert session.config["sim"]["probe_tilt_deg"] == conditions["probe_tilt_deg"] != [0.0, 0.0]
        # a thicker cover than the array is specified with: the session's calibration states the specified one,
        # which is what the analysis reads
        from session.physics import _cover_of

        assert sensor.cover_spread_m == conditions["cover_spread_m"] != sensor.stated_cover_spread_m
        assert session.calibration["cover_spread_m"] == sensor.stated_cover_spread_m == _cover_of(session)
    capsys.readouterr()
    config.write_text("[control.ramp]\nforce_step_N = -1.0\n")
    assert study_main(["-n", "1", "--out", str(out), "--config", str(config)]) == 2
    err = capsys.readouterr().err
    assert "control.ramp.force_step_N" in err and len(err.strip().splitlines()) == 1


def test_a_study_of_both_worlds_reports_each_under_its_own_keys(tmp_path, capsys, monkeypatch, qapp):
    """issue 48: `make study` runs both worlds on the same phantoms; the realistic world's figures are today's
    keys prefixed realistic_."""
    monkeypatch.setattr("app.study.study_cases",
                        lambda n, seed, paper, **options: tiny_cases(n, seed, dist=SHORT, **options))
    out = tmp_path / "both"
    assert study_main(["-n", "1", "--seed", "2", "--workers", "1", "--out", str(out), "--physics", "none",
                       "--no-depth-model", "--world", "both"]) == 0
    printed = capsys.readouterr().out
    assert "== the ideal world ==" in printed and "== the realistic world ==" in printed
    doc = json.loads((out / "study.json").read_text())
    assert doc["world"] == "both" and doc["phantoms"] == doc["realistic_phantoms"] == 1
    assert [c["name"] for c in doc["cases"]] == ["s2-0000", "realistic-s2-0000"]
    assert [c["world"] for c in doc["cases"]] == ["ideal", "realistic"]
    for key in ACCURACY_KEYS:
        assert f"realistic_{key}" in doc
    assert doc["sensitivity_pct"] == doc["maps"]["stiffness"]["sensitivity_pct"]
    assert doc["realistic_sensitivity_pct"] == doc["realistic_maps"]["stiffness"]["sensitivity_pct"]
    assert doc["realistic_conditions"]["mould_odds"] == 0.3
    assert sorted(p.name for p in out.glob("*.h5")) == ["realistic-s2-0000.h5", "s2-0000.h5"]
    one, both = QtGui.QImage(), QtGui.QImage(str(out / "study.png"))
    doc.pop("realistic_maps")
    render_study_png(out / "ideal.png", doc)
    one.load(str(out / "ideal.png"))
    assert both.height() > 1.8 * one.height()  # a row of plots per world


def test_a_kept_study_is_analysed_again_with_other_options_without_palpating(tmp_path, capsys, monkeypatch, qapp):
    from session.detect import threshold

    cases = tiny_cases(2, seed=6)
    local = LocalExecutor(workers=1)
    try:
        palpated, _ = run_study(cases, local, tmp_path, settings=LOW_TRAVEL, analysis=DETECTION_ONLY)
        kept = kept_cases(tmp_path)
        again, _ = reanalyse_study(kept, local, DETECTION_ONLY)
        strict, _ = reanalyse_study(kept, local, {**DETECTION_ONLY, "false_alarm": 1e-6})
    finally:
        local.close()
    assert [k.name for k in kept] == [c.name for c in cases] and not any(k.paper for k in kept)
    assert _without_timings(again) == _without_timings(palpated)  # the same options, the same findings
    limit = threshold(1e-6, (4, 15), 2e-3, (2e-3, 4e-3))
    assert all(t["score"] > limit for r in strict for t in r["tumours"])
    assert sum(len(r["tumours"]) for r in strict) <= sum(len(r["tumours"]) for r in again)

    # the command: analysis options recorded, palpation options refused, nothing kept refused
    monkeypatch.setattr("app.study.LocalExecutor", lambda workers=None: LocalExecutor(1))
    assert study_main(["--reanalyse", str(tmp_path), "--physics", "none", "--false-alarm", "0.001",
                       "--no-depth-model"]) == 0
    assert "re-analysing the 2 cases kept in" in capsys.readouterr().out
    doc = json.loads((tmp_path / "reanalysis.json").read_text())
    assert doc["reanalysed"] == str(tmp_path) and doc["analysis"]["false_alarm"] == 0.001
    assert doc["analysis"]["no_depth_model"] is True
    assert (tmp_path / "reanalysis.png").read_bytes().startswith(b"\x89PNG")
    assert study_main(["--reanalyse", str(tmp_path), "--seed", "3"]) == 2
    assert "--seed only apply to palpating" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert study_main(["--reanalyse", str(empty)]) == 2
    assert "holds no kept study case" in capsys.readouterr().err
    assert study_main(["--reanalyse", str(tmp_path), "--false-alarm", "2"]) == 2
    assert "false-alarm rate" in capsys.readouterr().err


def _alive(pid: int) -> bool:
    """Whether the process runs (a zombie nobody has reaped yet has ended)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_study_killed_outright_leaves_no_worker_running(qtbot, tmp_path):
    """A study killed (not closed) cannot shut its pool down: its workers end by themselves."""
    script = ("import sys\n"
              "from app.study import LocalExecutor\n"
              "pool = LocalExecutor(workers=2)\n"
              "print(sorted(pool.run(abs, [-1, -2])), flush=True)\n"
              "sys.stdin.read()\n")
    study = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             text=True, cwd=Path(__file__).resolve().parents[2])
    try:
        assert study.stdout.readline().strip() == "[1, 2]"
        children = Path(f"/proc/{study.pid}/task/{study.pid}/children").read_text().split()
        workers = [int(pid) for pid in children]
        assert len(workers) >= 2 and all(_alive(pid) for pid in workers)
    finally:
        study.kill()
        study.wait()
        study.stdin.close()
        study.stdout.close()
    qtbot.waitUntil(lambda: not any(_alive(pid) for pid in workers), timeout=10000)


def test_a_calibrated_study_calibrates_each_case_s_own_array_before_palpating_with_it(tmp_path):
    case = tiny_cases(1, seed=5, world="realistic", dist=SHORT)[0]
    local = LocalExecutor(workers=1)
    try:
        results, _ = run_study([replace(case, calibrated=True)], local, tmp_path, settings=LOW_TRAVEL,
                               analysis=DETECTION_ONLY)
    finally:
        local.close()
    result = results[0]
    assert "error" not in result, result.get("error")
    # the realistic array's own 7 % pattern, recovered from its six presses on the cushion
    assert result["calibrated"] and result["calibration_error_max"] < 0.01
    with open_session(tmp_path / f"{case.name}.h5") as session:
        assert session.array_calibration is not None and session.array_calibration.presses == 6
    assert (tmp_path / f"{case.name}-cushion.h5").is_file()
