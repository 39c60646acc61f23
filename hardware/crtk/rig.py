"""Build the CRTK rig: a CRTK arm (the dVRK's PSM) as the slave, a tactile array, an optional USB master.

Configured by the ``[hardware]`` tables of the TOML config (``rig.backend = "crtk"``)::

    [hardware.slave]          # the arm (CrtkSettings)
    arm = "PSM1"
    domain = 0                # the ROS side's ROS_DOMAIN_ID
    tissue_in_base_m = [0.0, 0.0, -0.15]
    probe_in_tool_m = [0.0, 0.0, 0.012]

    [hardware.sensor]         # the tactile array, as for the UDP rig:
    kind = "serial"           #   "serial": SerialTactileSettings keys (port, baud, calibration, ...)
    port = "/dev/serial/by-id/usb-Palpation_Lab_TSI-if00"   # "usb": UsbTactileSettings keys (vid_pid, ...)

    [hardware.master]         # kind = "none": X_d from the console's jog
    kind = "spacemouse"       #        "spacemouse": SpaceMouseSettings keys (vid_pid, speed_m_s, ...)

    [hardware.bus]            # the palpation on the ROS 2 bus, on the arm's domain (app/ros_bus.py)
    publish = true

A CRTK arm carries no tactile array of its own, so an array must be named: a real one, or ``kind = "sim"``, the
simulated array of hardware/sim pressing the ``[rig] phantom`` wherever the arm's pose puts it (a test and
benchmark rig: the composition root builds it, :mod:`app.crtk_sim`, since no real backend imports the
simulator). Every key is checked (:class:`hardware.settings.ConfigError` names it, e.g.
``hardware.slave.domain``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from hardware.crtk.slave import CrtkSettings, CrtkSlave
from hardware.device_tables import (
    ARRAY_KINDS,
    build_array,
    build_master,
    devices_mapping,
    kind_settings,
    master_settings,
    sub_table,
)
from hardware.interfaces import TactileSensor
from hardware.rig import Rig
from hardware.serial_tactile.adapter import SerialTactileSettings
from hardware.serial_tactile.config import boolean
from hardware.settings import ConfigError, Settings
from hardware.usb.spacemouse import SpaceMouseSettings
from hardware.usb.tactile import UsbTactileSettings

SIM_ARRAY = "sim"  # the simulated array on the arm's pose


@dataclass(frozen=True)
class BusSettings(Settings):
    # A lab that drives its arm through ROS 2 records with rosbag2: the console's topics are there unasked.
    publish: bool = True

    def __post_init__(self):
        self._set("publish", boolean("publish", self.publish))


@dataclass(frozen=True)
class CrtkHardwareSettings:
    slave: CrtkSettings = field(default_factory=CrtkSettings)
    sensor_kind: str = "serial"
    sensor: SerialTactileSettings | UsbTactileSettings | None = None
    master_kind: str = "none"
    master: SpaceMouseSettings | None = None
    bus: BusSettings = field(default_factory=BusSettings)

    @classmethod
    def from_mapping(cls, data: Any, prefix: str = "hardware.") -> CrtkHardwareSettings:
        if not isinstance(data, dict):
            raise ConfigError(prefix.rstrip("."), f"must be a table, got {data!r}")
        unknown = sorted(set(data) - {"slave", "sensor", "master", "bus"})
        if unknown:
            raise ConfigError(f"{prefix}{unknown[0]}", "unknown table (known: slave, sensor, master, bus)")
        slave = CrtkSettings.from_mapping(sub_table(data, "slave", prefix), f"{prefix}slave.")
        table = sub_table(data, "sensor", prefix)
        sensor_kind = table.get("kind")
        kinds = {**ARRAY_KINDS, SIM_ARRAY: None}
        if sensor_kind not in kinds:
            raise ConfigError(f"{prefix}sensor.kind", f"the CRTK rig takes its tactile array from "
                              f"{', '.join(ARRAY_KINDS)} or {SIM_ARRAY}, got {sensor_kind!r}")
        sensor = kind_settings(table, f"{prefix}sensor.", kinds[sensor_kind], sensor_kind)
        master_kind, master = master_settings(data, prefix)
        bus = BusSettings.from_mapping(sub_table(data, "bus", prefix), f"{prefix}bus.")
        return cls(slave=slave, sensor_kind=sensor_kind, sensor=sensor, master_kind=master_kind, master=master,
                   bus=bus)

    def to_mapping(self) -> dict[str, Any]:
        return {"slave": self.slave.to_mapping(),
                **devices_mapping(self.sensor_kind, self.sensor, self.master_kind, self.master),
                "bus": self.bus.to_mapping()}


# (arm) -> (the simulated array on it, what it is, for the session file)
SimArray = Callable[[CrtkSlave], tuple[TactileSensor, dict[str, Any]]]


def build_crtk_rig(settings: CrtkHardwareSettings, usb_backend=None, sim_array: SimArray | None = None) -> Rig:
    """Build (not open) the rig; ``usb_backend`` replaces libusb (the tests' emulated bus); ``sim_array``
    makes the simulated array on the arm (``sensor.kind = "sim"``)."""
    slave = CrtkSlave(settings.slave)
    if settings.sensor_kind == SIM_ARRAY:
        if sim_array is None:
            raise ConfigError("hardware.sensor.kind", "the simulated array is built by the console (app.crtk_sim)")
        sensor, described = sim_array(slave)
    else:
        sensor = build_array(settings.sensor_kind, settings.sensor, usb_backend)
        described = sensor.describe()
    description = {"backend": "crtk", "hardware": settings.to_mapping(), "slave": slave.describe(),
                   "sensor": described}
    return Rig(sensor=sensor, slave=slave,
               master=build_master(settings.master_kind, settings.master, usb_backend), description=description)


def build_rig(spec, sim_array: SimArray | None = None) -> Rig:
    """``app.rigs.BACKENDS["crtk"]``: the rig ``spec.hardware`` (the config's ``[hardware]`` table) describes."""
    return build_crtk_rig(CrtkHardwareSettings.from_mapping(spec.hardware, "hardware."), sim_array=sim_array)
