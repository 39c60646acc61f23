"""The array's calibration from a recorded session of presses on a uniform reference (the fit itself is
:func:`hardware.array_calibration.fit_gains`): what ``palpation-console calibrate --session`` and the console's
File menu both do."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hardware.array_calibration import ArrayCalibration, ArrayCalibrationError, fit_gains
from session.reader import SessionFileError, open_session

# The simulator's columns press every element alike; its continuum tissue reads high at the face's edges.
UNIFORM_TISSUE = "WinklerTissue"


def calibration_from_session(path: str | Path) -> ArrayCalibration:
    """The fit of a recorded session of presses on a uniform reference; ArrayCalibrationError says why not."""
    path = Path(path)
    try:
        session = open_session(path)
    except SessionFileError as err:
        raise ArrayCalibrationError(str(err)) from None
    try:
        tissue = session.rig.get("tissue_model")
        if session.simulated and tissue != UNIFORM_TISSUE:
            raise ArrayCalibrationError(f"{path}: simulated on {session.phantom_name or 'a phantom'} modelled as "
                                        f"{tissue}, which does not press every element alike: calibrate on the "
                                        f"simulated cushion (palpation-console calibrate, without --session)")
        levels = session.levels
        readings = np.asarray(levels["pressure_pa"], dtype=float)
        applied = session.array_calibration
        if applied is not None:
            # the frames were divided by the calibration the console then had: fit what the array itself read
            readings = readings * applied.gain
        return fit_gains(readings, levels["region"], array=describe_array(session.rig), source=path.name)
    finally:
        session.close()


def describe_array(rig: dict) -> str:
    """Which array a session's rig description names, in a few words."""
    settings = rig.get("settings")
    sensor = settings.get("sensor") if isinstance(settings, dict) else rig.get("sensor")
    if not isinstance(sensor, dict):
        return str(rig.get("backend", ""))
    if rig.get("backend") == "sim":
        return f"simulated array (seed {sensor.get('seed')}, {sensor.get('model')} model)"
    return " ".join(str(sensor[k]) for k in ("kind", "port", "vid_pid") if sensor.get(k))
