"""``palpation-console calibrate``: measure the tactile array's element sensitivities on a uniform reference
(hardware/array_calibration.py) and save them as the calibration file the console loads.

Two ways, one fit:

* ``calibrate --session FILE``: from a recorded session of presses on the reference. On a real rig: lay the
  calibration cushion (a fluid cushion or a thin pad on a rigid plate, larger than the face) on the table,
  palpate the same spot of it six times in the console, each press a whole force ramp, and give that session.
* ``calibrate`` alone, on the simulated rig: the scripted operator presses the simulated cushion
  (``tissue/phantoms/cushion.toml``) with the configured simulated array, the session is recorded, fitted, and
  the fit is checked against the pattern the simulated array was made with.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from app.config import load_config
from app.rigs import build_rig
from app.simulate import simulate
from hardware.array_calibration import ArrayCalibration, ArrayCalibrationError, gain_error
from hardware.settings import ConfigError
from session.array_calibration import calibration_from_session
from session.info import new_session_path
from tissue.phantom import PhantomError

CUSHION = "cushion"
MAX_TIME_S = 600.0  # simulated: six presses take 80 s of simulated time


def print_calibration(cal: ArrayCalibration) -> None:
    print(f"Element sensitivities over the array's mean, in % ({cal.shape[0]} rows along x, {cal.shape[1]} columns "
          f"along y):")
    for row in cal.gain:
        print("  " + " ".join(f"{(g - 1) * 100:+5.1f}" for g in row))
    print(cal.summary())


def calibrate_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="palpation-console calibrate", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--session", type=Path, metavar="FILE",
                        help="fit a recorded session of presses on the reference (else: press the simulated "
                             "cushion with the simulated rig)")
    parser.add_argument("--out", type=Path, metavar="FILE", required=True, help="the calibration file to write")
    parser.add_argument("--config", type=Path, help="simulated: the [sim] settings of the array to calibrate")
    parser.add_argument("--seed", type=int, help="simulated: random seed of the session (not of the array)")
    args = parser.parse_args(argv)
    if args.session is not None and (args.config is not None or args.seed is not None):
        print("error: --session fits a recorded session: --config and --seed belong to the simulated presses",
              file=sys.stderr)
        return 2
    if not args.out.resolve().parent.is_dir():
        print(f"error: --out {args.out}: the folder {args.out.resolve().parent} does not exist", file=sys.stderr)
        return 2
    try:
        if args.session is not None:
            cal = calibration_from_session(args.session)
            truth = None
        else:
            cal, truth = _simulated(args)
            if cal is None:
                return 1
    except (ArrayCalibrationError, ConfigError, PhantomError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print_calibration(cal)
    if truth is not None:
        print(f"Against the pattern the simulated array was made with: {gain_error(cal, truth):.2%} at worst "
              f"(the pattern itself departs up to {np.max(np.abs(truth / truth.mean() - 1)):.1%})")
    try:
        cal.save(args.out)
    except ArrayCalibrationError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"Calibration written to {args.out}: use it with `palpation-console run --calibration {args.out}` or "
          f"[rig] calibration in the config")
    return 0


def calibrate_simulated(settings: dict, path: Path, seed: int = 0) -> ArrayCalibration:
    """The simulated procedure without a word on the terminal (the study calibrates every case's array):
    the cushion pressed with the array ``settings`` (a configuration's tables) describe, recorded to ``path``
    and fitted."""
    from app.config import merge_tables
    from app.recording import record_simulation

    config = load_config(None, merge_tables(settings, _cushion(seed)))
    record_simulation(path, config, max_time_s=MAX_TIME_S)
    return calibration_from_session(path)


def _cushion(seed: int | None) -> dict:
    """What turns a configuration into the calibration's: the cushion, as columns, with no calibration."""
    rig = {"backend": "sim", "phantom": CUSHION, "calibration": ""}
    return {"rig": rig if seed is None else {**rig, "seed": seed}, "sim": {"tissue": "winkler"}}


def _simulated(args) -> tuple[ArrayCalibration | None, np.ndarray | None]:
    config = load_config(args.config, _cushion(args.seed))
    path = new_session_path()
    print("Pressing the calibration cushion six times with the simulated rig")
    if simulate(config, max_time_s=MAX_TIME_S, path=path) != 0:
        print(f"error: the presses did not all complete: nothing was calibrated (the session is {path})",
              file=sys.stderr)
        return None, None
    truth = build_rig(config.rig).sensor.gain_pattern
    return calibration_from_session(path), truth
