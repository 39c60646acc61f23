"""The simulated tactile array: timing, what a frame describes, converter, tare, creep, seeds, connection."""

import math

import numpy as np
import pytest

from hardware.interfaces import ConnectionState, DeviceError, TactileConstraints
from hardware.sim.sensor import SimTactileSensor
from hardware.sim.settings import SensorSimSettings, SimSettings
from hardware.sim.world import SimWorld
from tissue.phantom import load_phantom
from tissue.winkler import WinklerTissue

T0 = 40.0
MS = 1e-3
AREA = TactileConstraints().element_area_m2
IDEAL = dict(noise_std_pa=0.0, quantisation_pa=0.0, gain_spread=0.0, creep_fraction=0.0, hysteresis_fraction=0.0,
             cover_spread_m=0.0)


class KnownLoad:
    """Tissue double: the element forces the test sets, wherever the TSI is."""

    def __init__(self):
        self.phantom = load_phantom("flat")
        self.force_N = np.zeros((4, 15))

    def element_forces_N(self, x_m, y_m, z_m):
        return self.force_N.copy()


def make_sensor(tissue=None, run_seed=0, **sensor):
    tissue = tissue if tissue is not None else KnownLoad()
    world = SimWorld(tissue.phantom, tissue, SimSettings(sensor=SensorSimSettings(**sensor)))
    s = SimTactileSensor(world, seed=run_seed)
    s.open()
    return s


def run(sensor, start_s, duration_s, on_tick=None):
    """Poll at 1 kHz; the distinct frames in arrival order and the (now, latest) pairs."""
    frames, pairs = [], []
    for m in range(int(round(duration_s / MS)) + 1):
        now = start_s + m * MS
        if on_tick is not None:
            on_tick(now)
        sensor.poll(now)
        f = sensor.latest()
        pairs.append((now, f))
        if f is not None and (not frames or frames[-1] is not f):
            frames.append(f)
    return frames, pairs


@pytest.mark.parametrize("rate_hz, latency_s", [(100.0, 0.010), (50.0, 0.025)])
def test_frames_arrive_at_the_frame_rate_with_their_latency(rate_hz, latency_s):
    sensor = make_sensor(frame_rate_hz=rate_hz, latency_s=latency_s)
    frames, pairs = run(sensor, T0, 1.0)
    assert [f.seq for f in frames] == list(range(frames[0].seq, frames[0].seq + len(frames)))
    assert len(frames) == pytest.approx(rate_hz * (1.0 - latency_s), abs=1)
    assert np.allclose(np.diff([f.t_s for f in frames]), 1 / rate_hz)
    for now, f in pairs:
        if f is not None:
            assert f.t_s <= now - latency_s + 1e-9
            assert now - f.t_s < latency_s + 1 / rate_hz + 1e-9
    assert frames[0].pressure_pa.shape == (4, 15)


def test_a_frame_describes_the_tsi_where_it_was_at_its_own_instant():
    phantom = load_phantom("flat")
    sensor = make_sensor(WinklerTissue(phantom), latency_s=0.03, **IDEAL)
    world = sensor.world
    robot = world.robot
    x, y = 0.036, 0.015
    robot.position = [x, y, 0.0260]
    robot.set_reference((x, y, 0.0260), (0.0, 0.0, 0.0))
    speed = 0.01  # descending 10 mm/s through the surface at 25 mm

    def descend(now):
        robot.set_reference((x, y, 0.0260 - speed * (now - T0)), (0.0, 0.0, -speed))

    frames, _ = run(sensor, T0, 0.6, descend)
    loaded = [f for f in frames if f.pressure_pa.max() > 0]
    assert len(loaded) > 20
    for f in loaded:
        z_then = world.state_at(f.t_s)[0][2]
        expected = WinklerTissue(phantom).element_forces_N(x, y, z_then) / AREA
        assert np.allclose(f.pressure_pa, expected, rtol=1e-9, atol=1e-6)
    # 30 ms later the TSI is 0.3 mm deeper: a frame read "now" would be visibly off
    assert world.state_at(loaded[-1].t_s)[0][2] - world.state_at(loaded[-1].t_s + 0.03)[0][2] > 0.25e-3


def test_readings_are_quantised_to_the_converter_step():
    q = 100.0
    sensor = make_sensor(**{**IDEAL, "quantisation_pa": q})
    tissue = sensor.world.tissue
    rng = np.random.default_rng(1)
    loads = rng.uniform(0.0, 50e3, size=(4, 15))

    def load(now):
        if now > T0 + 0.05:
            tissue.force_N = loads * AREA

    frames, _ = run(sensor, T0, 0.2, load)
    last = frames[-1].pressure_pa
    assert np.allclose(last / q, np.round(last / q), atol=1e-9)
    assert np.abs(last - loads).max() <= q + 1e-6
    assert np.abs(last - loads).max() > 1.0  # it really is rounding


def test_the_converter_saturates_at_full_scale():
    sensor = make_sensor(**{**IDEAL, "full_scale_pa": 100e3})
    tissue = sensor.world.tissue
    run(sensor, T0, 0.05)
    tissue.force_N[:, :7] = 150e3 * AREA  # beyond full scale
    tissue.force_N[:, 7:] = 60e3 * AREA  # within it
    frames, _ = run(sensor, T0 + 0.051, 0.1)
    first = frames[-1].pressure_pa
    tissue.force_N[:, :7] = 400e3 * AREA
    frames, _ = run(sensor, T0 + 0.152, 0.1)
    p = frames[-1].pressure_pa
    assert np.array_equal(p[:, :7], first[:, :7])  # more load reads the same
    assert np.allclose(p[:, :7], 100e3, atol=1000.0)  # about full scale (it depends on each zero offset)
    assert np.allclose(p[:, 7:], 60e3)  # the rest is unaffected
    saturated = frames[-1].saturated
    assert saturated[:, :7].all() and not saturated[:, 7:].any()  # and the frame says which is which


def test_tare_zeroes_the_current_reading_per_element():
    sensor = make_sensor(noise_std_pa=30.0, creep_fraction=0.0)
    tissue = sensor.world.tissue
    load = np.linspace(1e3, 8e3, 60).reshape(4, 15)  # a drift-sized load, below 10 % of full scale
    run(sensor, T0, 0.05)
    unloaded = sensor.latest().pressure_pa
    assert np.abs(unloaded).max() < 6 * 30.0 + 50  # the connection baseline took the zero offsets out
    tissue.force_N = load * AREA
    frames, _ = run(sensor, T0 + 0.051, 0.1)
    assert np.allclose(frames[-1].pressure_pa, load, rtol=0.1, atol=300.0)
    sensor.tare()
    frames, _ = run(sensor, T0 + 0.152, 0.1)
    assert np.abs(frames[-1].pressure_pa).max() < 6 * 30.0 * math.sqrt(2) + 50
    tissue.force_N[:] = 0.0
    frames, _ = run(sensor, T0 + 0.253, 0.1)
    assert np.allclose(frames[-1].pressure_pa, -load, rtol=0.1, atol=300.0)


def test_a_reading_no_unloaded_array_gives_is_never_taken_as_zero():
    # Tare hid real force: pressed into the tissue, tared, then ramped, the true force passed the ceiling
    # while far less was measured.
    sensor = make_sensor(noise_std_pa=30.0, creep_fraction=0.0)
    tissue = sensor.world.tissue
    run(sensor, T0, 0.05)
    tissue.force_N[:] = 20e3 * AREA
    frames, _ = run(sensor, T0 + 0.051, 0.1)
    before = frames[-1].pressure_pa
    with pytest.raises(DeviceError, match=r"not tared: an element reads 2\d\.\d kPa, more than 10% of full scale"):
        sensor.tare()
    frames, _ = run(sensor, T0 + 0.152, 0.05)
    assert np.allclose(frames[-1].pressure_pa, before, atol=300.0)  # the zero did not move
    tissue.force_N[:] = 200e3 * AREA
    run(sensor, T0 + 0.203, 0.05)
    with pytest.raises(DeviceError, match="60 element.s. saturated"):
        sensor.tare()


def test_connecting_while_pressed_takes_no_zero_and_says_why():
    sensor = make_sensor(noise_std_pa=30.0, creep_fraction=0.0)
    sensor.world.tissue.force_N[:] = 30e3 * AREA
    frames, _ = run(sensor, T0, 0.05)
    assert "not tared on connection: an element reads" in sensor.tare_refused
    assert np.allclose(frames[-1].pressure_pa, 30e3, rtol=0.1)  # the load shows (with the small baseline)
    sensor.world.tissue.force_N[:] = 0.0
    frames, _ = run(sensor, T0 + 0.051, 0.05)
    sensor.tare()  # lifted clear, the operator tares
    frames, _ = run(sensor, T0 + 0.102, 0.05)
    assert np.abs(frames[-1].pressure_pa).max() < 300.0


def test_creep_rises_by_its_fraction_with_its_time_constant_and_recovers():
    alpha, tau = 0.05, 0.8
    sensor = make_sensor(**{**IDEAL, "creep_fraction": alpha, "creep_time_constant_s": tau})
    tissue = sensor.world.tissue
    p0 = 20e3
    run(sensor, T0, 0.05)
    tissue.force_N[:] = p0 * AREA
    frames, _ = run(sensor, T0 + 0.051, 3.0)
    loaded = [f for f in frames if f.pressure_pa[0, 0] > 0]
    t_load = loaded[0].t_s - 0.01  # the load counts from the frame interval it was first sampled in
    for f in loaded:
        expected = p0 * (1 + alpha * (1 - math.exp(-(f.t_s - t_load) / tau)))
        assert f.pressure_pa == pytest.approx(np.full((4, 15), expected), rel=1e-9)
    assert loaded[-1].pressure_pa[0, 0] / p0 - 1 == pytest.approx(alpha, rel=0.05)
    tissue.force_N[:] = 0.0
    frames, _ = run(sensor, T0 + 3.052, 2.0)
    residue = np.array([f.pressure_pa[0, 0] for f in frames[2:]])
    assert residue[0] > 0.9 * alpha * p0  # the dielectric has not relaxed yet ...
    assert np.all(np.diff(residue) < 0)  # ... and does so steadily
    assert residue[-1] < 0.12 * residue[0]


def _reading_through_a_cycle(hysteresis, loads_pa, step_s):
    """The reading of element (0, 0) at each load of ``loads_pa``, held for ``step_s`` each."""
    sensor = make_sensor(**{**IDEAL, "hysteresis_fraction": hysteresis})
    run(sensor, T0, 0.05)
    readings, t = [], T0 + 0.051
    for p in loads_pa:
        sensor.world.tissue.force_N[:] = p * AREA
        frames, _ = run(sensor, t, step_s)
        readings.append(frames[-1].pressure_pa[0, 0])
        t += step_s + MS
    return np.array(readings)


def test_hysteresis_reads_high_on_unloading_by_its_datasheet_gap_whatever_the_rate():
    fs = TactileConstraints().full_scale_pa
    up = np.linspace(0.0, fs, 11)
    cycle = np.concatenate([up, up[-2::-1]])
    slow = _reading_through_a_cycle(0.05, cycle, 0.05)
    loading, unloading = slow[:11], slow[10:][::-1]
    assert loading == pytest.approx(up, abs=1e-6)  # calibrated on loading
    gap = (unloading - loading) / fs
    assert gap.max() == pytest.approx(0.05, rel=1e-9)  # the datasheet's figure ...
    assert up[np.argmax(gap)] == pytest.approx(fs / 2)  # ... widest at half scale
    assert gap[0] == gap[-1] == 0.0  # the loop closes at zero and at full scale
    fast = _reading_through_a_cycle(0.05, cycle, 0.02)
    assert fast == pytest.approx(slow, rel=1e-12)
    # a partial unloading (a force level's overshoot settling) takes the memory only part of the way:
    # 20 % less load moves it from -1 to -0.6, and reloading by 25 % back to -0.68
    dip = _reading_through_a_cycle(0.05, [0.0, 0.5 * fs, 0.4 * fs, 0.5 * fs], 0.05)
    assert dip[1:] == pytest.approx([0.5 * fs, 0.4 * fs * (1 + 0.1 * 0.4), 0.5 * fs * (1 + 0.1 * 0.32)], rel=1e-9)


def loaded_frames(settings_seed=0, run_seed=0, sim_span_s=0.1, **sensor):
    """Frames of a sensor zeroed unloaded, then loaded with 10 kPa on every element for ``sim_span_s`` of
    simulated time (the run is stepped on the simulator's clock, not the wall clock)."""
    sensor = make_sensor(run_seed=run_seed, **{**IDEAL, **sensor, "seed": settings_seed})
    run(sensor, T0, 0.05)
    sensor.world.tissue.force_N[:] = 10e3 * AREA
    frames, _ = run(sensor, T0 + 0.051, sim_span_s)
    return np.array([f.pressure_pa for f in frames[3:]])


def test_the_noise_comes_from_the_run_seed():
    a = loaded_frames(run_seed=0, sim_span_s=2.0, noise_std_pa=50.0)
    assert np.array_equal(a, loaded_frames(run_seed=0, sim_span_s=2.0, noise_std_pa=50.0))
    b = loaded_frames(run_seed=1, sim_span_s=2.0, noise_std_pa=50.0)
    assert not np.array_equal(a, b)
    assert (a - a.mean(axis=0)).std() == pytest.approx(50.0, rel=0.05)
    assert (b - b.mean(axis=0)).std() == pytest.approx(50.0, rel=0.05)


def test_the_element_gains_come_from_the_sensor_seed():
    g0 = loaded_frames(settings_seed=0, gain_spread=0.03)[-1] / 10e3
    assert np.array_equal(g0, loaded_frames(settings_seed=0, run_seed=7, gain_spread=0.03)[-1] / 10e3)
    g1 = loaded_frames(settings_seed=1, gain_spread=0.03)[-1] / 10e3
    assert not np.allclose(g0, g1)
    assert g0.std() == pytest.approx(0.03, rel=0.35)
    assert g0.mean() == pytest.approx(1.0, abs=0.02)
    assert np.allclose(loaded_frames(settings_seed=0)[-1], 10e3)  # no spread configured, none seen


def test_connection_state_follows_open_unplug_and_reopen():
    sensor = SimTactileSensor(SimWorld(load_phantom("flat"), KnownLoad()))
    assert sensor.connection == ConnectionState.DISCONNECTED
    sensor.poll(T0)
    sensor.poll(T0 + 0.1)
    assert sensor.latest() is None
    sensor.open()
    assert sensor.connection == ConnectionState.CONNECTED
    run(sensor, T0 + 0.1, 0.1)
    last = sensor.latest()
    assert last is not None
    sensor.world.tissue.force_N[:] = 10e3 * AREA
    sensor.simulate_unplug()
    assert sensor.connection == ConnectionState.LOST
    run(sensor, T0 + 0.201, 0.1)
    assert sensor.latest() is last
    sensor.open()  # reconnecting takes a new baseline only where an unloaded array could give it
    frames, _ = run(sensor, T0 + 0.302, 0.1)
    fresh = [f for f in frames if f.seq > last.seq]
    assert fresh and np.abs(fresh[0].pressure_pa - 10e3).max() < 2e3  # the load still shows
    assert "not tared on connection" in sensor.tare_refused
    sensor.world.tissue.force_N[:] = 0.0
    sensor.close()
    sensor.open()
    frames, _ = run(sensor, T0 + 0.403, 0.1)
    assert np.abs(frames[-1].pressure_pa).max() < 300.0 and sensor.tare_refused == ""
    sensor.close()
    assert sensor.connection == ConnectionState.DISCONNECTED


def test_a_long_host_stall_leaves_only_a_fresh_frame():
    sensor = make_sensor()
    run(sensor, T0, 0.1)
    before = sensor.latest()
    sensor.poll(T0 + 5.0)
    after = sensor.latest()
    assert after.seq - before.seq == pytest.approx(490, abs=1)
    assert 5.0 + T0 - after.t_s <= 0.010 + 0.010 + 1e-9


def test_a_tissue_model_returning_garbage_is_reported():
    class Broken(KnownLoad):
        def element_forces_N(self, x_m, y_m, z_m):
            return np.zeros((15, 4))

    sensor = make_sensor(Broken())
    with pytest.raises(DeviceError, match=r"Broken returned shape \(15, 4\)"):
        run(sensor, T0, 0.05)


def test_the_cover_spreads_an_edge_peak_to_its_neighbours_and_keeps_the_total_force():
    from tissue.face import cover_operators, cover_weight

    w = cover_weight(0.5e-3, 2e-3)
    assert w == pytest.approx(0.0997, abs=5e-4)  # Q(4) + (phi(0) - phi(4)) / 4
    assert cover_weight(0.0, 2e-3) == 0.0
    sensor = SimTactileSensor.__new__(SimTactileSensor)
    sensor._cover_rows, sensor._cover_cols = cover_operators(w, (4, 15))
    p = np.zeros((4, 15))
    p[:, 0] = 10e3  # the rigid face's edge peak along one end of the array
    p[:, 1:] = 2e3
    seen = sensor._through_cover(p)
    assert seen.sum() == pytest.approx(p.sum())
    assert seen[0, 0] < p[0, 0] and seen[0, 1] > p[0, 1]
    assert seen[1, 0] == pytest.approx(10e3 - w * 8e3)  # lost to the neighbour column, none across rows


def test_a_cover_thicker_than_stated_blurs_the_frames_and_the_array_states_the_stated_one():
    """issue 48: the analysis knows the cover the array is specified with (its calibration), not the one it has."""
    def edge_column(sensor):
        sensor.world.tissue.force_N[:] = 0.02
        sensor.world.tissue.force_N[:, 0] = 0.1
        frames, _ = run(sensor, T0, 0.05)
        return frames[-1].pressure_pa[:, 0].mean()

    bare = make_sensor(**IDEAL)
    thicker = make_sensor(**{**IDEAL, "cover_spread_m": 1e-3})
    assert edge_column(thicker) < edge_column(bare) * 0.9  # the peak spreads into the next column
    specified = SensorSimSettings().stated_cover_spread_m
    assert bare.constraints.cover_spread_m == thicker.constraints.cover_spread_m == specified


class Layer:
    """Tissue double: every element a linear spring on a flat surface at 25 mm, ``k_N_m`` each."""

    def __init__(self, k_N_m=200.0):
        self.phantom = load_phantom("flat")
        self.k_N_m = k_N_m

    def element_forces_N(self, x_m, y_m, z_m):
        return np.full((4, 15), self.k_N_m * max(0.025 - z_m, 0.0))


def presses(sensor, n, depth_m=1e-3, press_s=0.3, rest_s=0.3, first_rest_s=0.0):
    """The mean reading of each of ``n`` presses ``depth_m`` into the Layer, over their last 0.1 s."""
    robot = sensor.world.robot
    readings, now = [], T0
    for k in range(n):
        for z, span in ((0.027, first_rest_s if k == 0 else rest_s), (0.025 - depth_m, press_s)):
            robot.position = [0.036, 0.015, z]
            robot.set_reference((0.036, 0.015, z), (0.0, 0.0, 0.0))
            frames, _ = run(sensor, now, span)
            now += span + MS
        readings.append(np.mean([f.pressure_pa for f in frames if f.t_s > now - 0.1 - sensor.settings.latency_s],
                                axis=0))
    return np.array(readings)


def test_a_realistic_array_reads_each_press_as_if_the_face_stood_at_another_depth():
    """Issue 48: pressing the same spot again moved a real array's reading like a 0.3-1 mm offset of the
    indentation, not like noise; the ideal array repeats itself up to its noise."""
    quiet = dict(noise_std_pa=5.0, quantisation_pa=0.0, creep_fraction=0.0, hysteresis_fraction=0.0,
                 cover_spread_m=0.0, gain_spread=0.0)
    k = 200.0
    per_mm = k * 1e-3 / AREA  # an element's reading per mm of indentation
    realistic = presses(make_sensor(Layer(k), run_seed=4, **{**SensorSimSettings.from_mapping(
        {"model": "realistic"}).to_mapping(), **quiet, "first_press_m": 0.0}), 40)
    face = realistic.mean(axis=(1, 2)) / per_mm  # each press's offset, common to the face, in mm
    own = (realistic - realistic.mean(axis=(1, 2), keepdims=True)) / per_mm  # each element's own
    assert 0.2 < face.std() < 0.45 and 0.17 < own.std() < 0.35  # drawn at 0.3 mm and 0.25 mm
    assert abs(face.mean() - 1.0) < 0.15  # about the true indentation, 1 mm
    ideal = presses(make_sensor(Layer(k), run_seed=4, **quiet), 10)
    assert (ideal.mean(axis=(1, 2)) / per_mm).std() < 0.01


def test_a_press_after_a_rest_reads_deeper_and_less_so_after_a_short_one():
    quiet = dict(noise_std_pa=0.0, quantisation_pa=0.0, creep_fraction=0.0, hysteresis_fraction=0.0,
                 cover_spread_m=0.0, gain_spread=0.0)
    k = 200.0
    per_mm = k * 1e-3 / AREA
    sensor = make_sensor(Layer(k), **quiet, first_press_m=0.7e-3, first_press_recovery_s=10.0)
    first, again = presses(sensor, 2, rest_s=0.3).mean(axis=(1, 2)) / per_mm
    assert first == pytest.approx(1.7, abs=0.01)  # the session's first press: a full rest before it
    assert again == pytest.approx(1.0 + 0.7 * (1 - math.exp(-0.3 / 10.0)), abs=0.01)
    sensor = make_sensor(Layer(k), **quiet, first_press_m=0.7e-3, first_press_recovery_s=10.0)
    _, after_20_s = presses(sensor, 2, rest_s=20.0).mean(axis=(1, 2)) / per_mm
    assert after_20_s == pytest.approx(1.0 + 0.7 * (1 - math.exp(-2.0)), abs=0.01)


def test_rest_offsets_move_between_sessions_and_the_tare_takes_them_out():
    offsets = []
    for seed in (1, 2):
        sensor = make_sensor(run_seed=seed, noise_std_pa=0.0, session_offset_fraction=0.02)
        frames, _ = run(sensor, T0, 0.05)
        offsets.append(sensor._latest_raw.copy())
        assert np.abs(frames[-1].pressure_pa).max() < 50.0  # tared at connection
    moved = np.abs(offsets[0] - offsets[1])
    assert 500.0 < moved.max() <= 4000.0  # each within 2 % of the 100 kPa full scale either way
