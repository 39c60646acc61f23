"""A rig: the three devices the loop drives, opened, polled and closed together."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hardware.interfaces import MasterDevice, SlaveManipulator, TactileSensor


@dataclass
class Rig:
    sensor: TactileSensor
    slave: SlaveManipulator
    master: MasterDevice | None = None  # None: X_d comes from the console's jog
    ground_truth: list[dict[str, Any]] = field(default_factory=list)  # simulated rigs: the phantom's tumours
    description: dict[str, Any] = field(default_factory=dict)  # what was built, for the session file

    def devices(self):
        return [d for d in (self.sensor, self.slave, self.master) if d is not None]

    def open(self) -> None:
        opened = []
        try:
            for device in self.devices():
                device.open()
                opened.append(device)
        except BaseException:
            for device in reversed(opened):
                device.close()
            raise

    def close(self) -> None:
        for device in reversed(self.devices()):
            device.close()

    def poll(self, now_s: float) -> None:
        for device in self.devices():
            device.poll(now_s)
