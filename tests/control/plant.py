"""Drives the loop alone against the exact layer plant of :mod:`hardware.sim.plant`, tick by tick."""

from __future__ import annotations

from control.config import ControlConfig
from control.loop import ControlLoop
from hardware.interfaces import MasterState, TactileConstraints
from hardware.sim.plant import LayerPlant


class Harness:
    """Drives a ControlLoop against a LayerPlant on a virtual 1 kHz clock."""

    def __init__(self, config: ControlConfig | None = None, plant: LayerPlant | None = None, master: bool = False):
        self.config = config or ControlConfig()
        self.plant = plant or LayerPlant()
        self.loop = ControlLoop(self.config, TactileConstraints(), has_master=master)
        self.now = 0.0
        self.events: list = []
        self.pending: list = []
        self.master_pos = tuple(self.plant.x)
        self.master_switch = True
        self.master = master
        self.results = []

    def send(self, *commands) -> None:
        self.pending.extend(commands)

    def run(self, seconds: float, until=None) -> None:
        n = int(round(seconds * self.config.rate_hz))
        for _ in range(n):
            self.tick()
            if until is not None and until(self):
                return

    def tick(self) -> None:
        p = self.plant
        p.poll(self.now)
        m = MasterState(int(self.now * 1e6), self.now, self.master_pos, self.master_switch) if self.master else None
        cmds, self.pending = self.pending, []
        r = self.loop.step(self.now, p.frame if p.sensor_alive else p.frame, p.slave(self.now), m, cmds)
        p.apply(r)
        self.events.extend(r.events)
        self.last = r
        self.now += 1.0 / self.config.rate_hz

    def of(self, kind):
        return [e for e in self.events if isinstance(e, kind)]
