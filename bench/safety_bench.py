"""The fault campaign at scale (bench/safety_campaign.py): ``safety.json``.

``PALPATION_SAFETY_RUNS`` plant runs (default 10,000, two in three with the second-order robot) in as many
processes as there are CPUs, 100 runs of the fast-forward simulated rig on the flat phantom's finite-element
tissue, and a fuzz of every reader of outside input, a recorded session included. Keys: ``runs``,
``dynamic_runs``, ``ticks``, ``violations``, ``max_force_over_ceiling_N`` and
``max_indentation_over_ceiling_mm`` (the true excesses, NaN if any was unknown), ``estop_overshoot_max_mm``,
``fuzz_inputs``, ``fuzz_crashes``, and the detail beside them: ``by_scenario`` (runs, the trouble come to
pass, violations) and ``by_stiffness``, the runs the two maxima come from (``max_force_run``,
``max_indentation_run``), and ``worst_runs`` and ``worst_by_scenario`` (seed, kind, what it drew and its first
violation, to replay with ``python -m bench.safety_campaign --replay SEED --kind KIND``). ``plant_seconds`` is the
plant runs' time on the clock, ``cpu_seconds`` what all the runs cost (on a machine shared with other work the two
differ).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import tomli_w

from bench import safety_campaign as campaign

RIG_RUNS = 100
FUZZ_PER_READER = 2000


def _plant_chunk(seeds: range) -> dict:
    return campaign.campaign(len(seeds), 0, seed=0, first=seeds.start)


def _record_session(folder: Path) -> Path:
    from app.config import load_config
    from app.recording import record_simulation
    from hardware.interfaces import TactileConstraints
    from hardware.settings import read_toml
    from hardware.sim.rig import build_sim_rig
    from tissue.phantom import PHANTOM_DIR, load_phantom
    from tissue.winkler import WinklerTissue

    data = read_toml(PHANTOM_DIR / "flat.toml", "phantom file")
    data["phantom"]["regions"] = [{"centre_xy_m": [0.012, 0.015]}, {"centre_xy_m": [0.036, 0.015]}]
    source = folder / "two-areas.toml"
    source.write_text(tomli_w.dumps(data), encoding="utf-8")
    config = load_config(None, {"control": {"ramp": {"force_min_N": 0.5, "force_max_N": 1.5, "force_step_N": 0.5}},
                                "rig": {"phantom": str(source)}})
    phantom = load_phantom(source)
    rig = build_sim_rig(phantom, tissue=WinklerTissue(phantom, TactileConstraints()))
    path = folder / "fuzz-source.h5"
    record_simulation(path, config, rig=rig, max_time_s=60.0)
    return path


def run(out_dir: Path) -> dict:
    started = time.monotonic()
    runs = int(os.environ.get("PALPATION_SAFETY_RUNS", "10000"))
    workers = max(1, os.cpu_count() or 1)
    step = -(-runs // workers)
    chunks = [range(i, min(i + step, runs)) for i in range(0, runs, step)]
    with ProcessPoolExecutor(workers) as pool:
        parts = list(pool.map(_plant_chunk, chunks))
    plant_seconds = time.monotonic() - started
    rig = campaign.campaign(0, RIG_RUNS, seed=1)
    parts.append(rig)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        try:
            session = _record_session(folder)
        except Exception as err:  # noqa: BLE001 - the fuzz still runs on every other reader
            print(f"safety bench: no session to fuzz ({err})")
            session = None
        fuzzed = campaign.fuzz(FUZZ_PER_READER, seed=7, folder=folder / "fuzz", session=session)
    result = campaign.merge(parts)
    result.update(fuzzed)
    result["fuzzed_session"] = session is not None
    result["plant_seconds"] = plant_seconds
    result["seconds"] = time.monotonic() - started
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "safety.json").write_text(json.dumps(result, indent=2) + "\n")
    return result
