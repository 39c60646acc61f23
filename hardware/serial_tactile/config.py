"""Validated settings for the hardware backends (serial, USB, UDP), built from TOML tables.

Every settings class is a frozen dataclass whose ``__post_init__`` checks each value and raises
:class:`control.config.ConfigError` naming the key; :meth:`Settings.from_mapping` refuses unknown keys
and prefixes the key with where the table sits (``hardware.sensor.baud``), so the console reports a
bad hardware setting exactly like a bad control setting.
"""

from __future__ import annotations

import math
from dataclasses import asdict, fields
from typing import Any

from control.config import ConfigError


class Settings:
    @classmethod
    def from_mapping(cls, data: Any, prefix: str = ""):
        if not isinstance(data, dict):
            raise ConfigError(prefix.rstrip(".") or cls.__name__, f"must be a table, got {data!r}")
        known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"{prefix}{unknown[0]}", f"unknown key (known: {', '.join(sorted(known))})")
        try:
            return cls(**data)
        except ConfigError as err:
            raise ConfigError(f"{prefix}{err.key}", err.problem) from None

    def to_mapping(self) -> dict[str, Any]:
        """Back to a table (TOML has no null: unset optional values are left out)."""
        return {k: list(v) if isinstance(v, tuple) else v
                for k, v in asdict(self).items() if v is not None}  # type: ignore[call-overload]

    def _set(self, name: str, value: Any) -> None:
        object.__setattr__(self, name, value)


def number(key: str, value: Any) -> float:
    if isinstance(value, bool):
        raise ConfigError(key, f"must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(key, f"must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ConfigError(key, f"must be finite, got {value!r}")
    return v


def in_range(key: str, value: Any, lo: float, hi: float, why: str = "") -> float:
    v = number(key, value)
    if not lo <= v <= hi:
        raise ConfigError(key, f"must be within [{lo:g}, {hi:g}]{' (' + why + ')' if why else ''}, got {v:g}")
    return v


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
