"""The fault campaign (bench/safety_campaign.py), short: the invariants hold off the happy path, and the
campaign would see it if they did not."""

from bench import safety_campaign as campaign
from control import safety
from control.loop import ControlLoop


def test_a_short_campaign_finds_no_violation_on_the_plants_and_the_rig():
    summary = campaign.campaign(plant_runs=60, rig_runs=2, seed=3, sim={"tissue": "winkler"})
    assert summary["runs"] == 62 and summary["ticks"] == 60 * 2000 + 2 * 3000
    assert summary["violations"] == 0, summary["violation_examples"]
    assert summary["faults_raised"] > 30  # the trouble was real: the loop had to act on it
    assert summary["stop_beyond_braking_plan_max_mm"] is None or summary["stop_beyond_braking_plan_max_mm"] <= 0.1


def test_the_campaign_catches_a_loop_that_ignores_its_ceilings(monkeypatch):
    check = safety.SafetySupervisor.check

    def blind(self, **readings):
        readings.update(force_N=0.0, max_pressure_pa=0.0, saturated_elements=0, indentation_m=float("nan"))
        return check(self, **readings)

    monkeypatch.setattr(safety.SafetySupervisor, "check", blind)
    # and descends as fast as it is told, wherever the tissue and the ceiling are
    monkeypatch.setattr(ControlLoop, "_descent_limit_m", lambda self, z, dt: -float("inf"))
    summary = campaign.campaign(plant_runs=60, rig_runs=0, seed=3)
    assert summary["violations"] > 0
    assert any("true force" in v or "true indentation" in v for v in summary["violation_examples"])


def test_fuzzed_inputs_get_the_readers_own_errors_never_a_crash(tmp_path):
    found = campaign.fuzz(150, seed=5, folder=tmp_path)
    assert found["fuzz_inputs"] == 600
    assert found["fuzz_crashes"] == 0, found["fuzz_crash_examples"]
