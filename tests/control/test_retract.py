"""Retract that always retracts: at region end and after any fault the probe leaves the tissue at the retract
speed whatever force it carries, and a probe held pressing over a ceiling is lifted (issue 49)."""

import pytest

from control.config import ControlConfig
from control.messages import EStop, FaultKind, FaultRaised, Notice, RegionDone
from hardware.interfaces import Phase

from .plant import Harness, LayerPlant


def start_region(h):
    h.run(0.4)  # the loop measures the sensor's noise before it lets force control start
    from control.messages import SetSz

    h.send(SetSz(position_control=False))
    h.run(0.01)


@pytest.mark.parametrize("force_max_N", [9.0, 11.5])
def test_a_region_ending_at_a_high_force_lifts_the_probe_at_the_retract_speed(force_max_N):
    """At F_max >= 9 N the retract rose at F/B (112 mm/s at 9 N), past the velocity limit: the guard refused it
    and latched a stop-where-it-is fault with the probe pressing 6-10 N."""
    config = ControlConfig.from_mapping({"ramp": {"force_max_N": force_max_N, "force_step_N": 2.0}})
    h = Harness(config=config, plant=LayerPlant(modulus_pa=200e3))
    start_region(h)
    h.run(30, until=lambda h: h.loop.sm.phase == Phase.DONE or h.loop.safety.faulted)
    assert not h.of(FaultRaised) and h.of(RegionDone)
    assert h.plant.true_force_N() == 0.0 and h.plant.x[2] > 0.025 + config.contact.retract_height_m - 1e-3
    speeds = []
    h2 = Harness(config=config, plant=LayerPlant(modulus_pa=200e3))
    start_region(h2)
    h2.run(30, until=lambda h: h.loop.sm.phase == Phase.RETRACT)
    h2.run(0.2, until=lambda h: speeds.append(h.plant.v[2]) or False)
    assert max(speeds) == pytest.approx(config.contact.retract_speed_m_s)


def test_a_probe_held_pressing_over_the_ceiling_is_lifted_and_the_fault_stays():
    """An e-stop while pressing: a robot that brakes into the tissue came to rest over the force ceiling and
    was held there, nothing retracting (12.25 N against 12 N; 17 N against 6.7 N with stiffer tissue)."""
    h = Harness()
    start_region(h)
    h.run(20, until=lambda h: h.loop.sm.level == 4)
    h.send(EStop("test"))
    h.run(0.2)
    assert h.loop.safety.fault == FaultKind.ESTOP and h.last.hold
    z_held = h.plant.x[2]
    h.plant.extra_force_pa = 10.0 / (60 * 4e-6)  # 10 N more on the array: over the 12 N ceiling
    h.run(1.0)
    assert h.loop.safety.fault == FaultKind.ESTOP  # still latched: the operator clears it
    (lifting,) = [e.message for e in h.of(Notice) if "while the robot was held" in e.message]
    assert lifting.startswith("The force ") and "over the 12.00 N ceiling" in lifting
    assert h.plant.x[2] > 0.025 and h.plant.x[2] > z_held  # off the tissue
    assert [e.kind for e in h.of(FaultRaised)] == [FaultKind.ESTOP]
