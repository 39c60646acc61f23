"""The simulated tactile array on a real arm: the CRTK rig with ``[hardware.sensor] kind = "sim"``.

The arm (the fake dVRK arm in tests and benchmarks) moves the probe; the array is hardware/sim's
:class:`~hardware.sim.sensor.SimTactileSensor` pressing the phantom's tissue model wherever the arm's
``measured_cp`` put the probe at each frame's sampling instant. That sensor asks its world for the tissue, the
probe's pose at an instant and the instants of its frames; on the simulated rig the world integrates a
simulated robot, here :class:`ArmPoseWorld` answers from the arm's readings instead. Nothing of the tissue's or
the array's physics is computed here.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from typing import Any

from hardware.interfaces import DeviceError, SlaveManipulator, TactileSensor, Vec3
from hardware.sim.rig import build_tissue
from hardware.sim.sensor import SimTactileSensor
from hardware.sim.settings import SimSettings
from hardware.sim.tissue import TissueModel
from tissue.phantom import load_phantom

HISTORY_S = 0.5  # as the simulated world keeps: past the array's latency and a slow poll or two
_GRID_EPS = 1e-6


class ArmPoseWorld:
    """What a :class:`SimTactileSensor` asks of its world, with the arm's readings for the robot: the probe's
    position at an instant is interpolated between the arm's readings around it (the oldest kept before the
    first); the frames' instants are ``epoch + m / rate`` from the first :meth:`advance`, as on the simulated
    rig, but the world's present is the newest instant the arm has reported: a frame sampled after it would
    describe where the probe was last reported, not where it is. (The arm's readings arrive late and in bursts
    when its process or the bus stalls: frames made meanwhile from the last pose read the tissue 1.8 mm
    shallower than the arm then reported, and the loop rightly took the array for dead.)"""

    def __init__(self, arm: SlaveManipulator, tissue: TissueModel, settings: SimSettings):
        self.arm = arm
        self.tissue = tissue
        self.settings = settings
        self.epoch_s: float | None = None
        self._now_s = -math.inf
        keep = max(16, int(HISTORY_S * arm.constraints.rate_hz))
        self._t: deque[float] = deque(maxlen=keep)
        self._states: deque[tuple[Vec3, Vec3]] = deque(maxlen=keep)
        self._seq: int | None = None

    def advance(self, now_s: float) -> None:
        if self.epoch_s is None:
            self.epoch_s = now_s
        self._now_s = max(self._now_s, now_s)
        state = self.arm.latest()
        if state is None or state.seq == self._seq:
            return
        self._seq = state.seq
        if self._t and state.t_s <= self._t[-1]:
            return  # a reading stamped no later than the one before it adds nothing to interpolate
        self._t.append(state.t_s)
        self._states.append((state.position_m, state.velocity_m_s))

    def state_at(self, t_s: float) -> tuple[Vec3, Vec3]:
        if not self._t:
            raise DeviceError("the simulated array on the arm: no reading of the arm's pose yet")
        k = bisect.bisect_right(self._t, t_s)
        if k == 0:
            return self._states[0]
        if k == len(self._t):
            return self._states[-1]
        t0, t1 = self._t[k - 1], self._t[k]
        (x0, v0), (x1, v1) = self._states[k - 1], self._states[k]
        f = (t_s - t0) / (t1 - t0)
        return (tuple(a + f * (b - a) for a, b in zip(x0, x1)),  # type: ignore[return-value]
                tuple(a + f * (b - a) for a, b in zip(v0, v1)))

    def instant_index(self, rate_hz: float) -> int:
        present = min(self._now_s, self._t[-1]) if self._t else self.epoch_s
        return math.floor((present - self.epoch_s) * rate_hz + _GRID_EPS)

    def instant_s(self, m: int, rate_hz: float) -> float:
        return self.epoch_s + m / rate_hz


def sim_array(phantom: str, sim: dict[str, Any], seed: int, arm: SlaveManipulator
              ) -> tuple[TactileSensor, dict[str, Any]]:
    """The simulated array of ``[sim]`` settings ``sim`` on ``arm``, pressing ``phantom``; and its description.
    The tissue model comes from the disk cache :func:`app.rigs.prepare_rig` filled."""
    settings = SimSettings.from_mapping(dict(sim))
    tissue = build_tissue(load_phantom(phantom), settings)
    sensor = SimTactileSensor(ArmPoseWorld(arm, tissue, settings), seed=seed)
    return sensor, {"kind": "sim", "phantom": tissue.phantom.name, "phantom_hash": tissue.phantom.content_hash(),
                    "tissue_model": type(tissue).__name__, "seed": seed, "settings": settings.to_mapping()}
