"""A lying tactile array: dead, frozen, drifting, or stamped in the future (issue 49). Each kind once drove the
probe on into the tissue; each now ends with the probe lifted, before 1 mm of travel the array cannot explain."""

import numpy as np
import pytest

from control.messages import FaultKind, FaultRaised, SetSz
from hardware.interfaces import Phase, TactileFrame

from .plant import Harness


def start_region(h):
    h.run(0.4)  # the loop measures the sensor's noise before it lets force control start
    h.send(SetSz(position_control=False))
    h.run(0.01)
    assert h.loop.sm.phase == Phase.SEEK_CONTACT


def lie(plant, reading):
    """From now on the array reports ``reading(true pressure)`` instead of the truth (fresh seq and stamp)."""
    honest = plant.pressure_at
    plant.pressure_at = lambda z: reading(honest(z))


def run_to_fault(h, seconds=10.0):
    deepest = [h.plant.x[2]]
    h.run(seconds, until=lambda h: deepest.append(h.plant.x[2]) or h.loop.safety.faulted)
    h.run(1.0)  # and the lift that follows
    return min(deepest)


def test_an_array_streaming_zeros_from_the_start_of_force_control_is_stale():
    """Zeros from the start of force control drove the probe through a 25 mm phantom to 38.7 N."""
    h = Harness()
    start_region(h)
    lie(h.plant, lambda p: np.zeros_like(p))
    lowest = run_to_fault(h)
    (fault,) = h.of(FaultRaised)
    assert fault.kind == FaultKind.SENSOR_STALE and fault.message.startswith("Frozen tactile array")
    assert h.plant.x[2] > 0.025 and 0.025 - lowest < 1e-3  # it never got a millimetre into the tissue


@pytest.mark.parametrize("level", [2, 5])
def test_an_array_that_repeats_one_frame_is_stale(level):
    """The same frame repeated after level 2 or 5 drove the probe to the indentation ceiling at 16 N."""
    h = Harness()
    start_region(h)
    h.run(20, until=lambda h: h.loop.sm.level == level)
    frozen = h.plant.pressure_at(h.plant.x[2])
    z = h.plant.x[2]
    lie(h.plant, lambda p: frozen)
    lowest = run_to_fault(h)
    (fault,) = h.of(FaultRaised)
    assert fault.kind == FaultKind.SENSOR_STALE and "identical, element by element" in fault.message
    assert z - lowest < 1e-3 and h.plant.x[2] > 0.025


def test_a_dead_array_that_reads_only_its_noise_in_the_tissue_is_found():
    """Alive electronics, no sensing: noise about zero while the probe is millimetres into the tissue."""
    h = Harness()
    start_region(h)
    h.run(20, until=lambda h: h.loop.sm.level == 2)
    z = h.plant.x[2]
    rng = np.random.default_rng(3)
    lie(h.plant, lambda p: rng.normal(0.0, 50.0, p.shape))
    lowest = run_to_fault(h)
    (fault,) = h.of(FaultRaised)
    # (the noise's first frame is a fall no tissue makes; without that check, the depth check's "Dead tactile array")
    assert fault.kind == FaultKind.SENSOR_IMPLAUSIBLE and fault.message.startswith("Tactile force fell from")
    assert z - lowest < 1e-3 and h.plant.x[2] > 0.025


def test_an_array_that_loses_half_its_gain_is_found_before_a_millimetre_of_travel():
    """A reading that falls short of the tissue's push: the force loop goes deeper without the force rising."""
    h = Harness()
    start_region(h)
    h.run(20, until=lambda h: h.loop.sm.level == 3)
    z = h.plant.x[2]
    lie(h.plant, lambda p: 0.5 * p)
    lowest = run_to_fault(h)
    (fault,) = h.of(FaultRaised)
    assert fault.kind == FaultKind.SENSOR_IMPLAUSIBLE and fault.message.startswith("Tactile force fell from")
    assert z - lowest < 1e-3 and h.plant.x[2] > 0.025


def test_a_uniform_negative_drift_within_the_old_bound_is_implausible():
    """-15 to -19 kPa per element, inside the old 20 %-of-full-scale bound, put 10.4-11.6 N on the tissue at a
    7 N ramp and 20 mm of indentation against a 16 mm ceiling, with the ramp reported done."""
    h = Harness()
    start_region(h)
    h.run(20, until=lambda h: h.loop.sm.level == 1)
    lie(h.plant, lambda p: p - 15e3)
    run_to_fault(h)
    (fault,) = h.of(FaultRaised)
    assert fault.kind == FaultKind.SENSOR_IMPLAUSIBLE and "far below zero" in fault.message
    assert h.plant.true_force_N() == 0.0


def test_an_unloaded_reading_that_drifted_since_the_tare_refuses_force_control():
    h = Harness()
    lie(h.plant, lambda p: p - 1.5e3)  # in air: within the implausible bound, beyond the drift one
    h.run(0.4)
    h.send(SetSz(position_control=False))
    h.run(0.01)
    assert "unloaded reading has drifted to -1.50 kPa" in h.of(type(h.events[-1]))[-1].reason
    assert h.loop.sm.phase == Phase.APPROACH and not h.of(FaultRaised)


def test_a_frame_stamped_in_the_future_does_not_keep_the_watchdog_quiet():
    """One frame 5 s ahead, stored as "last seen", kept the stale watchdog quiet for 0.5-1 s."""
    h = Harness()
    h.run(0.2)
    frame = h.plant.frame
    h.plant.frame = TactileFrame(frame.seq + 1, frame.t_s + 5.0, frame.pressure_pa + 1.0, None)
    h.plant.sensor_alive = False  # and then nothing
    silent_from = h.now
    h.run(1.0, until=lambda h: h.loop.safety.faulted)
    (fault,) = h.of(FaultRaised)
    assert fault.kind == FaultKind.SENSOR_STALE
    assert h.now - silent_from <= h.config.safety.sensor_timeout_s + 0.011  # the newest real frame's age


def test_a_robot_position_reading_that_jumps_is_held_on_not_followed():
    """The fault campaign: a position reading that lies 1-10 mm low, taken as the robot's place, sent the probe
    that far into the tissue at the next fault (up to 20 N over the ceiling)."""
    h = Harness()
    start_region(h)
    h.run(20, until=lambda h: h.loop.sm.level == 2)
    z, force = h.plant.x[2], h.plant.true_force_N()
    h.plant.position_offset_m = (0.0, 0.0, -0.005)  # the reading now says 5 mm deeper than the robot is
    h.run(1.0)
    (fault,) = h.of(FaultRaised)
    assert fault.kind == FaultKind.SLAVE_IMPLAUSIBLE and "jumped 5.00 mm" in fault.message
    assert h.last.hold and h.plant.x[2] == pytest.approx(z, abs=1e-4) and h.plant.true_force_N() <= force + 0.1


def test_a_force_that_falls_in_one_frame_while_the_probe_goes_deeper_is_no_tissue():
    """The fault campaign: an array that died while the ramp rose read 0 N for 16 ms before the depth check saw
    it, and the force loop dived 0.3 mm into 7 kN/m tissue; a reading that steps down by 0.5 N is the same."""
    h = Harness()
    start_region(h)
    h.run(20, until=lambda h: h.loop.sm.level == 3)
    z = h.plant.x[2]
    lie(h.plant, lambda p: p - 2e3)  # 0.48 N over the face, in one frame
    lowest = run_to_fault(h, seconds=0.05)
    (fault,) = h.of(FaultRaised)
    assert fault.kind == FaultKind.SENSOR_IMPLAUSIBLE and fault.message.startswith("Tactile force fell from")
    assert z - lowest < 0.1e-3


def test_a_probe_that_starts_pressed_in_goes_no_deeper_until_lifted_clear():
    """A probe started pressed into tissue is in by a depth no reading tells (the fault campaign: the ceiling
    counted from the start, and the probe went 1.9 mm past it); the operator may lift it, not press on."""
    from control.messages import Jog
    from hardware.sim.plant import LayerPlant

    # 2 mm into the 25 mm layer, and read so: the array refused to take the load as its zero
    h = Harness(plant=LayerPlant(start_m=(0.03, 0.015, 0.023)))
    h.send(Jog((0.0, 0.0, -0.010)))  # the operator asks for 10 mm more
    h.run(1.0)
    assert h.plant.x[2] > 0.023 - 0.05e-3
    h.send(Jog((0.0, 0.0, 0.017)))  # lifted clear of the tissue (jogs add up: to 30 mm) ...
    h.run(3.0)
    assert h.plant.x[2] > 0.0295
    h.send(Jog((0.0, 0.0, -0.0075)))  # ... and down again: now tracked from its contact
    h.run(1.5)
    assert h.plant.x[2] < 0.0235 and not h.of(FaultRaised)


def test_an_array_drifting_down_inside_each_elements_bound_faults_by_its_sum():
    """Issue 49 (our campaign, seeds 3639 and 6255): a uniform drift that stays inside each element's
    plausibility bound hid 3.7 N and read -0.6 N over the face in air, and the ramp went on to 1.6 N over the
    ceiling. No tissue pulls, so a face that adds up below what its tare may wander is lying."""
    h = Harness()
    start_region(h)
    z = h.plant.x[2]
    lie(h.plant, lambda p: p - 2e3)  # 0.48 N over the face, 2 kPa an element: inside the 3 kPa bound
    run_to_fault(h, seconds=0.1)
    (fault,) = h.of(FaultRaised)
    assert fault.kind == FaultKind.SENSOR_IMPLAUSIBLE and fault.message.startswith("Tactile force -0.4")
    assert h.plant.x[2] >= z - 0.1e-3  # still in the air it was seeking through


def test_an_array_tared_pressing_lets_the_probe_no_deeper():
    """Issue 49 (our campaign, rig seed 1500019): an array takes its first frame as zero, and the probe began
    1.7 mm into the tissue; the ceiling counted from where the reading rose, and the operator's jog took the
    probe 1.9 mm past it. Contact read as soon as the probe moves down from where it read nothing was not made
    from air: the probe goes no deeper until it has been seen clear, and force control is refused."""
    from control.messages import CommandRefused, Jog
    from hardware.sim.plant import LayerPlant

    plant = LayerPlant(start_m=(0.03, 0.015, 0.0233))  # 1.7 mm in ...
    preload = plant.pressure_at(plant.x[2])
    lie(plant, lambda p: p - preload)  # ... and read as zero
    h = Harness(plant=plant)
    h.run(0.4)
    h.send(Jog((0.0, 0.0, -0.020)))
    h.run(3.0)
    assert h.plant.x[2] > 0.0233 - 0.5e-3 and not h.of(FaultRaised)
    h.send(SetSz(position_control=False))
    h.run(0.01)
    (refused,) = h.of(CommandRefused)
    assert "may have been tared pressing the tissue" in refused.reason


def test_the_indentation_ceiling_counts_from_the_first_touch_of_a_probe_sliding_in():
    """Issue 49 (our campaign, rig seed 1500089): a jog down and sideways touched lightly while sliding, the
    tracking began afresh at every quarter pitch until the face pressed 0.5 N, and the ceiling counted from
    0.5 mm below the surface: the probe went 0.56 mm past it."""
    from control.config import ControlConfig, SafetyLimits
    from control.messages import Jog

    h = Harness(config=ControlConfig(safety=SafetyLimits(indentation_ceiling_m=0.008)))
    h.run(0.4)
    h.send(Jog((0.03, 0.0, -0.03)))
    deepest = run_to_fault(h)
    (fault,) = h.of(FaultRaised)
    assert fault.kind == FaultKind.INDENTATION_CEILING
    assert h.plant.surface_m - deepest < 0.008 + 0.1e-3
