"""Issue 49's independent campaign (bench/independent_campaign.py): runs of kinds that must end safely end safely
on its own plant, and its checker fails a loop that is kept from seeing what it presses."""

import ast
import json
from dataclasses import asdict
from pathlib import Path

import pytest

from bench import independent_campaign as campaign


def test_it_imports_no_physics_of_the_simulated_rig_or_our_campaign():
    # the point of an independent plant: a mistake shared with hardware/sim would pass both campaigns
    tree = ast.parse(Path(campaign.__file__).read_text(encoding="utf-8"))
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    imported |= {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    assert not any(name.startswith(("hardware.sim", "bench.safety_campaign")) for name in imported), imported


# Drawn so (checked below): the array reads exact zeros from the moment force control starts
DEAD_FROM_THE_START = [49, 109]
# an e-stop while the ramp presses at a level (31), and while the operator drives the probe down at speed (7)
ESTOP_PRESSING = [31, 7]


@pytest.mark.parametrize("seed", DEAD_FROM_THE_START)
def test_an_array_dead_from_the_start_of_force_control_ends_safely(seed):
    run = campaign.Run(seed)
    assert run.r.kind == "dead-array" and run.trigger == ("ramp", -1) and run.trouble["fault"] == "zeros"
    result = run.run()
    assert result.injected
    assert result.violations == []
    assert result.faults, "the loop must notice a dead array"
    assert result.max_force_over_ceiling_N <= campaign.FORCE_MARGIN_N
    assert result.max_indentation_over_ceiling_mm <= campaign.INDENTATION_MARGIN_M * 1e3


# Arrays that read only their noise (49000633, 49000993) or an unloaded frame under fresh noise (49001846, 49000262)
# from the start of the seek: nothing tells them from air, and the seek went on through the layer to 47 N
BLIND_FROM_THE_START = [49000633, 49000993, 49001846, 49000262]


@pytest.mark.parametrize("seed", BLIND_FROM_THE_START)
def test_a_seek_the_array_cannot_see_ends_before_the_stiffest_tissue_would_pass_the_ceiling(seed):
    run = campaign.Run(seed)
    assert run.r.kind in ("dead-array", "frozen-array") and run.trigger == ("ramp", -1)
    assert run.trouble["fault"] in ("noise", "stuck")
    result = run.run()
    assert result.injected and result.violations == []
    (aborted,) = result.aborted
    assert aborted[1].startswith("no tissue found within")
    assert result.max_force_over_ceiling_N <= campaign.FORCE_MARGIN_N


# Tissue whose push starts softly (force as the indentation to the power 2.1-2.2): the elements' onsets came
# 0.8 mm below the surface, and the probe went that much past the indentation ceiling (49001781 started in
# contact, 49000499 ramped towards 19 N). The ramp now stops a level short of where it predicts the ceiling, by
# the same depth the ceiling is held to; either way the probe goes no further past it than the margin.
SOFT_START = [49001781, 49000499]


@pytest.mark.parametrize("seed", SOFT_START)
def test_on_tissue_whose_push_starts_softly_the_indentation_ceiling_holds(seed):
    result = campaign.run(seed)
    assert result.drawn["tissue"]["law"] == "power" and result.drawn["tissue"]["shape"] > 2.0
    assert result.violations == []
    assert result.region_done or result.faults[0][1] == "INDENTATION_CEILING"
    assert result.max_indentation_over_ceiling_mm <= campaign.INDENTATION_MARGIN_M * 1e3


# A robot position reading that lies smoothly, so the jump check passes it: one that carries on descending at
# the speed it had when it stuck, after the robot has met the tissue (288: the force floor went 0.6 mm deeper,
# 0.6 N over the ceiling; 840: the lift started 7 mm below the robot, 28 N over), and one that creeps away (1705)
LYING_SMOOTHLY = [49000288, 49000840, 49001705]


@pytest.mark.parametrize("seed", LYING_SMOOTHLY)
def test_a_position_reading_that_lies_smoothly_ends_safely(seed):
    result = campaign.run(seed)
    assert result.kind in ("stuck-position", "lying-position") and result.injected
    assert result.violations == []
    assert result.max_force_over_ceiling_N <= campaign.FORCE_MARGIN_N


@pytest.mark.parametrize("seed", ESTOP_PRESSING)
def test_an_estop_while_pressing_ends_safely(seed):
    result = campaign.run(seed)
    assert result.kind == "estop-pressing" and result.injected
    assert result.faults[0][1] == "ESTOP"
    assert result.violations == []


def test_a_run_is_its_seed_and_replays_as_the_campaign_ran_it(capsys):
    first = asdict(campaign.run(31))
    assert asdict(campaign.run(31)) == first
    assert campaign.main(["--replay", "31"]) == 0
    out = capsys.readouterr().out
    assert '"seed": 31' in out and "ESTOP" in out


def test_the_campaign_summary_has_the_figures_issue_49_asks_for(tmp_path):
    results = [asdict(campaign.run(seed)) for seed in (49, 31)]
    results[1]["violations"] = [{"type": "force", "t_s": 1.0, "true_force_N": 13.0}]  # as a violation is kept
    summary = campaign.summarise(results)
    assert summary["runs"] == 2 and summary["violating_runs"] == 1
    assert summary["violations"][0]["seed"] == 31 and summary["violations"][0]["kind"] == "estop-pressing"
    assert set(summary["by_kind"]) == {"dead-array", "estop-pressing"}
    for key in ("max_force_over_ceiling_N", "max_indentation_over_ceiling_mm"):
        assert isinstance(summary[key], float)
    json.dumps(summary)


# ---- negative controls: the checker can fail --------------------------------------------------------------

def test_an_array_reading_a_third_of_the_force_takes_the_probe_over_the_ceiling():
    # a miscalibration no loop can tell by design: the force rises with depth as tissue's does, only too little;
    # the ramp to 3 N presses 10 N against a 7.8 N ceiling
    result = campaign.run(12, kind="plain", array_fault=("gain", 0.3))
    assert any(v["type"] == "force" for v in result.violations), result.violations
    assert result.max_force_over_ceiling_N > campaign.FORCE_MARGIN_N


def test_a_loop_blind_to_its_ceilings_is_caught(blind_loop):
    seed = 32  # the operator pushes the master down: today's loop stops the probe short of every ceiling
    assert campaign.run(seed).violations == []
    blind_loop()
    found = campaign.run(seed).violations
    assert {v["type"] for v in found} & {"force", "indentation"}, found


def test_a_campaign_tells_its_progress_as_its_runs_come_in(monkeypatch):
    monkeypatch.setattr(campaign, "CHUNK_RUNS", 1)
    told = []
    summary = campaign.campaign(3, seed=5, progress=lambda results: told.append(len(results)))
    assert told == [1, 2, 3] and summary["runs"] == 3
