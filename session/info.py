"""What a session file says about itself (configuration, calibration, rig, phantom, ground truth) and where
session files go."""

from __future__ import annotations

import importlib.metadata
import os
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class SessionInfo:
    """What makes a session file self-describing; everything plain data (JSON-able), SI units. The
    composition root fills it in from the configuration and the rig it built (``app.recording.session_info``)."""

    config: dict[str, Any]
    calibration: dict[str, Any]
    rig: dict[str, Any] = field(default_factory=dict)
    phantom: dict[str, Any] | None = None
    ground_truth: list[dict[str, Any]] = field(default_factory=list)
    software_version: str = ""

    @property
    def simulated(self) -> bool:
        return self.rig.get("backend") == "sim"


def calibration_of(sensor, table_height_m: float) -> dict[str, Any]:
    """The calibration block for a :class:`hardware.interfaces.TactileConstraints`."""
    return {
        "rows": sensor.rows,
        "cols": sensor.cols,
        "pitch_m": sensor.pitch_m,
        "element_area_m2": sensor.element_area_m2,
        "full_scale_pa": sensor.full_scale_pa,
        "frame_rate_hz": sensor.frame_rate_hz,
        "table_height_m": table_height_m,
        "cover_spread_m": sensor.cover_spread_m,
    }


def software_version() -> str:
    try:
        return importlib.metadata.version("palpation-console")
    except importlib.metadata.PackageNotFoundError:
        return "unknown (not installed)"


def sessions_dir() -> Path:
    """Where sessions go: ``$PALPATION_DATA_DIR/sessions``, else the platform's user data folder."""
    base = os.environ.get("PALPATION_DATA_DIR")
    if not base:
        import platformdirs

        base = platformdirs.user_data_dir("palpation-console")
    return Path(base) / "sessions"


def new_session_path(folder: Path | None = None, now: datetime | None = None) -> Path:
    """A fresh file name in ``folder`` named by the local date and time: ``session-2024-05-01_14-03-22.h5``."""
    folder = Path(folder) if folder is not None else sessions_dir()
    stamp = (now or datetime.now()).strftime("%Y-%m-%d_%H-%M-%S")
    path = folder / f"session-{stamp}.h5"
    n = 2
    while path.exists():
        path = folder / f"session-{stamp}-{n}.h5"
        n += 1
    return path


