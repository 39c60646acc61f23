"""Recording a simulated palpation (app/recording.py): a fault ends its area, and the scripted operator
clears it and goes on, so the rest of the tissue is still palpated."""

from __future__ import annotations

import numpy as np

from app.recording import record_simulation
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
    # the spring-bed tissue takes 2.2 mm at 0.5 N and 4.7 mm at 1 N: every area passes 3.5 mm on its second level
    path = _three_areas(tmp_path, {"safety": {"indentation_ceiling_m": 0.0035}})
    with open_session(path) as s:
        kinds = s.events["kind"]
        faults = s.events[kinds == EventKind.FAULT.encode()]
        cleared = s.events[kinds == EventKind.FAULT_CLEARED.encode()]
        assert len(faults) == len(REGIONS_XY_M) and len(cleared) == len(faults)
        assert all("Indentation ceiling exceeded" in text.decode() for text in faults["text"])
        # each area was palpated up to the level the ceiling stopped it at
        for region in range(len(REGIONS_XY_M)):
            assert sorted(s.levels["force_desired_N"][s.levels["region"] == region]) == [0.5]
        assert [r.outcome for r in s.regions()] == ["aborted"] * len(REGIONS_XY_M)
        assert np.all(np.diff(cleared["t_s"]) > 0)


def test_a_ramp_that_would_pass_the_element_ceiling_stops_short_and_every_area_is_done(tmp_path):
    """Issue 48: the pressure ceiling faulted such areas, and the rest of the ramp was lost with them."""
    # every area would pass 5.5 kPa on some element at its last level (1.5 N: 6.3 kPa), none before (1 N: 4.1 kPa)
    path = _three_areas(tmp_path, {"safety": {"element_pressure_ceiling_pa": 5.5e3}})
    with open_session(path) as s:
        assert not len(s.events[s.events["kind"] == EventKind.FAULT.encode()])
        done = s.events[s.events["kind"] == EventKind.REGION_DONE.encode()]
        assert list(done["value"]) == [1.0] * len(REGIONS_XY_M) and list(done["code"]) == [2] * len(REGIONS_XY_M)
        assert [r.outcome for r in s.regions()] == ["done"] * len(REGIONS_XY_M)
        assert all(text.decode() == "capped at 1 N" for text in done["text"])
