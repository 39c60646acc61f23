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

A CRTK arm carries no tactile array of its own, so one of the real arrays must be named; every key is checked
(:class:`hardware.settings.ConfigError` names it, e.g. ``hardware.slave.domain``).
"""

from __future__ import annotations

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
from hardware.rig import Rig
from hardware.serial_tactile.adapter import SerialTactileSettings
from hardware.settings import ConfigError
from hardware.usb.spacemouse import SpaceMouseSettings
from hardware.usb.tactile import UsbTactileSettings


@dataclass(frozen=True)
class CrtkHardwareSettings:
    slave: CrtkSettings = field(default_factory=CrtkSettings)
    sensor_kind: str = "serial"
    sensor: SerialTactileSettings | UsbTactileSettings | None = None
    master_kind: str = "none"
    master: SpaceMouseSettings | None = None

    @classmethod
    def from_mapping(cls, data: Any, prefix: str = "hardware.") -> CrtkHardwareSettings:
        if not isinstance(data, dict):
            raise ConfigError(prefix.rstrip("."), f"must be a table, got {data!r}")
        unknown = sorted(set(data) - {"slave", "sensor", "master"})
        if unknown:
            raise ConfigError(f"{prefix}{unknown[0]}", "unknown table (known: slave, sensor, master)")
        slave = CrtkSettings.from_mapping(sub_table(data, "slave", prefix), f"{prefix}slave.")
        table = sub_table(data, "sensor", prefix)
        sensor_kind = table.get("kind")
        if sensor_kind not in ARRAY_KINDS:
            raise ConfigError(f"{prefix}sensor.kind", f"the CRTK rig takes its tactile array from "
                              f"{' or '.join(ARRAY_KINDS)}, got {sensor_kind!r}")
        sensor = kind_settings(table, f"{prefix}sensor.", ARRAY_KINDS[sensor_kind], sensor_kind)
        master_kind, master = master_settings(data, prefix)
        return cls(slave=slave, sensor_kind=sensor_kind, sensor=sensor, master_kind=master_kind, master=master)

    def to_mapping(self) -> dict[str, Any]:
        return {"slave": self.slave.to_mapping(),
                **devices_mapping(self.sensor_kind, self.sensor, self.master_kind, self.master)}


def build_crtk_rig(settings: CrtkHardwareSettings, usb_backend=None) -> Rig:
    """Build (not open) the rig; ``usb_backend`` replaces libusb (the tests' emulated bus)."""
    slave = CrtkSlave(settings.slave)
    sensor = build_array(settings.sensor_kind, settings.sensor, usb_backend)
    description = {"backend": "crtk", "hardware": settings.to_mapping(), "slave": slave.describe(),
                   "sensor": sensor.describe()}
    return Rig(sensor=sensor, slave=slave,
               master=build_master(settings.master_kind, settings.master, usb_backend), description=description)


def build_rig(spec) -> Rig:
    """``app.rigs.BACKENDS["crtk"]``: the rig ``spec.hardware`` (the config's ``[hardware]`` table) describes."""
    return build_crtk_rig(CrtkHardwareSettings.from_mapping(spec.hardware, "hardware."))
