"""What the campaigns' tests share."""

import pytest

from control import safety
from control.loop import ControlLoop


@pytest.fixture
def blind_loop(monkeypatch):
    """Make the loop blind to its ceilings from here on: the supervisor reads no force, pressure or depth, and
    the probe descends as fast as it is told, wherever the tissue and the ceiling are. A campaign must catch
    it (its checker can fail)."""
    check = safety.SafetySupervisor.check

    def blind(self, **readings):
        readings.update(force_N=0.0, max_pressure_pa=0.0, saturated_elements=0, indentation_m=float("nan"))
        return check(self, **readings)

    def make_blind():
        monkeypatch.setattr(safety.SafetySupervisor, "check", blind)
        monkeypatch.setattr(ControlLoop, "_descent_limit_m", lambda self, z, dt: -float("inf"))

    return make_blind
