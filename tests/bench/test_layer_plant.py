"""The fault campaign's plant (hardware/sim/plant.py): its second-order robot and its device faults do what
the campaign counts on."""

import math

import numpy as np
import pytest

from hardware.sim.plant import ELEMENT_AREA_M2, ELEMENTS, LayerPlant, SecondOrderRobot


class _Result:
    def __init__(self, x=None, v=(0.0, 0.0, 0.0)):
        self.hold = x is None
        self.position_ref_m = x
        self.velocity_ref_m_s = v


def test_the_robot_follows_a_step_late_and_without_overshoot():
    robot = SecondOrderRobot((0.0, 0.0, 0.0), bandwidth_hz=20.0, max_accel_m_s2=100.0, max_speed_m_s=1.0)
    robot.command((0.0, 0.0, 1e-3), (0.0, 0.0, 0.0))
    trace = []
    for _ in range(200):
        robot.advance(1e-3)
        trace.append(robot.position[2])
    w = 2 * math.pi * 20.0
    exact = [1e-3 * (1 - (1 + w * t) * math.exp(-w * t)) for t in np.arange(1, 201) * 1e-3]
    assert max(trace) <= 1e-3 * (1 + 1e-6)  # critically damped
    assert max(abs(a - b) for a, b in zip(trace, exact)) < 0.04e-3
    assert trace[4] < 0.5e-3  # 5 ms after the step it is less than half way: the lag the loop must live with


def test_the_robot_is_limited_in_acceleration_and_speed():
    robot = SecondOrderRobot((0.0, 0.0, 0.0), bandwidth_hz=40.0, max_accel_m_s2=5.0, max_speed_m_s=0.25)
    robot.command((0.0, 0.0, -0.1), (0.0, 0.0, 0.0))
    speeds = []
    for _ in range(100):
        robot.advance(1e-3)
        speeds.append(abs(robot.velocity[2]))
    assert speeds[9] == pytest.approx(5.0 * 0.010, rel=0.01)  # 10 ms at the acceleration limit
    assert max(speeds) <= 0.25 + 1e-12


@pytest.mark.parametrize("speed", [0.05, 0.2])
def test_a_hold_brakes_along_the_travel_within_the_plan(speed):
    robot = SecondOrderRobot((0.0, 0.0, 0.05), max_accel_m_s2=5.0, max_speed_m_s=0.5)
    robot.command((0.0, 0.0, -1.0), (0.0, 0.0, -speed))
    while abs(robot.velocity[2]) < speed * 0.999:
        robot.advance(1e-3)
    start, v = list(robot.position), abs(robot.velocity[2])
    robot.hold()
    for _ in range(1000):
        robot.advance(1e-3)
    assert robot.velocity == [0.0, 0.0, 0.0]
    assert math.dist(start, robot.position) == pytest.approx(robot.braking_distance_m(v), rel=1e-6)
    assert robot.braking_distance_m(v) == pytest.approx(v * v / (2 * 0.6 * 5.0))


def test_the_plant_moves_its_robot_between_polls_and_knows_the_truth():
    robot = SecondOrderRobot((0.03, 0.015, 0.026))
    plant = LayerPlant(surface_m=0.025, modulus_pa=60e3, robot=robot)
    assert plant.stiffness_N_m == pytest.approx(60e3 * ELEMENT_AREA_M2 * ELEMENTS / 0.025)
    plant.poll(0.0)
    plant.apply(_Result((0.03, 0.015, 0.024)))
    plant.poll(0.001)
    assert 0.024 < plant.x[2] < 0.026  # on its way, not there
    for k in range(2, 300):
        plant.poll(k * 1e-3)
    assert plant.x[2] == pytest.approx(0.024, abs=1e-6)
    assert plant.true_force_N() == pytest.approx(plant.stiffness_N_m * 0.001)


def test_device_faults_change_what_is_read_not_the_truth():
    plant = LayerPlant(surface_m=0.025, modulus_pa=60e3, start_m=(0.03, 0.015, 0.024))
    plant.poll(0.0)
    good = plant.frame
    plant.array_fault = "frozen"
    plant.apply(_Result((0.03, 0.015, 0.023)))
    plant.poll(0.02)
    assert plant.frame.seq == good.seq + 1 and plant.frame.t_s > good.t_s
    np.testing.assert_array_equal(plant.frame.pressure_pa, good.pressure_pa)
    plant.array_fault = "zeros"
    plant.stamp_offset_s = 5.0
    plant.poll(0.04)
    assert not plant.frame.pressure_pa.any() and plant.frame.t_s == pytest.approx(0.035 + 5.0)
    plant.freeze_position()
    plant.apply(_Result((0.03, 0.015, 0.022)))
    plant.poll(0.05)
    assert plant.slave(0.05).position_m[2] == pytest.approx(0.023) and plant.slave(0.05).velocity_m_s == (0, 0, 0)
    assert plant.true_force_N() == pytest.approx(plant.stiffness_N_m * 0.003)
