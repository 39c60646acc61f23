"""Build the real-hardware rig: the robot behind the UDP link, a tactile array, an optional USB master.

Configured by the ``[hardware]`` tables of the TOML config (``rig.backend = "udp"``)::

    [hardware.slave]          # the UDP link to `palpation-console slave` (UdpLinkSettings)
    host = "127.0.0.1"
    port = 47600

    [hardware.sensor]         # kind = "udp": the slave forwards its sensor's frames over the link
    kind = "serial"           #        "serial": SerialTactileSettings keys (port, baud, calibration, ...)
    port = "/dev/serial/by-id/usb-Palpation_Lab_TSI-if00"   # "usb": UsbTactileSettings keys (vid_pid, ...)

    [hardware.master]         # kind = "none": X_d from the console's jog
    kind = "spacemouse"       #        "spacemouse": SpaceMouseSettings keys (vid_pid, speed_m_s, ...)

Every key is checked (:class:`control.config.ConfigError` names it, e.g. ``hardware.sensor.baud``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hardware.rig import Rig
from hardware.serial_tactile.adapter import SerialTactileSensor, SerialTactileSettings
from hardware.settings import ConfigError
from hardware.udp.link import UdpLinkSettings, UdpSlaveLink
from hardware.usb.spacemouse import SpaceMouseMaster, SpaceMouseSettings
from hardware.usb.tactile import UsbTactileSensor, UsbTactileSettings

SENSOR_KINDS = {"udp": None, "serial": SerialTactileSettings, "usb": UsbTactileSettings}
MASTER_KINDS = {"none": None, "spacemouse": SpaceMouseSettings}


def _kind(table: dict, key: str, kinds: dict, default: str) -> str:
    kind = table.get("kind", default)
    if kind not in kinds:
        raise ConfigError(key, f"unknown kind {kind!r} (known: {', '.join(kinds)})")
    return kind


@dataclass(frozen=True)
class HardwareSettings:
    slave: UdpLinkSettings = field(default_factory=UdpLinkSettings)
    sensor_kind: str = "udp"
    sensor: SerialTactileSettings | UsbTactileSettings | None = None
    master_kind: str = "none"
    master: SpaceMouseSettings | None = None

    @classmethod
    def from_mapping(cls, data: Any, prefix: str = "hardware.") -> HardwareSettings:
        if not isinstance(data, dict):
            raise ConfigError(prefix.rstrip("."), f"must be a table, got {data!r}")
        unknown = sorted(set(data) - {"slave", "sensor", "master"})
        if unknown:
            raise ConfigError(f"{prefix}{unknown[0]}", "unknown table (known: slave, sensor, master)")
        slave = UdpLinkSettings.from_mapping(data.get("slave", {}), f"{prefix}slave.")
        tables = {}
        for name in ("sensor", "master"):
            table = data.get(name, {})
            if not isinstance(table, dict):
                raise ConfigError(f"{prefix}{name}", f"must be a table, got {table!r}")
            tables[name] = table
        sensor_kind = _kind(tables["sensor"], f"{prefix}sensor.kind", SENSOR_KINDS, "udp")
        master_kind = _kind(tables["master"], f"{prefix}master.kind", MASTER_KINDS, "none")
        sensor_cls, master_cls = SENSOR_KINDS[sensor_kind], MASTER_KINDS[master_kind]
        sensor_table = {k: v for k, v in tables["sensor"].items() if k != "kind"}
        master_table = {k: v for k, v in tables["master"].items() if k != "kind"}
        for name, cls_, table in (("sensor", sensor_cls, sensor_table), ("master", master_cls, master_table)):
            if cls_ is None and table:
                raise ConfigError(f"{prefix}{name}.{sorted(table)[0]}",
                                  f"unknown key for kind {tables[name].get('kind', 'default')!r} "
                                  f"(it takes no settings)")
        return cls(slave=slave, sensor_kind=sensor_kind,
                   sensor=sensor_cls.from_mapping(sensor_table, f"{prefix}sensor.") if sensor_cls else None,
                   master_kind=master_kind,
                   master=master_cls.from_mapping(master_table, f"{prefix}master.") if master_cls else None)

    def to_mapping(self) -> dict[str, Any]:
        sensor = {"kind": self.sensor_kind, **(self.sensor.to_mapping() if self.sensor else {})}
        master = {"kind": self.master_kind, **(self.master.to_mapping() if self.master else {})}
        return {"slave": self.slave.to_mapping(), "sensor": sensor, "master": master}


def build_hardware_rig(settings: HardwareSettings, usb_backend=None) -> Rig:
    """Build (not open) the rig; ``usb_backend`` replaces libusb (the tests' emulated bus)."""
    link = UdpSlaveLink(settings.slave)
    if settings.sensor_kind == "serial":
        sensor = SerialTactileSensor(settings.sensor)  # type: ignore[arg-type]
    elif settings.sensor_kind == "usb":
        sensor = UsbTactileSensor(settings.sensor, backend=usb_backend)  # type: ignore[arg-type]
    else:
        sensor = link.tactile_sensor()
    master = SpaceMouseMaster(settings.master, backend=usb_backend) if settings.master_kind == "spacemouse" else None
    description = {"backend": "udp", "hardware": settings.to_mapping(), "slave": link.describe(),
                   "sensor": sensor.describe()}
    return Rig(sensor=sensor, slave=link, master=master, description=description)


def build_rig(spec) -> Rig:
    """``app.rigs.BACKENDS["udp"]``: the rig ``spec.hardware`` (the config's ``[hardware]`` table) describes."""
    return build_hardware_rig(HardwareSettings.from_mapping(spec.hardware, "hardware."))
