"""The validation study: how well the console finds tumours and their depth, on phantoms nobody tuned for.

``palpation-console study`` draws phantoms from a documented, seeded distribution
(:class:`tissue.generator.StudyDistribution`), palpates each one with the simulated rig on the fast-forward driver
exactly as ``simulate`` does (the scripted operator, the default ramp, every area of the phantom), records it to a
session file, analyses that file with the same pipeline the reviewer and the ``stitch`` command use
(:class:`session.analysis.SessionAnalysis`, default parameters), and scores what was found against the
phantom's ground truth (:func:`session.scoring.score`). The paper's two phantoms can be added to the set (``--paper``).

Phantoms are independent, so they run in parallel through one executor interface (:class:`Executor`): local
worker processes by default, or a Dask distributed cluster (``--scheduler ADDRESS``; ``pip install
palpation-console[study]``) for studies of thousands of phantoms. Both run the same function,
:func:`run_case`, on the same :class:`StudyCase`; only where it runs differs.

Every case leaves its phantom file (TOML) and, with ``keep_sessions``, its session file in the output
folder, so any result can be opened in the reviewer and replayed, and the whole study analysed again with
other analysis options without palpating again (``--reanalyse FOLDER``, :func:`reanalyse_study`): every
option ``stitch`` takes applies to a study too (:func:`analysis_options`).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import tomli_w

from hardware.settings import ConfigError, read_toml
from session.scoring import case_failures, print_summary, score
from tissue.generator import RealisticConditions, StudyDistribution, draw_conditions, draw_phantom, surface_kind

# ---- one case ------------------------------------------------------------------------------------------

TRAVEL_OVER_TOP_M = 0.005  # the operator's moves between areas clear the phantom's highest point by this at least


def travel_height_m(phantom, settings: dict[str, Any]) -> float:
    """The height the scripted operator moves between areas at: the settings' (the default's), or higher
    where the phantom stands taller. The distribution draws blocks up to 32 mm thick with bumps or a slope
    on top, and the operator clears the highest, as one would over a tall phantom (seed 4949 drew one whose
    approach stood at 46 mm, over the default travel height of 45 mm, and the case was lost)."""
    from hardware.sim.settings import OperatorSimSettings

    top = phantom.highest_surface_m(phantom.length_m / 2, phantom.width_m / 2, (phantom.length_m, phantom.width_m))
    given = settings.get("sim", {}).get("operator", {}).get("travel_height_m", OperatorSimSettings.travel_height_m)
    return max(float(given), top + OperatorSimSettings.clearance_m + TRAVEL_OVER_TOP_M)

# The worlds a study palpates in, as the settings every case's rig is built with. "ideal": the analysis and the
# simulator share the mechanics, and the array's only fast error is white noise. "realistic": the array has
# the errors a real capacitive array has (hardware/sim/settings.py, SENSOR_MODELS), and each phantom is
# palpated under conditions drawn for it (tissue.generator.draw_conditions: law, sides, micro-relief, probe
# tilt, a thicker cover than the array is specified with); the analysis knows of none of it.
WORLDS: dict[str, dict[str, Any]] = {
    "ideal": {"sim": {"sensor": {"model": "ideal"}}},
    "realistic": {"sim": {"sensor": {"model": "realistic"}}},
}


@dataclass(frozen=True)
class StudyCase:
    name: str
    phantom: dict[str, Any]  # a phantom file's content
    rig_seed: int  # the run's sensor noise
    sensor_seed: int  # the array as manufactured (gains, offsets)
    force_max_N: float = 7.0  # the ramp runs from 1 N in 1 N steps to this
    paper: bool = False  # one of the paper's two phantoms
    tissue: str = "continuum"  # the simulator's tissue model (hardware.sim.settings.TISSUE_MODELS)
    world: str = "ideal"  # WORLDS
    conditions: dict[str, Any] = field(default_factory=dict)  # what the realistic world drew for this case
    calibrated: bool = False  # its array calibrated on the cushion first, as a lab does (app/calibrate.py)


def ramp_for(phantom: dict[str, Any]) -> float:
    """F_max for a phantom, as the paper's operator chose it "based on the stiffness of the tissue"
    (Section III-B): the paper's 7 N for its 20 kPa, 25 mm phantom, scaled with the tissue's modulus and
    inversely with its thickness (a layer's stiffness under a punch), in whole newtons from 4 to 8 N, so a
    soft thick block is not pressed past the default 16 mm indentation ceiling at its free ends."""
    p = phantom["phantom"]
    scaled = 7.0 * (p["youngs_modulus_pa"] / 20e3) * (0.025 / p["thickness_m"])
    return float(min(8.0, max(4.0, round(scaled))))


def study_cases(n: int, seed: int, paper: bool = False, dist: StudyDistribution = StudyDistribution(),
                **overrides) -> list[StudyCase]:
    """``n`` phantoms drawn with ``seed`` (the same seed gives the same study), then the paper's two; with
    ``world="both"``, those of the ideal world, then the same in the realistic world (named ``realistic-...``)."""
    if overrides.get("world") == "both":
        ideal = _drawn_cases(n, seed, paper, dist, {**overrides, "world": "ideal"})
        realistic = _drawn_cases(n, seed, paper, dist, {**overrides, "world": "realistic"})
        return [*ideal, *(replace(c, name=f"realistic-{c.name}") for c in realistic)]
    return _drawn_cases(n, seed, paper, dist, overrides)


def _drawn_cases(n: int, seed: int, paper: bool, dist: StudyDistribution, overrides: dict[str, Any]) -> list[StudyCase]:
    rng = np.random.default_rng(seed)
    realistic = overrides.get("world") == "realistic"
    cases = []
    for k in range(n):
        name = f"s{seed}-{k:04d}"
        phantom = draw_phantom(rng, name, dist)
        force_max = ramp_for(phantom)  # as the operator would choose it, not knowing the conditions
        case = StudyCase(name, phantom, int(rng.integers(2**31)), int(rng.integers(2**31)),
                         **{"force_max_N": force_max, **overrides})
        # their own stream: both worlds palpate the same phantoms with the same seeds
        cases.append(_under_conditions(case, np.random.default_rng([seed, k])) if realistic else case)
    if paper:
        from tissue.phantom import PHANTOM_DIR

        for i, name in enumerate(("flat", "uneven")):
            data = read_toml(PHANTOM_DIR / f"{name}.toml", "phantom file")
            case = StudyCase(f"paper-{name}", data, rig_seed=seed, sensor_seed=0, paper=True,
                             **{k: v for k, v in overrides.items() if k != "force_max_N"})
            cases.append(_under_conditions(case, np.random.default_rng([seed, n + i])) if realistic else case)
    return cases


def _under_conditions(case: StudyCase, rng: np.random.Generator) -> StudyCase:
    phantom, conditions = draw_conditions(rng, case.phantom, paper=case.paper)
    return replace(case, phantom=phantom, conditions=conditions)


def analysis_options(**given) -> dict[str, Any]:
    """The analysis options ``stitch`` and the reviewer take (``app.session_commands``), by their argument
    names, defaults unless ``given``: what every case's session is analysed with (plain values, so any
    executor can ship them)."""
    import argparse

    from app.session_commands import add_analysis_arguments

    parser = argparse.ArgumentParser(add_help=False)
    add_analysis_arguments(parser)
    options = vars(parser.parse_args([]))
    unknown = set(given) - set(options)
    if unknown:
        raise ValueError(f"unknown analysis options: {', '.join(sorted(unknown))}")
    return {**options, **given}


def run_case(case: StudyCase, out_dir: str, keep_session: bool = True,
             settings: dict[str, Any] | None = None, analysis: dict[str, Any] | None = None) -> dict[str, Any]:
    """Palpate ``case`` on the simulated rig, analyse its session and score it; a JSON-able result, with
    ``error`` (one line) instead of the figures when the case could not be run. ``settings``: a
    configuration's tables (``--config``) under the case's own phantom, seeds, tissue and top force;
    ``analysis``: :func:`analysis_options` (None: the defaults).

    A top-level function of plain arguments, so any executor can ship it to a worker."""
    from hardware.interfaces import DeviceError
    from session.reader import SessionFileError
    from tissue.phantom import PhantomError

    try:
        return _run_case(case, Path(out_dir), keep_session, settings or {}, analysis or analysis_options())
    except (ConfigError, PhantomError, DeviceError, SessionFileError, ValueError, OSError) as err:
        return {"name": case.name, "paper": case.paper, "world": case.world, "error": f"{type(err).__name__}: {err}"}


def _run_case(case: StudyCase, folder: Path, keep_session: bool, settings: dict[str, Any],
              analysis: dict[str, Any]) -> dict[str, Any]:
    from app.calibrate import calibrate_simulated
    from app.config import load_config, merge_tables
    from app.recording import record_simulation
    from hardware.array_calibration import CalibratedSensor, gain_error
    from hardware.sim.rig import build_sim_rig, build_tissue
    from tissue.phantom import load_phantom

    folder.mkdir(parents=True, exist_ok=True)
    phantom_path = folder / f"{case.name}.toml"
    phantom_path.write_text(tomli_w.dumps(case.phantom), encoding="utf-8")
    started = time.perf_counter()
    phantom = load_phantom(phantom_path)
    config = load_config(None, merge_tables(merge_tables(settings, WORLDS[case.world]), {
        "rig": {"backend": "sim", "phantom": str(phantom_path), "seed": case.rig_seed},
        "sim": {"sensor": {"seed": case.sensor_seed, **_cover(case.conditions)}, "tissue": case.tissue,
                "probe_tilt_deg": list(case.conditions.get("probe_tilt_deg", (0.0, 0.0))),
                "operator": {"travel_height_m": travel_height_m(phantom, settings)}},
        "control": {"ramp": {"force_max_N": case.force_max_N}}}))
    tissue = build_tissue(phantom, config.rig.sim, workers=1)  # the study's own processes fill the cores
    prepared = time.perf_counter()
    rig = build_sim_rig(phantom, config.rig.sim, tissue=tissue, seed=case.rig_seed)
    calibration_error = None
    if case.calibrated:
        cushion = folder / f"{case.name}-cushion.h5"
        try:
            calibration = calibrate_simulated({"sim": config.rig.sim, "control": settings.get("control", {})},
                                              cushion, seed=case.rig_seed + 1)
        finally:
            if not keep_session:
                cushion.unlink(missing_ok=True)
        calibration_error = gain_error(calibration, rig.sensor.gain_pattern)
        rig.sensor = CalibratedSensor(rig.sensor, calibration)
    session_path = folder / f"{case.name}.h5" if keep_session else Path(tempfile.mkstemp(suffix=".h5")[1])
    session_path.unlink(missing_ok=True)
    try:
        record_simulation(session_path, config, rig=rig)
        palpated = time.perf_counter()
        result = _analysed(case.name, case.paper, case.phantom, session_path, analysis)
    finally:
        if not keep_session:
            session_path.unlink(missing_ok=True)
    result.update(calibration_error_max=calibration_error, prepare_s=prepared - started,
                  palpate_s=palpated - prepared, analyse_s=time.perf_counter() - palpated,
                  session=str(session_path) if keep_session else None)
    return result


def _analysed(name: str, paper: bool, phantom: dict[str, Any], session_path: Path,
              options: dict[str, Any]) -> dict[str, Any]:
    """The case's session analysed with ``options`` and scored against its phantom's ground truth."""
    import argparse

    from app.session_commands import analyse
    from session.detect import threshold
    from session.reader import open_session

    with open_session(session_path) as session:
        analysis = analyse(session, argparse.Namespace(**options))
        detector = analysis.params.detect
        limit = threshold(detector.false_alarm_per_area, tuple(session.levels.dtype["pressure_pa"].shape),
                          session.pitch_m, detector.kernel_widths_m)
        conditions = _conditions_of(session)
        tissue_pa = float(phantom["phantom"]["youngs_modulus_pa"])
        truths = [{"x_m": t["x_m"], "y_m": t["y_m"], "depth_m": t["depth_m"], "diameter_m": t["diameter_m"],
                   "modulus_ratio": t["youngs_modulus_pa"] / tissue_pa} for t in session.ground_truth]
        regions = session.regions()
        return {
            "name": name, "paper": paper, "surface": surface_kind(phantom),
            "regions": _areas_started(session), "regions_done": sum(1 for r in regions if r.outcome == "done"),
            "regions_aborted": _abort_reasons(session),
            "truths": truths, "matches": [asdict(m) for m in analysis.matches],
            "false_positives": analysis.false_positives,
            "tumours": [t.to_json() for t in analysis.tumours], "flat_field": analysis.flat_field,
            "conditions": conditions, "world": "realistic" if conditions else "ideal",
            "calibrated": session.array_calibration is not None,
            "detection_threshold_z": limit,  # what each match's evidence_z is compared with
        }


def _cover(drawn: dict[str, Any]) -> dict[str, float]:
    """The simulated array's actual cover, from what the realistic world drew for a case or from its
    session's ``[sim.sensor]`` table (the stated cover stays the default)."""
    return {"cover_spread_m": drawn["cover_spread_m"]} if "cover_spread_m" in drawn else {}


def _conditions_of(session) -> dict[str, Any]:
    """What the realistic world drew for a case (tissue.generator.draw_conditions), as its session recorded
    it; empty for a case of the ideal world."""
    table = (session.phantom or {}).get("phantom", {})
    relief = [f for f in table.get("surface", []) if isinstance(f, dict) and f.get("kind") == "relief"]
    if not relief:
        return {}
    material = table.get("material", {})
    sim = session.config.get("sim") or {}
    return {"law": material.get("law", "neo_hookean"), "c2_over_c1": material.get("c2_over_c1", 0.0),
            "c3_over_c1": material.get("c3_over_c1", 0.0), "sides": table.get("sides", "free"),
            "face_friction": table.get("face_friction", 0.0),
            "relief_rms_m": relief[0]["rms_m"], "relief_wavelength_m": relief[0]["wavelength_m"],
            "probe_tilt_deg": list(sim.get("probe_tilt_deg", [0.0, 0.0])),
            **_cover(sim.get("sensor") or {})}


def _areas_started(session) -> int:
    """Areas the operator began: those that recorded a level and those that ended (aborted) before one,
    which a sensor whose noise passed the contact thresholds did in most areas of every phantom."""
    ended = {event["region"] for event in session.event_dicts() if event["kind"] in ("region_aborted", "region_done")}
    return len({int(region) for region in session.levels["region"]} | ended)


def _abort_reasons(session) -> dict[str, int]:
    """How many areas ended aborted, by reason (the first clause of what the controller said): an area
    that stopped after a level or two leaves the detector little to work with, over a tumour that counts
    as palpated."""
    reasons: dict[str, int] = {}
    for event in session.event_dicts():
        if event["kind"] == "region_aborted":
            reason = event["text"].split(":")[0].strip() or "no reason given"
            reasons[reason] = reasons.get(reason, 0) + 1
    return reasons


@dataclass(frozen=True)
class KeptCase:
    """A case of an earlier study whose session was kept: its phantom file and session, side by side."""

    name: str
    phantom: dict[str, Any]
    session: str
    paper: bool


def kept_cases(folder: Path) -> list[KeptCase]:
    """The cases of a study's output folder (each ``NAME.h5`` beside its ``NAME.toml``), by name; raises
    ConfigError naming what is missing or unreadable. One of the paper's phantoms is told by its content."""
    from tissue.phantom import PHANTOM_DIR

    if not folder.is_dir():
        raise ConfigError("--reanalyse", f"{folder} is not a folder")
    paper = [read_toml(PHANTOM_DIR / f"{n}.toml", "phantom file") for n in ("flat", "uneven")]
    cases = []
    for session in sorted(folder.glob("*.h5")):
        toml = session.with_suffix(".toml")
        try:
            phantom = read_toml(toml, "phantom file")
        except ConfigError as err:
            if not toml.exists():
                continue  # not a case of a study (a session put there by hand)
            raise ConfigError("--reanalyse", f"cannot read the phantom {toml}: {err.problem}") from None
        cases.append(KeptCase(session.stem, phantom, str(session), _without_conditions(phantom) in paper))
    if not cases:
        raise ConfigError("--reanalyse", f"{folder} holds no kept study case (NAME.h5 beside NAME.toml); "
                                         "a study keeps them unless run with --no-sessions")
    return cases


def _without_conditions(phantom: dict[str, Any]) -> dict[str, Any]:
    """A phantom file's content without what the realistic world adds (tissue.generator.draw_conditions)."""
    table = {k: v for k, v in phantom.get("phantom", {}).items() if k not in ("material", "sides", "face_friction")}
    if "surface" in table:
        table["surface"] = [f for f in table["surface"] if not (isinstance(f, dict) and f.get("kind") == "relief")]
        if not table["surface"]:
            del table["surface"]
    return {**phantom, "phantom": table}


def reanalyse_case(case: KeptCase, analysis: dict[str, Any]) -> dict[str, Any]:
    """A kept case analysed again with ``analysis`` (:func:`analysis_options`) and scored; as :func:`run_case`,
    with ``error`` (one line) when it cannot be."""
    from app.session_commands import AnalysisInputError
    from session.reader import SessionFileError

    started = time.perf_counter()
    try:
        result = _analysed(case.name, case.paper, case.phantom, Path(case.session), analysis)
    except (ConfigError, AnalysisInputError, SessionFileError, ValueError, OSError) as err:
        return {"name": case.name, "paper": case.paper, "world": case.world, "error": f"{type(err).__name__}: {err}"}
    result.update(analyse_s=time.perf_counter() - started, session=case.session)
    return result


# ---- where cases run -------------------------------------------------------------------------------------


class Executor(Protocol):
    """Runs ``fn(item, *args)`` for every item, wherever it runs them; yields results as they finish."""

    def run(self, fn: Callable, items: Iterable, *args) -> Iterator[Any]: ...

    def close(self) -> None: ...


def _end_with(parent_pid: int) -> None:
    """A local worker's start: it ends when the study that started it is gone. A study killed outright
    cannot close its pool, and its workers, orphaned, went on with their cases for minutes."""
    import threading

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="study-parent-watch", daemon=True).start()


class LocalExecutor:
    """Worker processes on this machine (spawned, so the simulator's native libraries start clean)."""

    def __init__(self, workers: int | None = None):
        import multiprocessing

        self.workers = workers or os.cpu_count() or 1
        self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_end_with, initargs=(os.getpid(),))

    def run(self, fn: Callable, items: Iterable, *args) -> Iterator[Any]:
        futures = [self._pool.submit(fn, item, *args) for item in items]
        for future in as_completed(futures):
            yield future.result()

    def close(self) -> None:
        self._pool.shutdown(cancel_futures=True)


class DaskExecutor:
    """A Dask distributed cluster: ``address`` of its scheduler, or a ``distributed.Client`` to use."""

    def __init__(self, address):
        try:
            from distributed import Client
            from distributed import as_completed as dask_completed
        except ImportError:
            raise ConfigError("--scheduler", "Dask distributed is not installed: pip install "
                                             "'palpation-console[study]'") from None
        self._owns = not isinstance(address, Client)
        try:
            self._client = Client(address, timeout="10s") if self._owns else address
        except (OSError, TimeoutError) as err:
            raise ConfigError("--scheduler", f"cannot reach the Dask scheduler at {address}: {err}") from None
        self._completed = dask_completed
        self.workers = max(1, sum(w.get("nthreads", 1) for w in self._client.scheduler_info()["workers"].values()))

    def run(self, fn: Callable, items: Iterable, *args) -> Iterator[Any]:
        futures = [self._client.submit(fn, item, *args, pure=False) for item in items]
        for future in self._completed(futures):
            yield future.result()

    def close(self) -> None:
        if self._owns:
            self._client.close()


def run_study(cases: list[StudyCase], executor: Executor, out_dir: Path, keep_sessions: bool = True,
              progress: Callable[[dict], None] | None = None, settings: dict[str, Any] | None = None,
              analysis: dict[str, Any] | None = None) -> tuple[list[dict], float]:
    """Every case's result (in the order of ``cases``) and the study's wall time in seconds; ``settings``
    and ``analysis`` as :func:`run_case` takes them (shipped to every worker: a Dask worker need not see
    the file). ``out_dir`` is made absolute here, on the client: a worker elsewhere (a Dask worker in its
    own folder, on its own machine) writes the cases' files where the study asked, which must then be a
    folder every worker sees; a result whose session is not found here says so (``session_here``)."""
    out = str(Path(out_dir).resolve())
    results, wall_s = _gathered(cases, executor.run(run_case, cases, out, keep_sessions, settings or {},
                                                    analysis or analysis_options()), progress)
    for result in results:
        if result.get("session"):
            result["session_here"] = Path(result["session"]).is_file()
    return results, wall_s


def reanalyse_study(cases: list[KeptCase], executor: Executor, analysis: dict[str, Any] | None = None,
                    progress: Callable[[dict], None] | None = None) -> tuple[list[dict], float]:
    """As :func:`run_study` for the kept cases of an earlier study (:func:`kept_cases`), analysed again."""
    return _gathered(cases, executor.run(reanalyse_case, cases, analysis or analysis_options()), progress)


def _gathered(cases, results: Iterator[dict], progress) -> tuple[list[dict], float]:
    started = time.perf_counter()
    by_name = {}
    for result in results:
        by_name[result["name"]] = result
        if progress is not None:
            progress(result)
    return [by_name[c.name] for c in cases], time.perf_counter() - started


# ---- the command ---------------------------------------------------------------------------------------------


# Stable names of the benchmark file (build/bench/accuracy.json): the stiffness map's figures, the paper's
# primary map, flat; the full per-map figures and every case follow under "maps" and "cases".
ACCURACY_KEYS = ("sensitivity_pct", "sensitivity_le6mm_pct", "false_positives_per_phantom", "loc_err_p90_mm",
                 "depth_err_rule_median_mm", "depth_err_model_median_mm", "depth_interval_coverage_pct",
                 "paper_flat_found", "paper_uneven_found", "paper_false_positives")


def study_document(cases: list, results: list[dict], wall_s: float, seed: int | None, workers: int,
                   executor: str, analysis: dict[str, Any] | None = None) -> dict[str, Any]:
    """The study's JSON. A study of both worlds gives the ideal world's figures under today's keys and the
    realistic world's under the same keys prefixed ``realistic_`` (its maps as ``realistic_maps``)."""
    worlds = {r.get("world", "ideal") for r in results if "error" not in r}
    both = worlds == {"ideal", "realistic"}
    first = [r for r in results if r.get("world", "ideal") == "ideal"] if both else results
    figures = _figures(first)
    doc: dict[str, Any] = {key: figures["stiffness"][key] for key in ACCURACY_KEYS}
    if both:
        other = _figures([r for r in results if r.get("world") == "realistic"])
        doc.update({f"realistic_{key}": other["stiffness"][key] for key in ACCURACY_KEYS})
        doc.update(realistic_maps=other, realistic_phantoms=other["stiffness"]["phantoms"],
                   realistic_conditions=asdict(RealisticConditions()))
    doc.update(study_wall_s=wall_s, phantoms=figures["stiffness"]["phantoms"], seed=seed, workers=workers,
               executor=executor, distribution=asdict(StudyDistribution()),
               analysis={k: str(v) if isinstance(v, Path) else v for k, v in (analysis or analysis_options()).items()},
               maps=figures, cases=results)
    return doc


def _figures(results: list[dict]) -> dict[str, dict]:
    return {source: score(results, source) for source in ("stiffness", "force")}


# what only palpating a study takes; re-analysing kept cases refuses them
_PALPATION_OPTIONS = {"phantoms": "-n/--phantoms", "seed": "--seed", "paper": "--paper", "config": "--config",
                      "no_sessions": "--no-sessions", "world": "--world", "calibrated": "--calibrated"}


def study_parser():
    import argparse

    from app.session_commands import add_analysis_arguments

    parser = argparse.ArgumentParser(
        prog="palpation-console study",
        description="Validate tumour detection and depth on simulated phantoms drawn from a documented, seeded "
                    "distribution (app/study.py): palpate, analyse, score against the ground truth. With "
                    "--reanalyse, analyse the kept sessions of an earlier study again (other analysis options) "
                    "without palpating.")
    parser.add_argument("-n", "--phantoms", type=int, help="phantoms to draw (default 12)")
    parser.add_argument("--seed", type=int, help="the draw's seed: the same seed, the same study (default 1)")
    parser.add_argument("--paper", action="store_true", help="add the paper's flat and uneven phantoms")
    parser.add_argument("--out", type=Path, default=Path("study"),
                        help="folder for every case's phantom file and session (default ./study)")
    parser.add_argument("--reanalyse", type=Path, metavar="FOLDER",
                        help="analyse and score again the cases an earlier study kept in FOLDER (its --out), "
                             "with the analysis options given here; writes FOLDER/reanalysis.json and .png "
                             "unless --json and --plot say otherwise")
    parser.add_argument("--json", type=Path, help="the figures and every case as JSON (default OUT/study.json)")
    parser.add_argument("--plot", type=Path, help="PNG of sensitivity against depth and the FROC "
                                                  "(default OUT/study.png)")
    parser.add_argument("--workers", type=int, help="local worker processes (default: one per core)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="run on this Dask distributed scheduler (e.g. tcp://10.0.0.5:8786) instead of "
                             "local processes; needs pip install 'palpation-console[study]'")
    parser.add_argument("--no-sessions", action="store_true", help="do not keep the session files")
    parser.add_argument("--world", choices=[*WORLDS, "both"],
                        help="ideal: the analysis shares the simulator's mechanics and the array's only fast "
                             "error is white noise; realistic: the errors a real capacitive array has and "
                             "conditions drawn for each phantom (law, sides, micro-relief, probe tilt, a thicker "
                             "cover), none of which the analysis knows of; both: the same phantoms in each (default "
                             "ideal)")
    parser.add_argument("--calibrated", action="store_true",
                        help="calibrate every case's array on the simulated cushion before palpating with it, as "
                             "a lab calibrates its array (palpation-console calibrate); its session is kept")
    parser.add_argument("--config", type=Path, help="a TOML configuration whose [control] and [sim] settings "
                        "(ramp steps, gains, contact, safety; sensor noise, tissue model) every phantom is "
                        "palpated with; each case keeps its own phantom, seeds and top force")
    add_analysis_arguments(parser)
    return parser


def _problem(args) -> str:
    """The first thing wrong with the command line, or ''."""
    from app.session_commands import analysis_params
    from session.detect import DetectError
    from session.stitch import StitchError

    if args.reanalyse is not None:
        given = [flag for dest, flag in _PALPATION_OPTIONS.items() if getattr(args, dest) not in (None, False)]
        if given:
            return f"--reanalyse analyses kept sessions again: {', '.join(given)} only apply to palpating a study"
    else:
        if not 0 <= args.phantoms <= 100_000:
            return f"--phantoms must be within 0..100000, got {args.phantoms}"
        if args.seed < 0:
            return f"--seed must be >= 0, got {args.seed}"
        if not args.phantoms and not args.paper:
            return "nothing to run: --phantoms 0 without --paper"
    if args.workers is not None and args.workers < 1:
        return f"--workers must be >= 1, got {args.workers}"
    try:
        analysis_params(args)
    except (StitchError, DetectError) as err:
        return str(err)
    if args.reference is not None and not args.reference.is_file():
        return f"--reference {args.reference}: no such file"
    return ""


def study_main(argv: list[str] | None = None) -> int:
    import json

    from session.export import json_ready

    parser = study_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:
        return int(stop.code or 0)
    if args.reanalyse is None:
        args.phantoms = 12 if args.phantoms is None else args.phantoms
        args.seed = 1 if args.seed is None else args.seed
    problem = _problem(args)
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    analysis = analysis_options(**{k: getattr(args, k) for k in analysis_options()})
    settings: dict[str, Any] = {}
    if args.config is not None:
        from app.config import load_config

        try:  # every mistake in the file said here, before a worker starts
            settings = {k: v for k, v in load_config(args.config).raw.items() if k in ("control", "sim")}
        except ConfigError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
    folder = args.reanalyse or args.out
    stem = "reanalysis" if args.reanalyse else "study"
    json_path = args.json or folder / f"{stem}.json"
    plot_path = args.plot or folder / f"{stem}.png"
    try:
        cases = (kept_cases(args.reanalyse) if args.reanalyse
                 else study_cases(args.phantoms, args.seed, args.paper, world=args.world or "ideal",
                                  calibrated=args.calibrated))
        if not args.reanalyse:
            args.out.mkdir(parents=True, exist_ok=True)
        executor = DaskExecutor(args.scheduler) if args.scheduler else LocalExecutor(args.workers)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"error: cannot use {args.out}: {err.strerror or err}", file=sys.stderr)
        return 2
    where = 'Dask at ' + args.scheduler if args.scheduler else 'local processes'
    if args.reanalyse:
        print(f"study: re-analysing the {len(cases)} cases kept in {args.reanalyse}, {executor.workers} workers "
              f"({where})")
    else:
        print(f"study: {len(cases)} phantoms, {executor.workers} workers ({where}); cases in {args.out}")
    done = [0]

    def progress(result: dict) -> None:
        done[0] += 1
        found = sum(1 for m in result.get("matches", ()) if m["found"] and m["source"] == "stiffness")
        what = result.get("error") or (f"{found} of {len(result['truths'])} found, false positives "
                                       f"{result['false_positives'].get('stiffness', 0)}")
        print(f"  [{done[0]}/{len(cases)}] {result['name']}: {what}", flush=True)
        for line in case_failures(result):
            print(f"        {line}", flush=True)

    try:
        if args.reanalyse:
            results, wall_s = reanalyse_study(cases, executor, analysis, progress)
        else:
            results, wall_s = run_study(cases, executor, args.out, not args.no_sessions, progress, settings, analysis)
    except KeyboardInterrupt:
        return 130
    finally:
        executor.close()
    elsewhere = sum(1 for r in results if r.get("session_here") is False)
    if elsewhere:
        print(f"warning: {elsewhere} case(s) kept their session where their worker wrote it, not in "
              f"{args.out.resolve()}: give --out a folder every Dask worker sees (a shared file system)",
              file=sys.stderr)
    doc = study_document(cases, results, wall_s, args.seed, executor.workers,
                         "dask" if args.scheduler else "local", analysis)
    doc["config"] = str(args.config) if args.config is not None else None  # what the phantoms were palpated with
    doc["world"] = None if args.reanalyse else args.world or "ideal"
    doc["calibrated"] = None if args.reanalyse else args.calibrated
    if args.reanalyse:
        doc["reanalysed"] = str(args.reanalyse)
    if "realistic_maps" in doc:
        print("\n== the ideal world ==")
        print_summary(doc["maps"], wall_s)
        print("\n== the realistic world ==")
        print_summary(doc["realistic_maps"], wall_s)
    else:
        print_summary(doc["maps"], wall_s)
    try:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(json_ready(doc), indent=1, allow_nan=False), encoding="utf-8")
        from widgets.study_plot import render_study_png

        render_study_png(plot_path, doc)
    except OSError as err:
        print(f"error: cannot write the results: {err}", file=sys.stderr)
        return 1
    print(f"results: {json_path}\nplot: {plot_path}")
    return 0
