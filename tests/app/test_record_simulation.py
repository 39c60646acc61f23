"""Recording a simulated palpation (app/recording.py): a fault ends its area, and the scripted operator
clears it and goes on, so the rest of the tissue is still palpated."""

from __future__ import annotations

import numpy as np
import pytest

from app.recording import record_simulation
from control.palpation import CAPPED_BY_DEPTH, CAPPED_BY_PRESSURE
from session.format import EventKind
from session.reader import open_session
from tests.session.conftest import REGIONS_XY_M, _phantom_file


def _three_areas(tmp_path, control: dict):
    from app.config import load_config
    from hardware.interfaces import TactileConstraints
    from hardware.sim.rig import build_sim_rig
    from tissue.phantom import load_phantom
    from tissue.winkler import WinklerTissue

    phantom_path = _phantom_file(tmp_path, "three", with_tumours=False)
    config = load_config(None, {"control": {"ramp": {"force_min_N": 0.5, "force_max_N": 1.5, "force_step_N": 0.5},
                                            **control}, "rig": {"phantom": str(phantom_path)}})
    phantom = load_phantom(phantom_path)
    rig = build_sim_rig(phantom, tissue=WinklerTissue(phantom, TactileConstraints()))
    path = tmp_path / "three.h5"
    record_simulation(path, config, rig=rig, max_time_s=200.0)
    return path


def test_a_fault_ends_its_area_and_the_operator_clears_it_and_goes_on(tmp_path):
    # the spring-bed tissue takes 2.2 mm at 0.5 N: every area passes 2 mm on its first level. (A ceiling a later
    # level would pass stops the ramp short of it instead: test_a_ramp_that_would_pass_a_ceiling_stops_short...)
    path = _three_areas(tmp_path, {"safety": {"indentation_ceiling_m": 0.002}})
    with open_session(path) as s:
        kinds = s.events["kind"]
        faults = s.events[kinds == EventKind.FAULT.encode()]
        cleared = s.events[kinds == EventKind.FAULT_CLEARED.encode()]
        assert len(faults) == len(REGIONS_XY_M) and len(cleared) == len(faults)
        assert all("Indentation ceiling exceeded" in text.decode() for text in faults["text"])
        assert not len(s.levels)  # the ceiling stopped each area before its first level settled
        aborted = s.events[kinds == EventKind.REGION_ABORTED.encode()]
        assert list(aborted["region"]) == list(range(len(REGIONS_XY_M)))
        assert np.all(np.diff(cleared["t_s"]) > 0)


@pytest.mark.parametrize("safety, why", [
    # every area would pass 5.5 kPa on some element at its last level (1.5 N: 6.3 kPa), none before (1 N: 4.1 kPa)
    ({"element_pressure_ceiling_pa": 5.5e3}, CAPPED_BY_PRESSURE),
    # the spring-bed tissue takes 4.7 mm at 1 N, and would take some 7 mm at 1.5 N
    ({"indentation_ceiling_m": 0.0065}, CAPPED_BY_DEPTH)])
def test_a_ramp_that_would_pass_a_ceiling_stops_short_and_every_area_is_done(tmp_path, safety, why):
    """Issue 48: the pressure ceiling faulted such areas, and the rest of the ramp was lost with them; so did the
    indentation ceiling, on soft phantoms of the validation study's held-out seeds."""
    path = _three_areas(tmp_path, {"safety": safety})
    with open_session(path) as s:
        assert not len(s.events[s.events["kind"] == EventKind.FAULT.encode()])
        done = s.events[s.events["kind"] == EventKind.REGION_DONE.encode()]
        assert list(done["value"]) == [1.0] * len(REGIONS_XY_M) and list(done["code"]) == [2] * len(REGIONS_XY_M)
        assert [r.outcome for r in s.regions()] == ["done"] * len(REGIONS_XY_M)
        assert all(text.decode() == f"capped at 1 N: {why}" for text in done["text"])
