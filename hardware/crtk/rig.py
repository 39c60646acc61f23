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
from hardware.rig import Rig
from hardware.serial_tactile.adapter import SerialTactileSensor, SerialTactileSettings
from hardware.settings import ConfigError
from hardware.usb.spacemouse import SpaceMouseMaster, SpaceMouseSettings
from hardware.usb.tactile import UsbTactileSensor, UsbTactileSettings

SENSOR_KINDS: dict[str, type] = {"serial": SerialTactileSettings, "usb": UsbTactileSettings}
MASTER_KINDS: dict[str, type | None] = {"none": None, "spacemouse": SpaceMouseSettings}


def _table(data: dict, name: str, prefix: str) -> dict:
    table = data.get(name, {})
    if not isinstance(table, dict):
        raise ConfigError(f"{prefix}{name}", f"must be a table, got {table!r}")
    return table


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
        slave = CrtkSettings.from_mapping(_table(data, "slave", prefix), f"{prefix}slave.")
        sensor_table, master_table = _table(data, "sensor", prefix), _table(data, "master", prefix)
        sensor_kind = sensor_table.get("kind")
        if sensor_kind not in SENSOR_KINDS:
            raise ConfigError(f"{prefix}sensor.kind", f"the CRTK rig takes its tactile array from "
                              f"{' or '.join(SENSOR_KINDS)}, got {sensor_kind!r}")
        master_kind = master_table.get("kind", "none")
        if master_kind not in MASTER_KINDS:
            raise ConfigError(f"{prefix}master.kind",
                              f"unknown kind {master_kind!r} (known: {', '.join(MASTER_KINDS)})")
        sensor = SENSOR_KINDS[sensor_kind].from_mapping({k: v for k, v in sensor_table.items() if k != "kind"},
                                                        f"{prefix}sensor.")
        master_cls = MASTER_KINDS[master_kind]
        master_keys = {k: v for k, v in master_table.items() if k != "kind"}
        if master_cls is None and master_keys:
            raise ConfigError(f"{prefix}master.{sorted(master_keys)[0]}", "unknown key for kind 'none' (it takes no "
                              "settings)")
        master = master_cls.from_mapping(master_keys, f"{prefix}master.") if master_cls else None
        return cls(slave=slave, sensor_kind=sensor_kind, sensor=sensor, master_kind=master_kind, master=master)

    def to_mapping(self) -> dict[str, Any]:
        sensor = {"kind": self.sensor_kind, **(self.sensor.to_mapping() if self.sensor else {})}
        master = {"kind": self.master_kind, **(self.master.to_mapping() if self.master else {})}
        return {"slave": self.slave.to_mapping(), "sensor": sensor, "master": master}


def build_crtk_rig(settings: CrtkHardwareSettings, usb_backend=None) -> Rig:
    """Build (not open) the rig; ``usb_backend`` replaces libusb (the tests' emulated bus)."""
    slave = CrtkSlave(settings.slave)
    if settings.sensor_kind == "usb":
        sensor = UsbTactileSensor(settings.sensor, backend=usb_backend)  # type: ignore[arg-type]
    else:
        sensor = SerialTactileSensor(settings.sensor)  # type: ignore[arg-type]
    master = SpaceMouseMaster(settings.master, backend=usb_backend) if settings.master_kind == "spacemouse" else None
    description = {"backend": "crtk", "hardware": settings.to_mapping(), "slave": slave.describe(),
                   "sensor": sensor.describe()}
    return Rig(sensor=sensor, slave=slave, master=master, description=description)


def build_rig(spec) -> Rig:
    """``app.rigs.BACKENDS["crtk"]``: the rig ``spec.hardware`` (the config's ``[hardware]`` table) describes."""
    return build_crtk_rig(CrtkHardwareSettings.from_mapping(spec.hardware, "hardware."))
