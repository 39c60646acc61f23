"""The settings vocabulary every floor shares: a settings base that reads TOML tables, and validators.

Every settings object in the project (control, simulator, hardware backends) is a frozen dataclass built on
:class:`Settings`; it refuses an invalid value with :class:`ConfigError`, whose message names the full key
and the problem, so the same check serves the TOML loader, the GUI and the command queue.
"""

from __future__ import annotations

import math
from dataclasses import asdict, fields, replace
from pathlib import Path
from typing import Any, ClassVar

from tissue import files

Vec3 = tuple[float, float, float]


class ConfigError(ValueError):
    def __init__(self, key: str, problem: str):
        super().__init__(f"{key}: {problem}")
        self.key = key
        self.problem = problem


def read_toml(path: Path, what: str = "configuration file") -> dict[str, Any]:
    """A TOML file's table, or ConfigError(path, one line) for any file that cannot serve
    (:func:`tissue.files.read_toml` says which)."""
    try:
        return files.read_toml(path, what)
    except files.UnreadableFile as err:
        raise ConfigError(err.path, err.problem) from None


def number(key: str, value: Any) -> float:
    """A finite number (TOML's true/false and strings such as "12" are refused, not read as numbers)."""
    if isinstance(value, (bool, str, bytes)):
        raise ConfigError(key, f"must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(key, f"must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ConfigError(key, f"must be finite, got {value!r}")
    return v


def positive(key: str, value: Any) -> float:
    v = number(key, value)
    if v <= 0:
        raise ConfigError(key, f"must be > 0, got {v:g}")
    return v


def bounded(key: str, value: Any, lo: float = -math.inf, hi: float = math.inf, why: str = "") -> float:
    """A number in [lo, hi] (one side open where its bound is infinite); ``why`` says where the bounds come
    from."""
    v = number(key, value)
    if not lo <= v <= hi:
        if lo == -math.inf:
            rule = f"must be <= {hi:g}"
        elif hi == math.inf:
            rule = f"must be >= {lo:g}"
        else:
            rule = f"must lie between {lo:g} and {hi:g}"
        raise ConfigError(key, f"{rule}{f' ({why})' if why else ''}, got {v:g}")
    return v


def non_negative(key: str, value: Any) -> float:
    return bounded(key, value, lo=0.0)


def vec3(key: str, value: Any, is_positive: bool = False) -> Vec3:
    if isinstance(value, (str, bytes)):
        raise ConfigError(key, f"must be three numbers [x, y, z], got {value!r}")
    try:
        items = list(value)
    except TypeError:
        raise ConfigError(key, f"must be three numbers [x, y, z], got {value!r}") from None
    if len(items) != 3:
        raise ConfigError(key, f"must be three numbers [x, y, z], got {len(items)}")
    check = positive if is_positive else number
    return tuple(check(f"{key}[{i}]", v) for i, v in enumerate(items))  # type: ignore[return-value]


class Settings:
    """Base of every settings dataclass in the project: built from a TOML table with unknown keys refused
    (nested tables through ``_nested``), errors naming the full key, and dumped back to a table."""

    _nested: ClassVar[dict[str, type[Settings]]] = {}

    @classmethod
    def from_mapping(cls, data: Any, prefix: str = ""):
        if not isinstance(data, dict):
            raise ConfigError(prefix.rstrip(".") or cls.__name__, f"must be a table, got {data!r}")
        known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            if key not in known:
                raise ConfigError(f"{prefix}{key}", f"unknown key (known: {', '.join(sorted(known))})")
            sub = cls._nested.get(key)
            kwargs[key] = sub.from_mapping(value, f"{prefix}{key}.") if sub else value
        try:
            return cls(**kwargs)
        except ConfigError as err:
            raise ConfigError(f"{prefix}{err.key}", err.problem) from None

    def to_mapping(self) -> dict[str, Any]:
        """Back to a table (TOML has no null: unset optional values are left out)."""
        return _plain(asdict(self))  # type: ignore[call-overload]

    def replace(self, **changes):
        return replace(self, **changes)  # type: ignore[type-var]

    def _set(self, name: str, value: Any) -> None:
        """Store a normalised value on a frozen dataclass from its __post_init__."""
        object.__setattr__(self, name, value)


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items() if v is not None}
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return value
