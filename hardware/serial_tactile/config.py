"""Validated settings for the hardware backends (serial, USB, UDP), built from TOML tables.

Every settings class is a frozen dataclass whose ``__post_init__`` checks each value and raises
:class:`control.config.ConfigError` naming the key; :meth:`Settings.from_mapping` refuses unknown keys
and prefixes the key with where the table sits (``hardware.sensor.baud``), so the console reports a
bad hardware setting exactly like a bad control setting.
"""

from __future__ import annotations

from typing import Any

from hardware.settings import ConfigError


def integer(key: str, value: Any, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(key, f"must be an integer, got {value!r}")
    if not lo <= value <= hi:
        raise ConfigError(key, f"must be within [{lo}, {hi}], got {value}")
    return value


def boolean(key: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(key, f"must be true or false, got {value!r}")
    return value


def text(key: str, value: Any, allow_empty: bool = False) -> str:
    if not isinstance(value, str) or (not allow_empty and not value.strip()):
        raise ConfigError(key, f"must be {'text' if allow_empty else 'non-empty text'}, got {value!r}")
    return value


def optional_path(key: str, value: Any) -> str | None:
    if value is None or value == "":
        return None
    return text(key, value)


def vid_pid(key: str, value: Any) -> tuple[int, int]:
    """A USB id written ``"256f:c635"`` (hex, as lsusb prints it)."""
    if isinstance(value, (list, tuple)) and len(value) == 2 and all(isinstance(v, int) for v in value):
        vid, pid = value
    elif isinstance(value, str) and value.count(":") == 1:
        try:
            vid, pid = (int(part, 16) for part in value.split(":"))
        except ValueError:
            raise ConfigError(key, f"must be a USB id like \"256f:c635\" (hex vendor:product), got {value!r}") from None
    else:
        raise ConfigError(key, f"must be a USB id like \"256f:c635\" (hex vendor:product), got {value!r}")
    if not (0 <= vid <= 0xFFFF and 0 <= pid <= 0xFFFF):
        raise ConfigError(key, f"vendor and product ids are 16-bit, got {value!r}")
    return vid, pid


def format_vid_pid(ids: tuple[int, int]) -> str:
    return f"{ids[0]:04x}:{ids[1]:04x}"
