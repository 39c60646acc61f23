"""The ``[hardware.sensor]`` and ``[hardware.master]`` tables every real rig reads alike: which tactile array
and which master, each checked key by key, and the devices built from them. The UDP rig and the CRTK rig
differ in their slave (and the UDP rig's array may also come through its link), not in these."""

from __future__ import annotations

from typing import Any

from hardware.interfaces import MasterDevice, TactileSensor
from hardware.serial_tactile.adapter import SerialTactileSensor, SerialTactileSettings
from hardware.settings import ConfigError
from hardware.usb.spacemouse import SpaceMouseMaster, SpaceMouseSettings
from hardware.usb.tactile import UsbTactileSensor, UsbTactileSettings

# the arrays a rig reads itself, and the masters; a kind whose settings are None takes none
ARRAY_KINDS: dict[str, type | None] = {"serial": SerialTactileSettings, "usb": UsbTactileSettings}
MASTER_KINDS: dict[str, type | None] = {"none": None, "spacemouse": SpaceMouseSettings}


def sub_table(data: dict, name: str, prefix: str) -> dict:
    """``data[name]`` (empty if absent), or a ConfigError if it is not a table."""
    table = data.get(name, {})
    if not isinstance(table, dict):
        raise ConfigError(f"{prefix}{name}", f"must be a table, got {table!r}")
    return table


def kind_of(table: dict, key: str, kinds: dict, default: str) -> str:
    kind = table.get("kind", default)
    if kind not in kinds:
        raise ConfigError(key, f"unknown kind {kind!r} (known: {', '.join(kinds)})")
    return kind


def kind_settings(table: dict, prefix: str, settings_cls: type | None, kind_name: str) -> Any:
    """The settings ``table``'s keys besides ``kind`` give ``settings_cls`` (None for a kind that takes none,
    and a ConfigError naming the first key if it was given some)."""
    keys = {k: v for k, v in table.items() if k != "kind"}
    if settings_cls is None:
        if keys:
            raise ConfigError(f"{prefix}{sorted(keys)[0]}",
                              f"unknown key for kind {kind_name!r} (it takes no settings)")
        return None
    return settings_cls.from_mapping(keys, prefix)


def master_settings(data: dict, prefix: str) -> tuple[str, SpaceMouseSettings | None]:
    """(kind, settings) of the ``master`` table of ``data``."""
    table = sub_table(data, "master", prefix)
    kind = kind_of(table, f"{prefix}master.kind", MASTER_KINDS, "none")
    return kind, kind_settings(table, f"{prefix}master.", MASTER_KINDS[kind], table.get("kind", "default"))


def devices_mapping(sensor_kind: str, sensor, master_kind: str, master) -> dict[str, Any]:
    """The ``sensor`` and ``master`` tables as a rig's settings give them back (for the session file)."""
    return {"sensor": {"kind": sensor_kind, **(sensor.to_mapping() if sensor else {})},
            "master": {"kind": master_kind, **(master.to_mapping() if master else {})}}


def build_array(kind: str, settings, usb_backend=None) -> TactileSensor:
    """The serial or USB array; ``usb_backend`` replaces libusb (the tests' emulated bus)."""
    if kind == "usb":
        return UsbTactileSensor(settings, backend=usb_backend)
    return SerialTactileSensor(settings)


def build_master(kind: str, settings, usb_backend=None) -> MasterDevice | None:
    return SpaceMouseMaster(settings, backend=usb_backend) if kind == "spacemouse" else None
