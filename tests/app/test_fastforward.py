"""The fast-forward driver: the real tick on a virtual clock."""

import numpy as np
import pytest

from app.fastforward import FastForward, FastForwardTimeout
from app.rigs import RigSpec, build_rig
from control.config import ControlConfig
from control.messages import ClearFault, CommandApplied, EStop, FaultCleared, FaultKind, FaultRaised, Jog, Notice, Tare
from control.telemetry import FRAME_DTYPE, TICK_DTYPE
from hardware.interfaces import Phase


@pytest.fixture
def ff():
    driver = FastForward(ControlConfig(), build_rig(RigSpec()), block_rows=256)
    yield driver
    driver.close()


def test_ticks_run_on_an_exact_virtual_grid_and_the_row_store_grows(ff):
    assert ff.run_for(1.0) == 1000
    ticks = ff.ticks
    assert ticks.dtype == TICK_DTYPE and len(ticks) == 1000  # past several 256-row blocks
    np.testing.assert_array_equal(ticks["tick"], np.arange(1000))
    np.testing.assert_array_equal(ticks["t_s"], np.arange(1000) * 1e-3)
    assert np.all(ticks["late_s"] == 0) and np.all(ticks["missed_ticks"] == 0)
    assert np.all(ticks["compute_s"] > 0) and np.all(ticks["io_s"] > 0)
    assert ff.now_s == pytest.approx(1.0) and ff.tick_count == 1000
    # the simulated sensor delivers ~100 frames/s, each seen once
    frames = ff.frames
    assert frames.dtype == FRAME_DTYPE and 90 <= len(frames) <= 101
    assert np.all(np.diff(frames["sensor_seq"]) > 0)


def test_clear_forgets_rows_and_events_but_not_the_clock(ff):
    ff.run_for(0.2)
    ff.clear()
    assert len(ff.ticks) == 0 and len(ff.frames) == 0 and ff.events == []
    ff.run_for(0.01)
    assert int(ff.ticks["tick"][0]) == 200 and len(ff.ticks) == 10


def test_commands_take_effect_on_the_next_tick(ff):
    ff.run_for(0.1)
    ff.send(EStop("test"))
    ff.step()
    faults = [e for e in ff.events if isinstance(e, FaultRaised)]
    assert [f.kind for f in faults] == [FaultKind.ESTOP]
    assert faults[0].t_s == pytest.approx(0.1)
    assert int(ff.ticks[-1]["fault"]) == FaultKind.ESTOP and int(ff.ticks[-1]["phase"]) == Phase.HOLD
    ff.send(ClearFault())
    ff.step()
    assert any(isinstance(e, FaultCleared) for e in ff.events)
    with pytest.raises(TypeError, match="not a control command"):
        ff.send(("EStop",))


def test_run_until_stops_as_soon_as_the_condition_holds(ff):
    def first_frame(f):
        return len(f.frames) > 0

    taken = ff.run_until(first_frame, timeout_s=1.0)
    assert len(ff.frames) == 1 and 0 < taken < 0.1
    assert taken == pytest.approx(ff.now_s)
    assert ff.run_until(first_frame, timeout_s=1.0) == 0.0


def test_run_until_times_out_with_a_clear_message_after_exactly_the_budget(ff):
    def never(f):
        return False

    with pytest.raises(FastForwardTimeout, match=r"never did not come true within 0.5 s of simulated time"):
        ff.run_until(never, timeout_s=0.5)
    assert ff.tick_count == 500


def test_same_seed_same_run():
    def run():
        with FastForward(ControlConfig(), build_rig(RigSpec(seed=3))) as driver:
            driver.run_for(0.5)
            return driver.ticks.copy(), driver.frames.copy()

    (ticks_a, frames_a), (ticks_b, frames_b) = run(), run()
    for name in TICK_DTYPE.names:
        if name not in ("compute_s", "io_s"):  # wall-clock times, which a virtual clock cannot fix
            np.testing.assert_array_equal(ticks_a[name], ticks_b[name], err_msg=name)
    assert frames_a.tobytes() == frames_b.tobytes()


def test_close_holds_and_closes_the_rig_and_refuses_more_ticks():
    rig = build_rig(RigSpec())
    driver = FastForward(ControlConfig(), rig)
    driver.run_for(0.05)
    driver.close()
    driver.close()
    assert all(d.connection.name == "DISCONNECTED" for d in rig.devices())
    with pytest.raises(RuntimeError, match="closed"):
        driver.step()


def test_the_tick_applies_a_tare_the_loop_asks_for(ff, monkeypatch):
    tared = []
    monkeypatch.setattr(ff.rig.sensor, "tare", lambda: tared.append(ff.now_s))
    ff.run_for(0.1)
    ff.send(Tare())
    ff.step()
    assert tared == [pytest.approx(0.1)]
    assert any(isinstance(e, CommandApplied) and isinstance(e.command, Tare) and "tared" in e.message
               for e in ff.events)


def test_an_estop_while_moving_stops_within_the_braking_plan_and_says_how_far_it_went():
    # Before the simulated robot latched its stop point, an e-stop at 0.075 m/s travelled 4.2 mm (plan 0.94 mm).
    config = ControlConfig.from_mapping({"safety": {"velocity_limit_m_s": 0.1},
                                      "master": {"jog_speed_m_s": 0.075}})
    with FastForward(config, build_rig(RigSpec())) as driver:
        driver.run_for(0.05)
        driver.send(Jog((0.03, 0.0, 0.0)))
        driver.run_for(0.15)
        speed = float(np.linalg.norm(driver.rig.slave.latest().velocity_m_s))
        assert speed > 0.07
        driver.send(EStop("test"))
        driver.run_for(0.5)
        plan = speed**2 / (2 * 0.6 * driver.rig.slave.world.settings.robot.max_accel_m_s2)
        assert 0.5 * plan < driver.loop.stop_distance_m <= plan + 0.1e-3
        told = [e for e in driver.events if isinstance(e, Notice) and "came to rest" in e.message]
        assert len(told) == 1 and f"{driver.loop.stop_distance_m * 1e3:.2f} mm" in told[0].message
