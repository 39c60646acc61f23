"""The scripted operator: the Section IV-A protocol against a timetabled stand-in for the loop's feedback."""

import numpy as np
import pytest

from hardware.interfaces import ConnectionState, MasterFeedback, Phase
from hardware.settings import ConfigError
from hardware.sim.operator import ScriptedOperator
from hardware.sim.settings import OperatorSimSettings, SimSettings
from hardware.sim.world import SimWorld
from tissue.phantom import load_phantom, parse_phantom
from tissue.winkler import WinklerTissue

T0 = 12.0
MS = 1e-3
FAST = dict(lateral_speed_m_s=0.05, vertical_speed_m_s=0.05, dwell_above_s=0.1, dwell_after_s=0.1)


class TimetableLoop:
    """Stands in for the loop, on a fixed timetable after each switch-off: seek, settle, then the ending.

    Like the real loop it reacts a few ticks late, keeps "region done" set until the next area starts (so
    a stale flag is on display when the operator switches off), presses the TSI into the tissue while the
    switch is off, and when the operator takes z back it re-clutches: X_r = hand + offset from there on. A
    fault is cleared 0.3 s after it latched, re-clutching every axis, as clearing one does.
    """

    def __init__(self, world, ending="done", ramp_s=0.5, delay_ticks=3, press_m=0.008, untouched=()):
        self.robot = world.robot
        self.ending, self.ramp_s, self.delay, self.press_m = ending, ramp_s, delay_ticks, press_m
        self.untouched = set(untouched)  # the switch-offs (counted from 0) whose seek touches nothing
        self.switch_offs = 0
        self.phase, self.region_done, self.faulted = Phase.APPROACH, False, False
        self.offset = np.zeros(3)
        self._switch = True
        self._off_since = None
        self._ticks_since_edge = 0

    def step(self, now, state):
        hand = np.array(state.position_m)
        if state.sz_switch != self._switch:
            self._switch = state.sz_switch
            self._ticks_since_edge = 0
            if self._switch:
                self._off_since = None
                self.offset = np.array(self.robot.reference) - hand
        self._ticks_since_edge += 1
        if self._ticks_since_edge == self.delay and not self._switch:
            self._off_since = now
            self.region_done, self.faulted = False, False
            self.phase = Phase.SEEK_CONTACT
            self._seek_only = self.switch_offs in self.untouched
            self.switch_offs += 1
        elif self._ticks_since_edge == self.delay and self.phase != Phase.HOLD:
            self.phase = Phase.APPROACH
        reference = hand + self.offset
        if self._off_since is not None:
            t = now - self._off_since
            reference[2] -= self.press_m * min(1.0, t / self.ramp_s)
            if self._seek_only:
                if t >= self.ramp_s and self.phase == Phase.SEEK_CONTACT:
                    self.phase = Phase.RETRACT  # no tissue within the seek's depth: aborted
                elif t >= self.ramp_s + 0.1 and self.phase == Phase.RETRACT:
                    self.phase = Phase.APPROACH
            elif 0.1 <= t < self.ramp_s:
                self.phase = Phase.SETTLING
            elif t >= self.ramp_s and self.phase == Phase.SETTLING:
                if self.ending == "done":
                    self.phase, self.region_done = Phase.RETRACT, True
                elif self.ending == "aborted":
                    self.phase = Phase.RETRACT
                else:
                    self.phase, self.faulted = Phase.HOLD, True
            elif t >= self.ramp_s + 0.1 and self.phase == Phase.RETRACT:
                self.phase = Phase.DONE if self.region_done else Phase.APPROACH
            elif t >= self.ramp_s + 0.3 and self.faulted:  # cleared (by whoever watches the console): re-clutched
                self.phase, self.faulted, self._off_since = Phase.APPROACH, False, None
                self.offset = np.array(self.robot.reference) - hand
                reference = hand + self.offset
        self.robot.set_reference(tuple(reference), (0.0, 0.0, 0.0))
        return MasterFeedback(now, int(self.phase), self.region_done, 0.0, self.faulted)


def short_phantom():
    """Three areas instead of the flat phantom's nine, for the tests about what happens per area."""
    return parse_phantom({"phantom": {"name": "short", "length_m": 0.024, "width_m": 0.030, "thickness_m": 0.025,
                                      "youngs_modulus_pa": 20e3, "poisson_ratio": 0.49}})


def make_operator(ph=None, **operator):
    ph = ph if ph is not None else load_phantom("flat")
    world = SimWorld(ph, WinklerTissue(ph), SimSettings(operator=OperatorSimSettings(**{**FAST, **operator})))
    op = ScriptedOperator(world)
    op.open()
    return op


def drive(op, loop=None, limit_s=120.0):
    """Poll at 1 kHz to the end of the script; the operator's readings and the TSI positions."""
    states, tsi = [], []
    m = 0
    while not op.finished and m * MS < limit_s:
        now = T0 + m * MS
        op.poll(now)
        states.append(op.latest())
        if loop is not None:
            op.feedback(loop.step(now, states[-1]))
        tsi.append(op.world.state_at(now)[0])
        m += 1
    for k in range(50):  # a little past the end: it stays home
        op.poll(T0 + (m + k) * MS)
        states.append(op.latest())
    return states, np.array(tsi)


def test_visits_every_area_in_order_and_flips_the_switch_at_each():
    op = make_operator()
    states, tsi = drive(op, TimetableLoop(op.world))
    assert op.finished
    pos = np.array([s.position_m for s in states])
    sz = np.array([s.sz_switch for s in states])
    offs = np.flatnonzero(sz[:-1] & ~sz[1:]) + 1
    ons = np.flatnonzero(~sz[:-1] & sz[1:]) + 1
    regions = load_phantom("flat").palpation_regions()
    assert len(offs) == len(ons) == len(regions) == 9
    assert np.all(offs < ons) and np.all(ons[:-1] < offs[1:])
    for i, k in enumerate(offs):
        # the TSI, not the hand: each area's re-clutch moved the hand 8 mm (the press) further from it
        assert tsi[k, :2] == pytest.approx(regions[i], abs=1e-6)
        assert tsi[k, 2] == pytest.approx(0.025 + 0.0015, abs=1e-5)  # clearance above the flat surface
        assert pos[k, 2] == pytest.approx(0.0265 + 0.008 * i, abs=1e-5)
        assert np.all(pos[k:ons[i], :] == pos[k])  # the hand stays put while the loop works
    assert [o.result for o in op.outcomes] == ["done"] * 9
    assert [o.index for o in op.outcomes] == list(range(9))
    assert all(o.ended_s - o.switched_off_s >= 0.5 for o in op.outcomes)  # the stale flag was not taken
    assert tsi[-1] == pytest.approx(op.home_m, abs=1e-5)
    assert sz[-1]


def test_moves_are_smooth_speed_limited_and_lateral_only_at_travel_height():
    op = make_operator(short_phantom(), lateral_speed_m_s=0.04, vertical_speed_m_s=0.02)
    states, tsi = drive(op, TimetableLoop(op.world))
    assert [s.seq for s in states] == list(range(len(states)))
    assert all(abs(s.t_s - (T0 + s.seq * MS)) < 1e-9 for s in states)
    pos = np.array([s.position_m for s in states])
    v = np.diff(pos, axis=0) / MS
    lateral = np.hypot(v[:, 0], v[:, 1])
    assert lateral.max() <= 0.04 * (1 + 1e-6)
    assert lateral.max() > 0.039
    assert np.abs(v[:, 2]).max() <= 0.02 * (1 + 1e-6)
    assert np.abs(v[:, 2]).max() > 0.0195
    assert np.abs(np.diff(v, axis=0)).max() / MS < 0.5  # no jumps in speed: minimum-jerk moves
    moving_sideways = lateral > 1e-6
    assert moving_sideways.any()
    # the TSI (the hand is offset by the loop's clutch) moves sideways only at travel height
    assert np.allclose(tsi[1:][moving_sideways[:len(tsi) - 1], 2], 0.045, rtol=0.0, atol=0.1e-3)


@pytest.mark.parametrize("ending", ["aborted", "fault"])
def test_an_area_that_ends_without_done_is_left_and_the_next_one_palpated(ending):
    op = make_operator(short_phantom())
    states, _ = drive(op, TimetableLoop(op.world, ending=ending))
    assert op.finished
    assert [o.result for o in op.outcomes] == [ending] * 3
    sz = np.array([s.sz_switch for s in states])
    assert np.count_nonzero(sz[:-1] & ~sz[1:]) == 3


def test_an_area_whose_seek_touched_nothing_is_tried_once_more_from_the_highest_point_under_the_tsi():
    """The second area's seek touches nothing, twice: it is tried once more, switched off with the face level
    with the tissue (25 mm) instead of 1.5 mm above it, and then left; an area aborted after touching the
    tissue is not tried again."""
    op = make_operator(short_phantom())
    loop = TimetableLoop(op.world, untouched={1, 2})
    states, tsi = drive(op, loop)
    assert op.finished
    assert [(o.index, o.result) for o in op.outcomes] == [(0, "done"), (1, "aborted"), (1, "aborted"), (2, "done")]
    sz = np.array([s.sz_switch for s in states])
    offs = np.flatnonzero(sz[:-1] & ~sz[1:]) + 1
    regions = op.regions
    np.testing.assert_allclose(tsi[offs, :2], [regions[0], regions[1], regions[1], regions[2]], atol=1e-6)
    assert tsi[offs, 2] == pytest.approx([0.0265, 0.0265, 0.025, 0.0265], abs=1e-5)
    op = make_operator(short_phantom())
    drive(op, TimetableLoop(op.world, ending="aborted"))
    assert [o.result for o in op.outcomes] == ["aborted"] * 3


def test_gives_up_on_an_area_the_loop_never_finishes():
    op = make_operator(short_phantom(), region_timeout_s=0.4)
    drive(op)
    assert op.finished
    assert [o.result for o in op.outcomes] == ["timeout"] * 3
    assert all(o.ended_s - o.switched_off_s == pytest.approx(0.4) for o in op.outcomes)


def test_approaches_above_the_highest_point_under_the_tsi():
    bumpy = parse_phantom({"phantom": {
        "name": "bumpy", "length_m": 0.072, "width_m": 0.030, "thickness_m": 0.025, "youngs_modulus_pa": 20e3,
        "poisson_ratio": 0.49,
        "surface": [{"kind": "half_cylinder", "centre_y_m": 0.025, "radius_m": 0.005, "x_range_m": [0.0, 0.0235]}],
    }})
    op = make_operator(bumpy)
    heights = op.approach_heights_m
    assert heights[:3] == pytest.approx([0.0315] * 3, abs=1e-9)  # the bump's crest, 30 mm, + 1.5 mm
    assert heights[3:] == pytest.approx([0.0265] * 6, abs=1e-9)


def test_a_travel_height_that_does_not_clear_the_tissue_is_refused():
    with pytest.raises(ConfigError, match=r"operator\.travel_height_m.*does not clear phantom 'flat'"):
        make_operator(travel_height_m=0.026)
    with pytest.raises(ConfigError, match=r"operator\.travel_height_m.*above the robot's workspace"):
        make_operator(travel_height_m=0.2)


def test_no_positions_while_disconnected():
    ph = load_phantom("flat")
    op = ScriptedOperator(SimWorld(ph, WinklerTissue(ph)))
    assert op.connection == ConnectionState.DISCONNECTED
    op.poll(T0)
    assert op.latest() is None
    op.open()
    op.poll(T0 + MS)
    first = op.latest()
    assert first.position_m == op.home_m and first.sz_switch is True
    op.simulate_unplug()
    op.poll(T0 + 2 * MS)
    assert op.connection == ConnectionState.LOST and op.latest() is first
