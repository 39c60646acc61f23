"""Building the simulated rig, its settings, and running its devices together on a virtual clock."""

import numpy as np
import pytest

from hardware.interfaces import ConnectionState, TactileConstraints
from hardware.rig import Rig
from hardware.settings import ConfigError
from hardware.sim.operator import ScriptedOperator
from hardware.sim.rig import build_sim_rig
from hardware.sim.robot import SimSlave
from hardware.sim.sensor import SimTactileSensor
from hardware.sim.settings import SimSettings
from tissue.phantom import PhantomError, load_phantom, parse_phantom
from tissue.winkler import WinklerTissue

T0 = 1000.0
MS = 1e-3


def test_builds_the_three_devices_on_one_world_with_a_description():
    rig = build_sim_rig("flat", seed=4)
    assert isinstance(rig, Rig)
    assert isinstance(rig.sensor, SimTactileSensor)
    assert isinstance(rig.slave, SimSlave)
    assert isinstance(rig.master, ScriptedOperator)
    assert rig.sensor.world is rig.slave.world is rig.master.world
    flat = load_phantom("flat")
    assert rig.ground_truth == flat.ground_truth()
    assert [g["depth_m"] for g in rig.ground_truth] == pytest.approx([0.002, 0.007, 0.010])
    d = rig.description
    assert (d["backend"], d["phantom"], d["phantom_hash"], d["tissue_model"], d["seed"]) == (
        "sim", "flat", flat.content_hash(), "ContinuumTissue", 4)
    assert SimSettings.from_mapping(d["settings"]) == SimSettings()


def test_settings_come_from_a_mapping_and_bad_ones_name_their_key():
    rig = build_sim_rig("flat", {"sensor": {"noise_std_pa": 10.0, "frame_rate_hz": 50},
                                 "robot": {"home_m": [0.01, 0.01, 0.05]}, "substep_s": 5e-4})
    assert rig.sensor.constraints.frame_rate_hz == 50.0
    assert rig.sensor.settings.noise_std_pa == 10.0
    assert rig.master.home_m == (0.01, 0.01, 0.05)
    assert rig.description["settings"]["substep_s"] == 5e-4
    cases = [
        ({"sensor": {"noise": 1.0}}, r"^sensor\.noise: unknown key \(known: cover_spread_m, creep_fraction, "),
        ({"robot": {"bandwidth_hz": -20}}, r"^robot\.bandwidth_hz: must be > 0, got -20"),
        ({"robot": {"home_m": [0.0, 0.0, 0.5]}}, r"^robot\.home_m: z = 0\.5 m lies outside the workspace"),
        ({"robot": {"home_m": "up"}}, r"^robot\.home_m: must be three numbers"),
        ({"sensor": {"latency_s": "fast"}}, r"^sensor\.latency_s: must be a number"),
        ({"sensor": {"seed": 1.5}}, r"^sensor\.seed: must be a non-negative integer"),
        ({"operator": []}, r"^operator: must be a table"),
        ({"substep_s": 2e-3}, r"^substep_s: must lie between 1e-05 and 0\.001 .*, got 0\.002$"),
        ({"warp": 1}, r"^warp: unknown key"),
        ({"probe_tilt_deg": [0.0, -7.0]}, r"^probe_tilt_deg: must lie between -5 and 5 .*, got -7$"),
        ({"probe_tilt_deg": [1.0]}, r"^probe_tilt_deg: must be two numbers of degrees"),
    ]
    for mapping, message in cases:
        with pytest.raises(ConfigError, match=message):
            build_sim_rig("flat", mapping)


def test_bad_phantoms_seeds_and_mismatched_tissues_are_refused_with_a_reason():
    with pytest.raises(PhantomError, match="no such phantom .*shipped phantoms: .*flat"):
        build_sim_rig("no-such-phantom")
    with pytest.raises(ValueError, match="seed must be a non-negative integer"):
        build_sim_rig("flat", seed=-1)
    other = load_phantom("flat")
    other = type(other)(**{**other.__dict__, "name": "other", "source": {"other": True}})
    with pytest.raises(ValueError, match="built for phantom 'other'"):
        build_sim_rig("flat", tissue=WinklerTissue(other))


def test_a_given_tissue_model_is_the_one_simulated():
    flat = load_phantom("flat")
    tissue = WinklerTissue(flat)
    rig = build_sim_rig(flat, tissue=tissue)
    assert rig.sensor.world.tissue is tissue


def test_the_devices_run_together_on_a_virtual_clock():
    """A pass-through stand-in for the loop: X_r = the operator's position, then a press into the tissue."""
    rig = build_sim_rig("flat", {"tissue": "winkler", "sensor": {"gain_spread": 0.0, "creep_fraction": 0.0}})
    rig.open()
    assert all(d.connection == ConnectionState.CONNECTED for d in rig.devices())
    lag = []
    for m in range(3000):
        now = T0 + m * MS
        rig.poll(now)
        master, slave = rig.master.latest(), rig.slave.latest()
        assert now - master.t_s < MS and now - slave.t_s < MS
        frame = rig.sensor.latest()
        if frame is not None:
            assert now - frame.t_s < 0.020 + 1e-9
        rig.slave.command(master.position_m, (0.0, 0.0, 0.0), now)
        lag.append(np.linalg.norm(np.subtract(master.position_m, slave.position_m)))
    assert max(lag) < 0.5e-3  # the robot keeps up with a hand
    assert np.abs(rig.sensor.latest().pressure_pa).max() < 300.0  # above the tissue: nothing but noise

    # press 4 mm into the tissue at the middle tumour-free area: contact does not stop the robot
    x, y = 0.024, 0.015
    t = T0 + 3.0
    for m in range(1500):
        now = t + m * MS
        rig.poll(now)
        rig.slave.command((x, y, 0.021), (0.0, 0.0, 0.0), now)
    assert rig.slave.latest().position_m == pytest.approx((x, y, 0.021), abs=1e-7)
    force = rig.sensor.latest().pressure_pa.sum() * TactileConstraints().element_area_m2
    assert force == pytest.approx(20e3 * 240e-6 * 0.004 / 0.025, rel=0.02)  # Eq. 1 over the whole face
    rig.close()
    assert all(d.connection == ConnectionState.DISCONNECTED for d in rig.devices())


def test_the_control_loop_palpates_an_area_of_the_simulated_rig():
    """End to end on a virtual clock: operator, loop and robot; on Winkler tissue Eq. 1 must give E back."""
    from control.config import ControlConfig, RampSettings
    from control.loop import ControlLoop
    from control.messages import LevelRecorded

    layer = parse_phantom({"phantom": {"name": "layer", "length_m": 0.030, "width_m": 0.030, "thickness_m": 0.025,
                                       "youngs_modulus_pa": 20e3, "poisson_ratio": 0.49,
                                       "regions": [{"centre_xy_m": [0.015, 0.015]}]}})
    rig = build_sim_rig(layer, {"tissue": "winkler",
                                "operator": {"lateral_speed_m_s": 0.05, "vertical_speed_m_s": 0.05}})
    loop = ControlLoop(ControlConfig(ramp=RampSettings(force_min_N=0.5, force_max_N=2.0, force_step_N=0.5)),
                       rig.sensor.constraints)
    rig.open()
    records = []
    now = T0
    while not rig.master.finished and now < T0 + 30.0:
        rig.poll(now)
        result = loop.step(now, rig.sensor.latest(), rig.slave.latest(), rig.master.latest())
        if result.hold:
            rig.slave.hold(now)
        else:
            rig.slave.command(result.position_ref_m, result.velocity_ref_m_s, now)
        if result.feedback is not None:
            rig.master.feedback(result.feedback)
        records += [e.record for e in result.events if isinstance(e, LevelRecorded)]
        now += MS
    rig.close()
    assert rig.master.finished
    assert [o.result for o in rig.master.outcomes] == ["done"]
    assert [r.level for r in records] == [0, 1, 2, 3]
    last = records[-1]
    assert np.nanmedian(last.L0_m) == pytest.approx(0.025, abs=0.3e-3)
    assert np.nanmedian(last.stiffness_pa) == pytest.approx(20e3, rel=0.08)  # gain spread and creep: a few %
    assert last.indentation_m == pytest.approx(last.force_measured_N / (20e3 * 240e-6 / 0.025), rel=0.08)


def test_the_tissue_model_is_chosen_in_the_settings():
    assert build_sim_rig("flat", {"tissue": "winkler"}).description["tissue_model"] == "WinklerTissue"
    with pytest.raises(ConfigError, match="tissue: unknown tissue model 'springs'"):
        build_sim_rig("flat", {"tissue": "springs"})
