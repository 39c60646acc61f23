"""The application's configuration: the shipped defaults, overridden key by key by a user's TOML file."""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from app.rigs import BACKENDS, RigSpec, check_hardware, load_calibration
from control.config import ControlConfig
from control.safety import FORCE_RESERVE_N, blind_seek_depth_m
from hardware.settings import ConfigError, read_toml

# shipped as package data beside this module, in a checkout and in an installed wheel alike
DEFAULT_CONFIG = Path(str(resources.files(__package__).joinpath("default.toml")))
COMMAND_LINE = "command line"  # the source of load_config's overrides, as errors and session files name it


@dataclass(frozen=True)
class AppConfig:
    control: ControlConfig
    rig: RigSpec
    sources: tuple[str, ...] = ()
    raw: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)


def merge_tables(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``override`` laid over it, table by table (neither is changed)."""
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_tables(out[key], value)
        else:
            out[key] = value
    return out




SECTIONS = ("control", "rig", "sim", "hardware")
# The share of the blind seek's depth (control.safety.blind_seek_depth_m) the scripted operator's clearance may
# take: the rest is for the surface under the face being higher than the phantom's nominal one (micro-relief of
# 0.1-0.3 mm, a probe tilted 1.5 degrees lifts one end of the 30 mm face 0.4 mm)
SEEK_SHARE = 0.7


def parse_config(data: dict[str, Any], sources: tuple[str, ...] = ()) -> AppConfig:
    """Validate every section, whichever backend is chosen, so a typo is reported before anything starts."""
    # Imported here: the hardware settings pull in the device drivers, which nothing needs before a config is read.
    from hardware.sim.settings import SimSettings

    where = sources[-1] if sources else "<config>"
    unknown = set(data) - set(SECTIONS)
    if unknown:
        raise ConfigError(f"{where}: {sorted(unknown)[0]}", f"unknown section (known: {', '.join(SECTIONS)})")
    try:
        control = ControlConfig.from_mapping(data.get("control", {}), "control.")
        rig = data.get("rig", {})
        if not isinstance(rig, dict):
            raise ConfigError("rig", "must be a table")
        extra = set(rig) - {"backend", "phantom", "seed", "calibration"}
        if extra:
            raise ConfigError(f"rig.{sorted(extra)[0]}", "unknown key (known: backend, phantom, seed, calibration)")
        backend = rig.get("backend", "sim")
        if backend not in BACKENDS:
            raise ConfigError("rig.backend", f"unknown backend {backend!r} (known: {', '.join(sorted(BACKENDS))})")
        seed = rig.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ConfigError("rig.seed", f"must be an integer, got {seed!r}")
        sim = data.get("sim", {})
        clearance_m = SimSettings.from_mapping(sim, "sim.").operator.clearance_m
        seek_m = blind_seek_depth_m(control.safety)
        if clearance_m > SEEK_SHARE * seek_m:
            raise ConfigError("sim.operator.clearance_m", (
                f"{clearance_m * 1e3:g} mm: the seek goes no deeper than {seek_m * 1e3:.2f} mm (the force ceiling less "
                f"{FORCE_RESERVE_N:g} N over control.safety.tissue_stiffness_max_N_m), so at most "
                f"{SEEK_SHARE * seek_m * 1e3:.2f} mm leaves it room to find the tissue"))
        hardware = data.get("hardware", {})
        check_hardware(backend, hardware)
        calibration = rig.get("calibration", "")
        if not isinstance(calibration, str):
            raise ConfigError("rig.calibration", f"must be the path of a calibration file, got {calibration!r}")
        if calibration:
            # a relative path is the config file's neighbour, wherever the console is started from (the
            # command line's is made absolute where it is read)
            files = [source for source in sources if source != COMMAND_LINE]
            calibration = str(Path(files[-1]).parent / calibration) if files else calibration
            load_calibration(calibration)  # a bad file is told now, not when the controller starts
        spec = RigSpec(backend=backend, phantom=str(rig.get("phantom", "flat")), sim=dict(sim), seed=seed,
                       hardware=dict(hardware), calibration=calibration)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err.key}", err.problem) from None
    return AppConfig(control=control, rig=spec, sources=sources, raw=data)


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> AppConfig:
    """The defaults, then the user's file (if any), then command-line overrides."""
    data = read_toml(DEFAULT_CONFIG)
    sources = [str(DEFAULT_CONFIG)]
    if path is not None:
        data = merge_tables(data, read_toml(Path(path)))
        sources.append(str(path))
    if not overrides:
        return parse_config(data, tuple(sources))
    # The files alone first: a mistake in them is reported against the file, so any mistake left after
    # merging came from the command line and is reported against it.
    parse_config(data, tuple(sources))
    return parse_config(merge_tables(data, overrides), (*sources, COMMAND_LINE))
