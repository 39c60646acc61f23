"""The continuum tissue model: precompute time, per-tick cost, and what it predicts for the paper's bench.

Writes ``rig.json``:

* ``precompute_s`` - building the flat phantom's model as the simulated rig uses it (finite-strain
  correction on) from nothing (empty cache), and ``uneven_precompute_s`` the same for the uneven one;
* ``contact_eval_p50_us`` / ``contact_eval_p99_us`` - one ``element_forces_N`` call of the rig's model, at poses a
  palpation visits (region centres with up to 0.5 mm of drift, depths between the 1 N and 7 N levels);
* ``flat_7N_indentation_mm`` - the TSI indentation (mean dL over elements in contact) at 7 N, averaged
  over the flat phantom's regions, with the rig's default model (``flat_7N_indentation_linear_mm``:
  without the finite-strain correction); the paper measured 9.29 mm;
* per phantom, the TSI indentation at 1..7 N in every region (``*_indentation_mm``), the paper's
  measured points beside them, the same for the Winkler spring model and for the continuum model with
  its finite-strain correction, and each tumour's contrast in the force and the stiffness (Eq. 1) maps
  at every level against the same phantom without tumours (see tissue/mechanics/study.py), with the
  linear model and (``*_contrast_finite_strain``) with the rig's finite-strain model;
* ``contrast_2mm_at_1N``, ``contrast_2mm_at_7N`` and the same for the 7 mm and 10 mm tumours: each flat-phantom
  tumour's stiffness-map contrast at 1 N and 7 N with the rig's model (it grows with the press at finite
  strain; the linear model's does not);
* ``full_solve_validation`` - the finite-strain model against a full nonlinear solve, per element, in total
  force and in each tumour's contrast, at 2, 5 and 8 mm (see :func:`_validation`).
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from tissue.mechanics.finite_strain import homogeneous, punch
from tissue.mechanics.model import ContinuumTissue, MeshSettings, phantom_material
from tissue.mechanics.progress import TextProgressBar
from tissue.mechanics.study import height_for_force, palpate, tumour_contrast, tumour_standout, without_inclusions
from tissue.phantom import load_phantom, parse_phantom
from tissue.winkler import WinklerTissue

LEVELS_N = (1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0)
PAPER = {"flat": {2.0: 2.26, 5.0: 7.40, 7.0: 9.29}, "uneven": {7.0: 10.54}}
# A tumour "shows" in a map when its patch reads 10 % above the tumour-free phantom's: over three
# standard deviations of the simulated array's element-to-element gain spread (3 %).
CONTRAST_VISIBLE = 0.10


def _timed_load(phantom, cache_dir: str | None, finite_strain: bool = False) -> tuple[ContinuumTissue, float]:
    started = time.perf_counter()
    tissue = ContinuumTissue.load(phantom, cache_dir=cache_dir, progress=TextProgressBar(interval_s=1.0),
                                  settings=MeshSettings(finite_strain=finite_strain))
    return tissue, time.perf_counter() - started


def _per_call_us(tissue: ContinuumTissue, calls: int = 20000) -> np.ndarray:
    rng = np.random.default_rng(7)
    regions = tissue.phantom.palpation_regions()
    poses = []
    for x, y in regions:
        lo, hi = height_for_force(tissue, x, y, 7.0), height_for_force(tissue, x, y, 1.0)
        poses.append((x, y, lo, hi))
    samples = np.empty(calls)
    for i in range(calls):
        x, y, lo, hi = poses[i % len(poses)]
        args = (x + rng.uniform(-5e-4, 5e-4), y + rng.uniform(-5e-4, 5e-4), rng.uniform(lo, hi))
        started = time.perf_counter_ns()
        tissue.element_forces_N(*args)
        samples[i] = time.perf_counter_ns() - started
    return samples / 1e3


def _phantom_report(name: str, tissue: ContinuumTissue, stiffened: ContinuumTissue) -> dict:
    phantom = tissue.phantom
    study = palpate(tissue, LEVELS_N)
    finite = palpate(stiffened, LEVELS_N)
    clean, _ = _timed_load(without_inclusions(phantom), None)
    clean_finite, _ = _timed_load(without_inclusions(phantom), None, finite_strain=True)
    reference = palpate(clean, LEVELS_N)
    finite_reference = palpate(clean_finite, LEVELS_N)
    winkler = palpate(WinklerTissue(phantom), LEVELS_N)
    report: dict = {
        f"{name}_levels_N": list(LEVELS_N),
        f"{name}_indentation_mm": [[r.tsi_indentation_m * 1e3 for r in region] for region in study],
        f"{name}_mean_indentation_mm": [float(np.mean([region[k].tsi_indentation_m for region in study]) * 1e3)
                                        for k in range(len(LEVELS_N))],
        # NaN where the springs cannot push that hard before the face reaches the table.
        f"{name}_winkler_mean_indentation_mm": [
            float(np.mean([region[k].tsi_indentation_m for region in winkler]) * 1e3) for k in range(len(LEVELS_N))],
        f"{name}_finite_strain_mean_indentation_mm": [
            float(np.mean([region[k].tsi_indentation_m for region in finite]) * 1e3) for k in range(len(LEVELS_N))],
        f"{name}_paper_indentation_mm": {f"{f:g}N": v for f, v in PAPER[name].items()},
    }
    a, b = stiffened.stiffening
    s10 = 0.010 / phantom.thickness_m
    report[f"{name}_finite_strain_force_ratio_at_10mm"] = 1.0 + a * s10 + b * s10 * s10
    truths = phantom.ground_truth()
    for field, label, unit in (("forces_N", "force", 1e3), ("stiffness_pa", "stiffness", 1e-3)):
        rel, excess, standout = {}, {}, {}
        for which, truth in enumerate(truths):
            key = f"tumour_{truth['depth_m'] * 1e3:.0f}mm_at_x{truth['x_m'] * 1e3:.0f}mm"
            pairs = [tumour_contrast(study, reference, k, truth, field) for k in range(len(LEVELS_N))]
            rel[key] = [p[0] for p in pairs]
            excess[key] = [p[1] * unit for p in pairs]
            standout[key] = [tumour_standout(study, k, truths, which, field) for k in range(len(LEVELS_N))]
        report[f"{name}_{label}_map_contrast"] = rel
        report[f"{name}_{label}_map_excess_{'mN' if label == 'force' else 'kPa'}"] = excess
        report[f"{name}_{label}_map_standout"] = standout
        report[f"{name}_{label}_map_contrast_finite_strain"] = {
            f"tumour_{truth['depth_m'] * 1e3:.0f}mm_at_x{truth['x_m'] * 1e3:.0f}mm":
                [tumour_contrast(finite, finite_reference, k, truth, field)[0] for k in range(len(LEVELS_N))]
            for truth in truths}
    return report


VALIDATION_DEPTHS_MM = (2.0, 5.0, 8.0)


def _validation(cache_dir: str) -> dict:
    """The rig's finite-strain model against a full nonlinear solve (finite_strain.punch) of the flat phantom
    with one of its tumours (2, 7, 10 mm deep) under the middle region, at 2, 5 and 8 mm of indentation:
    each element's nonlinear/linear force ratio in the two, the total force, and the tumour's contrast
    in total force over the region against the same phantom without it. The full solve is a 2 mm mesh (it
    agrees with a 1 mm one within 2.7 % per element at 8 mm); where it stops short of 8 mm its deepest
    depth is reported.
    The uniform correction the model had before (every element scaled by the block's total stiffening)
    is scored beside it."""
    flat = load_phantom("flat")
    base = without_inclusions(flat)
    x0, y0 = flat.length_m / 2, flat.width_m / 2
    solve = dict(face_m=(8e-3, 30e-3), max_indentation_m=8e-3, step_m=0.5e-3, spacing_m=2e-3, y_spacing_m=2e-3,
                 layers=6)
    models = {"none": (ContinuumTissue.load(base, cache_dir, settings=MeshSettings(finite_strain=True)),
                       ContinuumTissue.load(base, cache_dir, settings=MeshSettings()))}
    full = {"none": punch(flat.length_m, flat.width_m, flat.thickness_m,
                          homogeneous(flat.youngs_modulus_pa, flat.poisson_ratio), **solve)}
    for truth in flat.ground_truth():
        key = f"{truth['depth_m'] * 1e3:.0f}mm"
        data = json.loads(json.dumps(base.source))
        data["phantom"]["name"] = f"flat-{key}-tumour-centred"
        data["phantom"]["inclusions"] = [{"centre_xy_m": [x0, y0], "diameter_m": truth["diameter_m"],
                                          "youngs_modulus_pa": truth["youngs_modulus_pa"], "depth_m": truth["depth_m"]}]
        phantom = parse_phantom(data, data["phantom"]["name"])
        models[key] = (ContinuumTissue.load(phantom, cache_dir, settings=MeshSettings(finite_strain=True)),
                       ContinuumTissue.load(phantom, cache_dir, settings=MeshSettings()))
        material = phantom_material(phantom)
        full[key] = punch(flat.length_m, flat.width_m, flat.thickness_m,
                          lambda points, m=material: m(points + np.array([x0, y0, 0.0])), **solve)
    a_total, b_total = models["none"][0].stiffening
    out: dict = {}
    for key, solution in full.items():
        finite, linear = models[key]
        rows = []
        for want in VALIDATION_DEPTHS_MM:
            k = int(np.argmin(np.abs(solution.indentation_m - want * 1e-3)))
            d = float(solution.indentation_m[k])
            z = flat.thickness_m - d
            model_ratio = finite.element_forces_N(x0, y0, z) / linear.element_forces_N(x0, y0, z)
            full_ratio = solution.nonlinear_N[k] / solution.linear_N()[k]
            err = model_ratio / full_ratio - 1.0
            s = d / flat.thickness_m
            uniform_err = (1.0 + a_total * s + b_total * s * s) / full_ratio - 1.0
            row = {"depth_mm": d * 1e3,
                   "element_err_max_pct": float(np.abs(err).max() * 100),
                   "element_err_rms_pct": float(np.sqrt((err**2).mean()) * 100),
                   "uniform_element_err_max_pct": float(np.abs(uniform_err).max() * 100),
                   "total_err_pct": float((finite.total_force_N(x0, y0, z) / linear.total_force_N(x0, y0, z))
                                          / (solution.nonlinear_N[k].sum() / solution.linear_N()[k].sum()) * 100
                                          - 100)}
            same = np.flatnonzero(np.abs(full["none"].indentation_m - d) < 1e-9)
            if key != "none" and len(same):
                clean_finite, clean_linear = models["none"]
                clean = full["none"].nonlinear_N[same[0]].sum()
                row["contrast_full"] = float(solution.nonlinear_N[k].sum() / clean - 1)
                row["contrast_full_linear"] = float(solution.linear_N_per_m.sum()
                                                    / full["none"].linear_N_per_m.sum() - 1)
                row["contrast_model"] = float(finite.total_force_N(x0, y0, z)
                                              / clean_finite.total_force_N(x0, y0, z) - 1)
                row["contrast_model_linear"] = float(linear.total_force_N(x0, y0, z)
                                                     / clean_linear.total_force_N(x0, y0, z) - 1)
            rows.append(row)
        out[f"tumour_{key}" if key != "none" else "no_tumour"] = rows
    return out


def _print_summary(result: dict) -> None:
    print(f"precompute: flat {result['precompute_s']:.1f} s, uneven {result['uneven_precompute_s']:.1f} s; "
          f"per call p50 {result['contact_eval_p50_us']:.1f} us, p99 {result['contact_eval_p99_us']:.1f} us")
    for name in ("flat", "uneven"):
        levels = result[f"{name}_levels_N"]
        print(f"{name}: mean TSI indentation (mm) at " + ", ".join(f"{f:g}" for f in levels) + " N")
        print("  continuum " + " ".join(f"{v:6.2f}" for v in result[f"{name}_mean_indentation_mm"]))
        print("  winkler   " + " ".join(f"{v:6.2f}" for v in result[f"{name}_winkler_mean_indentation_mm"]))
        print("  finite-e  " + " ".join(f"{v:6.2f}" for v in result[f"{name}_finite_strain_mean_indentation_mm"])
              + f"   (force x{result[f'{name}_finite_strain_force_ratio_at_10mm']:.2f} at 10 mm)")
        print("  paper     " + ", ".join(f"{k}: {v} mm" for k, v in result[f"{name}_paper_indentation_mm"].items()))
        for label in ("force", "stiffness"):
            for tumour, contrast in result[f"{name}_{label}_map_contrast"].items():
                shown = [f"{f:g}" for f, c in zip(levels, contrast) if c > CONTRAST_VISIBLE]
                print(f"  {label:9s} map, {tumour}: contrast " + " ".join(f"{c:+.2f}" for c in contrast)
                      + f"  (shows at {', '.join(shown) or 'no'} N)")
                standout = result[f"{name}_{label}_map_standout"][tumour]
                print(f"  {'':9s}      {'':{len(tumour)}s}  standout " + " ".join(f"{v:5.2f}" for v in standout))
                finite = result[f"{name}_{label}_map_contrast_finite_strain"][tumour]
                print(f"  {'':9s}      {'':{len(tumour)}s}  finite-e " + " ".join(f"{c:+.2f}" for c in finite))
    print("finite-strain model against a full nonlinear solve (flat phantom, one tumour under the face):")
    for case, rows in result["full_solve_validation"].items():
        for row in rows:
            line = (f"  {case:12s} {row['depth_mm']:4.1f} mm: element ratio error max "
                    f"{row['element_err_max_pct']:4.1f} %"
                    f" rms {row['element_err_rms_pct']:4.1f} % (uniform correction: max"
                    f" {row['uniform_element_err_max_pct']:4.1f} %), total {row['total_err_pct']:+5.1f} %")
            if "contrast_full" in row:
                line += (f"; contrast full {row['contrast_full']:+.3f} (linear {row['contrast_full_linear']:+.3f}),"
                         f" model {row['contrast_model']:+.3f} (linear {row['contrast_model_linear']:+.3f})")
            print(line)


def run(out_dir: Path) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="tissue-cache-") as fresh:
        # the rig's default model (finite strain on) from an empty cache: what a new phantom costs
        flat_fs, precompute_s = _timed_load(load_phantom("flat"), fresh, finite_strain=True)
        uneven_fs, uneven_precompute_s = _timed_load(load_phantom("uneven"), fresh, finite_strain=True)
        flat, _ = _timed_load(load_phantom("flat"), fresh)  # the linear model shares the cached tables
        uneven, _ = _timed_load(load_phantom("uneven"), fresh)
    calls = np.concatenate([_per_call_us(flat_fs), _per_call_us(uneven_fs)])  # the rig's model
    result = {
        "precompute_s": precompute_s,
        "uneven_precompute_s": uneven_precompute_s,
        "contact_eval_p50_us": float(np.percentile(calls, 50)),
        "contact_eval_p99_us": float(np.percentile(calls, 99)),
        "contact_eval_calls": int(len(calls)),
        "flat_mesh_elements": list(flat.mesh_shape),
    }
    result.update(_phantom_report("flat", flat, flat_fs))
    result.update(_phantom_report("uneven", uneven, uneven_fs))
    seven = LEVELS_N.index(7.0)
    # the simulated rig's default model stiffens at finite strain; the linear figure is kept beside it
    result["flat_7N_indentation_mm"] = result["flat_finite_strain_mean_indentation_mm"][seven]
    result["flat_7N_indentation_linear_mm"] = result["flat_mean_indentation_mm"][seven]
    result["uneven_7N_indentation_mm"] = result["uneven_finite_strain_mean_indentation_mm"][seven]
    result["contrast_visible_threshold"] = CONTRAST_VISIBLE
    # the tumours' contrast in the stiffness map (Eq. 1) with the rig's model, at the first and last level
    for key, contrast in result["flat_stiffness_map_contrast_finite_strain"].items():
        depth = key.split("_")[1]
        result[f"contrast_{depth}_at_1N"] = contrast[LEVELS_N.index(1.0)]
        result[f"contrast_{depth}_at_7N"] = contrast[seven]
    with tempfile.TemporaryDirectory(prefix="tissue-cache-") as fresh:
        result["full_solve_validation"] = _validation(fresh)
    (out_dir / "rig.json").write_text(json.dumps(result, indent=2), encoding="utf-8")
    _print_summary(result)
    return result


if __name__ == "__main__":
    run(Path(__file__).resolve().parents[1] / "build" / "bench")
