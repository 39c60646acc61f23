"""How far the probe may go deeper without the force rising as tissue would (issue 49)."""

import math

from hardware.liveness import TravelWatch


def _travel(watch, readings):
    for force_N, z_m in readings:
        watch.push(force_N, z_m)
    return watch.travel_m(readings[-1][1])


def test_tissue_pushing_back_keeps_the_travel_at_nothing():
    watch = TravelWatch(rise_N=5e-3, softest_N_m=50.0, engaged_N=0.25)
    # 0.65 N/mm, the paper's phantom, from 0.3 N on: each frame's rise answers its travel
    readings = [(0.3 + 650.0 * k * 1e-5, 0.020 - k * 1e-5) for k in range(100)]
    assert _travel(watch, readings) <= 1e-5


def test_a_reading_that_creeps_up_by_millinewtons_while_the_probe_sinks_is_travel_unexplained():
    """The fault campaign's drifting array (seed 7779): 20 mN over 0.7 mm, each frame a little higher than the
    last, which a watch content with any 5 mN rise took for tissue."""
    watch = TravelWatch(rise_N=5e-3, softest_N_m=50.0, engaged_N=0.25)
    readings = [(0.60 + 0.0003 * k, 0.020 - k * 1e-5) for k in range(70)]
    assert math.isclose(_travel(watch, readings), 0.69e-3, rel_tol=0.02)
    assert _travel(TravelWatch(rise_N=5e-3), readings) < 0.1e-3  # the old rule


def test_before_the_face_bears_on_the_tissue_any_rise_will_do():
    """A first touch on a ridge rises by millinewtons a millimetre (the paper's uneven phantom at a bump's edge):
    below engaged_N the rise alone counts."""
    watch = TravelWatch(rise_N=5e-3, softest_N_m=50.0, engaged_N=0.25)
    readings = [(0.006 * k, 0.020 - k * 1e-4) for k in range(8)]  # 6 mN per 0.1 mm
    assert _travel(watch, readings) < 0.15e-3
