"""The validation study: how well the console finds tumours and their depth, on phantoms nobody tuned for.

``palpation-console study`` draws phantoms from a documented, seeded distribution
(:class:`StudyDistribution`), palpates each one with the simulated rig on the fast-forward driver exactly as
``simulate`` does (the scripted operator, the default ramp, every area of the phantom), records it to a
session file, analyses that file with the same pipeline the reviewer and the ``stitch`` command use
(:class:`session.analysis.SessionAnalysis`, default parameters), and scores what was found against the
phantom's ground truth (:func:`score`). The paper's two phantoms can be added to the set (``--paper``).

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

import math
import os
import statistics
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import tomli_w

from hardware.settings import ConfigError

DEPTH_BANDS_M = ((0.0, 3e-3), (3e-3, 6e-3), (6e-3, 9e-3), (9e-3, 12.5e-3))
# the paper's comparison of the two maps turns on the surface: on even thickness they see the same
# within-face pattern, where the thickness varies only Eq. 1 tells a tumour from thicker tissue
SURFACES = ("flat", "sloped", "bumpy")
SHALLOW_M = 6e-3  # the goal's "tumours whose top is at most 6 mm deep"


# ---- the distribution ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StudyDistribution:
    """Where the study's phantoms come from (all ranges uniform unless said otherwise; lengths in m).

    The phantom is a silicone block on the table like the paper's, as wide as the TSI is long (the TSI
    spans it, as in Section IV-A), palpated in 8 mm strips along its length. Its surface is flat, sloped
    (a plane tilted along x and y) or bumpy (one or two half-cylinders along x over part of the length,
    like the paper's uneven phantom), each with the probability given. It holds 0 to 3 spherical tumours
    (each count equally likely) at a depth (surface to the sphere's top) of 1-12 mm, 5-12 mm across and
    3-12 times stiffer than the tissue (log-uniform), anywhere inside the block that keeps 1 mm of tissue
    between tumours and 2 mm above the table. The tissue's modulus is log-uniform around the paper's
    20 kPa. A draw that the phantom schema refuses is drawn again.
    """

    length_m: tuple[float, float] = (0.056, 0.088)
    width_m: float = 0.030
    thickness_m: tuple[float, float] = (0.020, 0.032)
    youngs_modulus_pa: tuple[float, float] = (15e3, 30e3)  # log-uniform
    poisson_ratio: float = 0.49
    surface_odds: tuple[float, float, float] = (0.4, 0.3, 0.3)  # flat, sloped, bumpy
    slope_x: tuple[float, float] = (-0.10, 0.10)  # rise per unit length along x
    slope_y: tuple[float, float] = (-0.05, 0.05)
    bump_radius_m: tuple[float, float] = (0.003, 0.006)
    tumours: tuple[int, int] = (0, 3)
    depth_m: tuple[float, float] = (1e-3, 12e-3)
    diameter_m: tuple[float, float] = (5e-3, 12e-3)
    modulus_ratio: tuple[float, float] = (3.0, 12.0)  # log-uniform
    min_gap_m: float = 1e-3  # tissue between two tumours
    table_clearance_m: float = 2e-3  # tissue under a tumour


def _uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(bounds[0], bounds[1]))


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(math.exp(rng.uniform(math.log(bounds[0]), math.log(bounds[1]))))


def draw_phantom(rng: np.random.Generator, name: str, dist: StudyDistribution = StudyDistribution(),
                 attempts: int = 200) -> dict[str, Any]:
    """One phantom from ``dist`` as a phantom file's table (see docs/phantoms.md), valid by construction."""
    from hardware.sim.phantom import PhantomError, parse_phantom

    for _ in range(attempts):
        length = round(_uniform(rng, dist.length_m), 4)
        thickness = round(_uniform(rng, dist.thickness_m), 4)
        tissue_pa = round(_log_uniform(rng, dist.youngs_modulus_pa), -2)
        table: dict[str, Any] = {
            "name": name, "length_m": length, "width_m": dist.width_m, "thickness_m": thickness,
            "youngs_modulus_pa": tissue_pa, "poisson_ratio": dist.poisson_ratio,
        }
        kind = SURFACES[int(rng.choice(len(SURFACES), p=np.asarray(dist.surface_odds)))]
        if kind == "sloped":
            gx, gy = round(_uniform(rng, dist.slope_x), 3), round(_uniform(rng, dist.slope_y), 3)
            # tilted about the phantom's centre, so the base thickness is its mean height
            table["surface"] = [{"kind": "slope", "gradient": [gx, gy], "origin_m": [length / 2, dist.width_m / 2],
                                 "x_range_m": [0.0, length]}]
        elif kind == "bumpy":
            table["surface"] = []
            for _ in range(int(rng.integers(1, 3))):
                radius = round(_uniform(rng, dist.bump_radius_m), 4)
                start = round(float(rng.uniform(0.0, 0.5)) * length, 4)
                end = round(min(length, start + float(rng.uniform(0.3, 0.7)) * length), 4)
                centre = round(float(rng.choice([radius, dist.width_m - radius])), 4)
                table["surface"].append({"kind": "half_cylinder", "centre_y_m": centre, "radius_m": radius,
                                         "x_range_m": [start, end]})
        table["inclusions"] = []
        for _ in range(int(rng.integers(dist.tumours[0], dist.tumours[1] + 1))):
            diameter = round(_uniform(rng, dist.diameter_m), 4)
            radius = diameter / 2
            table["inclusions"].append({
                "centre_xy_m": [round(_uniform(rng, (radius, length - radius)), 4),
                                round(_uniform(rng, (radius, dist.width_m - radius)), 4)],
                "diameter_m": diameter,
                "youngs_modulus_pa": round(tissue_pa * _log_uniform(rng, dist.modulus_ratio), -2),
                "depth_m": round(_uniform(rng, dist.depth_m), 4),
            })
        data = {"phantom": table}
        try:
            phantom = parse_phantom(data, name)
        except PhantomError:
            continue
        if _room_around_tumours(phantom, dist):
            table["description"] = (f"study phantom, {kind} surface, {len(table['inclusions'])} tumour(s), "
                                    f"E = {tissue_pa / 1e3:.1f} kPa")
            return data
    raise RuntimeError(f"no valid phantom after {attempts} draws: the distribution leaves no room")


def _room_around_tumours(phantom, dist: StudyDistribution) -> bool:
    for i, a in enumerate(phantom.inclusions):
        if a.z_m - a.radius_m < dist.table_clearance_m:
            return False
        for b in phantom.inclusions[:i]:
            if math.dist((a.x_m, a.y_m, a.z_m), (b.x_m, b.y_m, b.z_m)) < a.radius_m + b.radius_m + dist.min_gap_m:
                return False
    return True


# ---- one case ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StudyCase:
    name: str
    phantom: dict[str, Any]  # a phantom file's content
    rig_seed: int  # the run's sensor noise
    sensor_seed: int  # the array as manufactured (gains, offsets)
    force_max_N: float = 7.0  # the ramp runs from 1 N in 1 N steps to this
    paper: bool = False  # one of the paper's two phantoms
    tissue: str = "continuum"  # the simulator's tissue model (hardware.sim.settings.TISSUE_MODELS)


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
    """``n`` phantoms drawn with ``seed`` (the same seed gives the same study), then the paper's two."""
    rng = np.random.default_rng(seed)
    cases = []
    for k in range(n):
        name = f"s{seed}-{k:04d}"
        phantom = draw_phantom(rng, name, dist)
        cases.append(StudyCase(name, phantom, int(rng.integers(2**31)), int(rng.integers(2**31)),
                               **{"force_max_N": ramp_for(phantom), **overrides}))
    if paper:
        from hardware.sim.phantom import PHANTOM_DIR

        for name in ("flat", "uneven"):
            data = tomllib.loads((PHANTOM_DIR / f"{name}.toml").read_text(encoding="utf-8"))
            cases.append(StudyCase(f"paper-{name}", data, rig_seed=seed, sensor_seed=0, paper=True,
                                   **{k: v for k, v in overrides.items() if k != "force_max_N"}))
    return cases


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
    from hardware.sim.phantom import PhantomError
    from session.reader import SessionFileError

    try:
        return _run_case(case, Path(out_dir), keep_session, settings or {}, analysis or analysis_options())
    except (ConfigError, PhantomError, DeviceError, SessionFileError, ValueError, OSError) as err:
        return {"name": case.name, "paper": case.paper, "error": f"{type(err).__name__}: {err}"}


def _run_case(case: StudyCase, folder: Path, keep_session: bool, settings: dict[str, Any],
              analysis: dict[str, Any]) -> dict[str, Any]:
    from app.config import load_config, merge_tables
    from app.recording import record_simulation
    from hardware.sim.phantom import load_phantom
    from hardware.sim.rig import build_sim_rig, build_tissue

    folder.mkdir(parents=True, exist_ok=True)
    phantom_path = folder / f"{case.name}.toml"
    phantom_path.write_text(tomli_w.dumps(case.phantom), encoding="utf-8")
    config = load_config(None, merge_tables(settings, {
        "rig": {"backend": "sim", "phantom": str(phantom_path), "seed": case.rig_seed},
        "sim": {"sensor": {"seed": case.sensor_seed}, "tissue": case.tissue},
        "control": {"ramp": {"force_max_N": case.force_max_N}}}))
    started = time.perf_counter()
    phantom = load_phantom(phantom_path)
    tissue = build_tissue(phantom, config.rig.sim, workers=1)  # the study's own processes fill the cores
    prepared = time.perf_counter()
    rig = build_sim_rig(phantom, config.rig.sim, tissue=tissue, seed=case.rig_seed)
    session_path = folder / f"{case.name}.h5" if keep_session else Path(tempfile.mkstemp(suffix=".h5")[1])
    session_path.unlink(missing_ok=True)
    try:
        record_simulation(session_path, config, rig=rig)
        palpated = time.perf_counter()
        result = _analysed(case.name, case.paper, case.phantom, session_path, analysis)
    finally:
        if not keep_session:
            session_path.unlink(missing_ok=True)
    result.update(prepare_s=prepared - started, palpate_s=palpated - prepared,
                  analyse_s=time.perf_counter() - palpated,
                  session=str(session_path) if keep_session else None)
    return result


def _analysed(name: str, paper: bool, phantom: dict[str, Any], session_path: Path,
              options: dict[str, Any]) -> dict[str, Any]:
    """The case's session analysed with ``options`` and scored against its phantom's ground truth."""
    import argparse

    from app.session_commands import analyse
    from session.reader import open_session

    with open_session(session_path) as session:
        analysis = analyse(session, argparse.Namespace(**options))
        tissue_pa = float(phantom["phantom"]["youngs_modulus_pa"])
        truths = [{"x_m": t["x_m"], "y_m": t["y_m"], "depth_m": t["depth_m"], "diameter_m": t["diameter_m"],
                   "modulus_ratio": t["youngs_modulus_pa"] / tissue_pa} for t in session.ground_truth]
        regions = session.regions()
        return {
            "name": name, "paper": paper, "surface": _surface_kind(phantom),
            "regions": _areas_started(session), "regions_done": sum(1 for r in regions if r.outcome == "done"),
            "regions_aborted": _abort_reasons(session),
            "truths": truths, "matches": [asdict(m) for m in analysis.matches],
            "false_positives": analysis.false_positives,
            "tumours": [t.to_json() for t in analysis.tumours], "flat_field": analysis.flat_field,
        }


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
    from hardware.sim.phantom import PHANTOM_DIR

    if not folder.is_dir():
        raise ConfigError("--reanalyse", f"{folder} is not a folder")
    paper = [tomllib.loads((PHANTOM_DIR / f"{n}.toml").read_text(encoding="utf-8")) for n in ("flat", "uneven")]
    cases = []
    for session in sorted(folder.glob("*.h5")):
        toml = session.with_suffix(".toml")
        try:
            phantom = tomllib.loads(toml.read_text(encoding="utf-8"))
        except FileNotFoundError:
            continue  # not a case of a study (a session put there by hand)
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
            raise ConfigError("--reanalyse", f"cannot read the phantom {toml}: {err}") from None
        cases.append(KeptCase(session.stem, phantom, str(session), phantom in paper))
    if not cases:
        raise ConfigError("--reanalyse", f"{folder} holds no kept study case (NAME.h5 beside NAME.toml); "
                                         "a study keeps them unless run with --no-sessions")
    return cases


def reanalyse_case(case: KeptCase, analysis: dict[str, Any]) -> dict[str, Any]:
    """A kept case analysed again with ``analysis`` (:func:`analysis_options`) and scored; as :func:`run_case`,
    with ``error`` (one line) when it cannot be."""
    from app.session_commands import AnalysisInputError
    from session.reader import SessionFileError

    started = time.perf_counter()
    try:
        result = _analysed(case.name, case.paper, case.phantom, Path(case.session), analysis)
    except (ConfigError, AnalysisInputError, SessionFileError, ValueError, OSError) as err:
        return {"name": case.name, "paper": case.paper, "error": f"{type(err).__name__}: {err}"}
    result.update(analyse_s=time.perf_counter() - started, session=case.session)
    return result


def _surface_kind(phantom: dict[str, Any]) -> str:
    features = phantom["phantom"].get("surface", [])
    if not features:
        return "flat"
    return "sloped" if features[0]["kind"] == "slope" else "bumpy"


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
            from distributed import Client, as_completed as dask_completed
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
    the file)."""
    return _gathered(cases, executor.run(run_case, cases, str(out_dir), keep_sessions, settings or {},
                                         analysis or analysis_options()), progress)


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


# ---- scoring -----------------------------------------------------------------------------------------------


def _pct(numerator: float, denominator: float) -> float | None:
    return 100.0 * numerator / denominator if denominator else None


def _quantile(values: list[float], q: float) -> float | None:
    return float(np.quantile(values, q)) if values else None


def _finite(value) -> bool:
    return value is not None and math.isfinite(value)


def _median(values: list[float]) -> float | None:
    return float(statistics.median(values)) if values else None


def _depth_figures(found: list[dict]) -> dict[str, float | None]:
    """Both depth estimates of the ``found`` matches against the truth: median error, median signed error
    (estimate minus truth: negative reads shallow), and how often the model's 90 % interval covers it."""
    rule = [(m["depth_estimate_m"] - m["depth_m"]) * 1e3 for m in found if _finite(m["depth_estimate_m"])]
    model = [(m["depth_model_m"] - m["depth_m"]) * 1e3 for m in found if _finite(m.get("depth_model_m"))]
    covered = [m["depth_low_m"] <= m["depth_m"] <= m["depth_high_m"] for m in found
               if _finite(m.get("depth_low_m")) and _finite(m.get("depth_high_m"))]
    return {"depth_err_rule_median_mm": _median([abs(e) for e in rule]),
            "depth_err_model_median_mm": _median([abs(e) for e in model]),
            "depth_bias_rule_median_mm": _median(rule),
            "depth_bias_model_median_mm": _median(model),
            "depth_interval_coverage_pct": _pct(sum(covered), len(covered))}


def _false_positives_per_phantom(results: list[dict], source: str) -> float | None:
    return sum(r["false_positives"].get(source, 0) for r in results) / len(results) if results else None


def score(results: list[dict], source: str = "stiffness") -> dict[str, Any]:
    """The study's figures for one map (``source``), over the drawn phantoms; the paper's phantoms apart."""
    failed = [r for r in results if "error" in r]
    results = [r for r in results if "error" not in r]
    drawn = [r for r in results if not r["paper"]]
    truths = [(r, m, r["truths"][m["truth_index"]]) for r in drawn for m in r["matches"]
              if m["source"] == source and m["palpated"]]
    found = [(r, m, t) for r, m, t in truths if m["found"]]
    bands = {}
    for lo, hi in DEPTH_BANDS_M:
        inside = [m for _, m, t in truths if lo <= t["depth_m"] < hi]
        bands[f"{lo * 1e3:.0f}-{hi * 1e3:.0f}mm"] = {
            "tumours": len(inside), "found": sum(1 for m in inside if m["found"]),
            "sensitivity_pct": _pct(sum(1 for m in inside if m["found"]), len(inside)),
            **_depth_figures([m for m in inside if m["found"]])}
    surfaces = {}
    for kind in SURFACES:
        phantoms = [r for r in drawn if r["surface"] == kind]
        inside = [m for r, m, _ in truths if r["surface"] == kind]
        surfaces[kind] = {
            "phantoms": len(phantoms), "tumours": len(inside), "found": sum(1 for m in inside if m["found"]),
            "sensitivity_pct": _pct(sum(1 for m in inside if m["found"]), len(inside)),
            "false_positives_per_phantom": _false_positives_per_phantom(phantoms, source)}
    shallow = [m for _, m, t in truths if t["depth_m"] <= SHALLOW_M]
    paper = {r["name"]: r for r in results if r["paper"]}
    return {
        "phantoms": len(drawn),
        "tumours": len(truths),
        "sensitivity_pct": _pct(len(found), len(truths)),
        "sensitivity_le6mm_pct": _pct(sum(1 for m in shallow if m["found"]), len(shallow)),
        "by_depth": bands,
        "by_surface": surfaces,
        "false_positives_per_phantom": _false_positives_per_phantom(drawn, source),
        "false_positives_tumour_free_phantoms": sum(r["false_positives"].get(source, 0) for r in drawn
                                                    if not r["truths"]),
        "loc_err_p90_mm": _quantile([m["error_xy_m"] * 1e3 for _, m, _ in found], 0.9),
        "loc_err_median_mm": _median([m["error_xy_m"] * 1e3 for _, m, _ in found]),
        **_depth_figures([m for _, m, _ in found]),
        "paper_flat_found": _found_count(paper.get("paper-flat"), source),
        "paper_uneven_found": _found_count(paper.get("paper-uneven"), source),
        "paper_false_positives": (sum(r["false_positives"].get(source, 0) for r in paper.values())
                                  if paper else None),
        "regions_not_done": sum(r["regions"] - r["regions_done"] for r in results),
        "failed_cases": len(failed),
        "froc": froc(drawn, source),
    }


def froc(results: list[dict], source: str, scores: Iterable[float] = (3.0, 3.5, 4.0, 5.0, 6.0, 8.0, 10.0, 15.0)
         ) -> list[dict[str, float | None]]:
    """Sensitivity against false positives per phantom as the least score a detection needs rises from the
    analysis' own threshold (points stricter than it: the study analyses at one false-alarm rate)."""
    from session.detect import Tumour, match_ground_truth

    points = []
    for least in scores:
        found = truths = false = 0
        for r in results:
            kept = [Tumour(**{**t, "levels_N": tuple(t["levels_N"])})
                    for t in r["tumours"] if t["source"] == source and t["score"] >= least]
            matches, fp = match_ground_truth(kept, r["truths"])
            palpated = {m["truth_index"] for m in r["matches"] if m["source"] == source and m["palpated"]}
            truths += len(palpated)
            found += sum(1 for m in matches if m.source == source and m.found and m.truth_index in palpated)
            false += fp.get(source, 0)
        points.append({"least_score": least, "sensitivity_pct": _pct(found, truths),
                       "false_positives_per_phantom": false / len(results) if results else None})
    return points


def _found_count(result: dict | None, source: str) -> int | None:
    if result is None:
        return None
    return sum(1 for m in result["matches"] if m["source"] == source and m["found"])


def case_failures(result: dict, source: str = "stiffness") -> list[str]:
    """What one case got wrong in one map, a line each: every palpated tumour it missed and every false
    positive, where they are (a study's figures say how often, these say where to look), after how many
    of its areas ended aborted, and why."""
    lines = []
    aborted = result.get("regions_aborted") or {}
    if aborted:
        why = ", ".join(f"{reason.lower()} {count}" for reason, count in sorted(aborted.items(), key=lambda i: -i[1]))
        lines.append(f"{sum(aborted.values())} of {result['regions']} areas aborted ({why})")
    for m in result.get("matches", ()):
        if m["source"] == source and not m["found"] and m["palpated"]:
            t = result["truths"][m["truth_index"]]
            lines.append(f"missed ({t['x_m'] * 1e3:.1f}, {t['y_m'] * 1e3:.1f}) mm: {t['depth_m'] * 1e3:.1f} mm deep, "
                         f"{t['diameter_m'] * 1e3:.1f} mm across, {t['modulus_ratio']:.1f}x stiffer")
    matched = {m["detection"] for m in result.get("matches", ()) if m["source"] == source and m["found"]}
    for k, t in enumerate(result.get("tumours", ())):
        if t["source"] == source and k not in matched:
            lines.append(f"false positive ({t['x_m'] * 1e3:.1f}, {t['y_m'] * 1e3:.1f}) mm: z {t['score']:.1f}, "
                         f"contrast {t['contrast'] * 100:+.0f} %, first at {t['first_level_N']:g} N")
    return lines


# ---- the command ---------------------------------------------------------------------------------------------


def _fmt(value, unit: str = "", decimals: int = 1) -> str:
    return "—" if value is None else f"{value:.{decimals}f}{unit}"


def _depth_cell(figures: dict, estimate: str) -> str:
    error, bias = figures[f"depth_err_{estimate}_median_mm"], figures[f"depth_bias_{estimate}_median_mm"]
    return "—" if error is None else f"{error:.2f} ({bias:+.2f}) mm"


def print_summary(figures: dict[str, dict], wall_s: float, out=None) -> None:
    out = out or sys.stdout
    for source, f in figures.items():
        print(f"\n{source} map: {f['tumours']} tumours in {f['phantoms']} phantoms", file=out)
        print("  depth band   tumours  found  sensitivity   depth error (bias), rule / model   covered", file=out)
        for band, b in f["by_depth"].items():
            print(f"  {band:>10} {b['tumours']:>9} {b['found']:>6}  {_fmt(b['sensitivity_pct'], ' %'):>10}   "
                  f"{_depth_cell(b, 'rule'):>15} / {_depth_cell(b, 'model'):<15} "
                  f"{_fmt(b['depth_interval_coverage_pct'], ' %'):>7}", file=out)
        print("  surface     phantoms tumours  found  sensitivity   false positives per phantom", file=out)
        for kind, s in f["by_surface"].items():
            print(f"  {kind:>10} {s['phantoms']:>9} {s['tumours']:>7} {s['found']:>6}  "
                  f"{_fmt(s['sensitivity_pct'], ' %'):>10}   {_fmt(s['false_positives_per_phantom'], '', 2):>10}",
                  file=out)
        print(f"  sensitivity {_fmt(f['sensitivity_pct'], ' %')} (<= 6 mm: {_fmt(f['sensitivity_le6mm_pct'], ' %')}), "
              f"false positives {_fmt(f['false_positives_per_phantom'], ' per phantom', 2)}", file=out)
        print(f"  localisation p90 {_fmt(f['loc_err_p90_mm'], ' mm', 2)}, depth error median: paper's rule "
              f"{_fmt(f['depth_err_rule_median_mm'], ' mm', 2)}, model {_fmt(f['depth_err_model_median_mm'], ' mm', 2)}"
              f"; 90 % intervals cover {_fmt(f['depth_interval_coverage_pct'], ' %')}", file=out)
        if f["paper_flat_found"] is not None:
            print(f"  paper phantoms: flat {f['paper_flat_found']} of 3, uneven {f['paper_uneven_found']} of 3, "
                  f"false positives {f['paper_false_positives']}", file=out)
    print(f"\nstudy wall time {wall_s:.0f} s", file=out)
    failed = max((f.get("failed_cases", 0) for f in figures.values()), default=0)
    if failed:
        print(f"{failed} case(s) could not be run: see 'cases' in the JSON", file=out)


# Stable names of the benchmark file (build/bench/accuracy.json): the stiffness map's figures, the paper's
# primary map, flat; the full per-map figures and every case follow under "maps" and "cases".
ACCURACY_KEYS = ("sensitivity_pct", "sensitivity_le6mm_pct", "false_positives_per_phantom", "loc_err_p90_mm",
                 "depth_err_rule_median_mm", "depth_err_model_median_mm", "depth_interval_coverage_pct",
                 "paper_flat_found", "paper_uneven_found", "paper_false_positives")


def study_document(cases: list, results: list[dict], wall_s: float, seed: int | None, workers: int,
                   executor: str, analysis: dict[str, Any] | None = None) -> dict[str, Any]:
    figures = {source: score(results, source) for source in ("stiffness", "force")}
    doc: dict[str, Any] = {key: figures["stiffness"][key] for key in ACCURACY_KEYS}
    doc.update(study_wall_s=wall_s, phantoms=figures["stiffness"]["phantoms"], seed=seed, workers=workers,
               executor=executor, distribution=asdict(StudyDistribution()),
               analysis={k: str(v) if isinstance(v, Path) else v for k, v in (analysis or analysis_options()).items()},
               maps=figures, cases=results)
    return doc


# what only palpating a study takes; re-analysing kept cases refuses them
_PALPATION_OPTIONS = {"phantoms": "-n/--phantoms", "seed": "--seed", "paper": "--paper", "config": "--config",
                      "no_sessions": "--no-sessions"}


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
        cases = kept_cases(args.reanalyse) if args.reanalyse else study_cases(args.phantoms, args.seed, args.paper)
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
    doc = study_document(cases, results, wall_s, args.seed, executor.workers,
                         "dask" if args.scheduler else "local", analysis)
    doc["config"] = str(args.config) if args.config is not None else None  # what the phantoms were palpated with
    if args.reanalyse:
        doc["reanalysed"] = str(args.reanalyse)
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
