"""Build the real-hardware rig: the robot behind the UDP link, a tactile array, an optional USB master.

Configured by the ``[hardware]`` tables of the TOML config (``rig.backend = "udp"``)::

    [hardware.slave]          # the UDP link to `palpation-console slave` (UdpLinkSettings)
    host = "127.0.0.1"
    port = 47600

    [hardware.sensor]         # kind = "udp": the slave forwards its sensor's frames over the link
    kind = "serial"           #        (ForwardedTactileSettings: the cover its maker states, cover_spread_m)
                              #        "serial": SerialTactileSettings keys (port, baud, calibration, ...)
    port = "/dev/serial/by-id/usb-Palpation_Lab_TSI-if00"   # "usb": UsbTactileSettings keys (vid_pid, ...)

    [hardware.master]         # kind = "none": X_d from the console's jog
    kind = "spacemouse"       #        "spacemouse": SpaceMouseSettings keys (vid_pid, speed_m_s, ...)

Every key is checked (:class:`control.config.ConfigError` names it, e.g. ``hardware.sensor.baud``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hardware.device_tables import (
    ARRAY_KINDS,
    build_array,
    build_master,
    devices_mapping,
    kind_of,
    kind_settings,
    master_settings,
    sub_table,
)
from hardware.rig import Rig
from hardware.serial_tactile.adapter import SerialTactileSettings
from hardware.settings import ConfigError
from hardware.udp.link import ForwardedTactileSettings, UdpLinkSettings, UdpSlaveLink
from hardware.usb.spacemouse import SpaceMouseSettings
from hardware.usb.tactile import UsbTactileSettings

# the array forwarded by the slave over the link, or one the console reads itself
SENSOR_KINDS = {"udp": ForwardedTactileSettings, **ARRAY_KINDS}


@dataclass(frozen=True)
class HardwareSettings:
    slave: UdpLinkSettings = field(default_factory=UdpLinkSettings)
    sensor_kind: str = "udp"
    sensor: ForwardedTactileSettings | SerialTactileSettings | UsbTactileSettings | None = None
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
        table = sub_table(data, "sensor", prefix)
        sensor_kind = kind_of(table, f"{prefix}sensor.kind", SENSOR_KINDS, "udp")
        sensor = kind_settings(table, f"{prefix}sensor.", SENSOR_KINDS[sensor_kind], table.get("kind", "default"))
        master_kind, master = master_settings(data, prefix)
        return cls(slave=slave, sensor_kind=sensor_kind, sensor=sensor, master_kind=master_kind, master=master)

    def to_mapping(self) -> dict[str, Any]:
        return {"slave": self.slave.to_mapping(),
                **devices_mapping(self.sensor_kind, self.sensor, self.master_kind, self.master)}


def build_hardware_rig(settings: HardwareSettings, usb_backend=None) -> Rig:
    """Build (not open) the rig; ``usb_backend`` replaces libusb (the tests' emulated bus)."""
    link = UdpSlaveLink(settings.slave)
    if settings.sensor_kind == "udp":
        sensor = link.tactile_sensor(settings.sensor.constraints() if settings.sensor is not None else None)
    else:
        sensor = build_array(settings.sensor_kind, settings.sensor, usb_backend)
    description = {"backend": "udp", "hardware": settings.to_mapping(), "slave": link.describe(),
                   "sensor": sensor.describe()}
    return Rig(sensor=sensor, slave=link,
               master=build_master(settings.master_kind, settings.master, usb_backend), description=description)


def build_rig(spec) -> Rig:
    """``app.rigs.BACKENDS["udp"]``: the rig ``spec.hardware`` (the config's ``[hardware]`` table) describes."""
    return build_hardware_rig(HardwareSettings.from_mapping(spec.hardware, "hardware."))
