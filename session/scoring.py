"""Scoring what the analysis found against a phantom's ground truth, over many cases: the study's figures.

Each case's result is the JSON-able dictionary the study records (its truths, the analysis' matches,
false positives and tumours); :func:`score` turns a list of them into one map's figures (sensitivity,
false positives per phantom, localisation, both depth estimates, by depth band and by surface), and
:func:`print_summary` prints them.
"""

from __future__ import annotations

import math
import statistics
import sys
from collections.abc import Iterable
from typing import Any

import numpy as np

from session.detect import Tumour, match_ground_truth
from tissue.generator import SURFACES

DEPTH_BANDS_M = ((0.0, 3e-3), (3e-3, 6e-3), (6e-3, 9e-3), (9e-3, 12.5e-3))
SHALLOW_M = 6e-3  # the goal's "tumours whose top is at most 6 mm deep"


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


def _signal_figures(truths: list[tuple[dict, dict]]) -> dict[str, float | None]:
    """What the physics let the detector see of the (case, match) ``truths``: the median of its statistic
    where each tumour truly is (its signal over healthy tissue's error), and how many of them stood over the
    case's detection threshold there. A band whose tumours mostly do not cannot be reached at that false-alarm
    rate, whatever the analysis does with what it saw; one whose tumours do, and are not found, loses them in
    the analysis. None where the cases do not record it."""
    seen = [(m["evidence_z"], r["detection_threshold_z"]) for r, m in truths
            if _finite(m.get("evidence_z")) and _finite(r.get("detection_threshold_z"))]
    return {"signal_z_median": _median([z for z, _ in seen]),
            "signal_over_threshold_pct": _pct(sum(z >= limit for z, limit in seen), len(seen))}


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
        inside = [(r, m) for r, m, t in truths if lo <= t["depth_m"] < hi]
        bands[f"{lo * 1e3:.0f}-{hi * 1e3:.0f}mm"] = {
            "tumours": len(inside), "found": sum(1 for _, m in inside if m["found"]),
            "sensitivity_pct": _pct(sum(1 for _, m in inside if m["found"]), len(inside)),
            **_depth_figures([m for _, m in inside if m["found"]]),
            **_signal_figures(inside)}
    surfaces = {}
    for kind in SURFACES:
        phantoms = [r for r in drawn if r["surface"] == kind]
        inside = [m for r, m, _ in truths if r["surface"] == kind]
        surfaces[kind] = {
            "phantoms": len(phantoms), "tumours": len(inside), "found": sum(1 for m in inside if m["found"]),
            "sensitivity_pct": _pct(sum(1 for m in inside if m["found"]), len(inside)),
            "false_positives_per_phantom": _false_positives_per_phantom(phantoms, source)}
    shallow = [m for _, m, t in truths if t["depth_m"] <= SHALLOW_M]
    # by the phantom's name, whatever world's prefix the case has (app.study names them realistic-paper-flat)
    paper = {r["name"].removeprefix("realistic-"): r for r in results if r["paper"]}
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



def _fmt(value, unit: str = "", decimals: int = 1) -> str:
    return "—" if value is None else f"{value:.{decimals}f}{unit}"


def _depth_cell(figures: dict, estimate: str) -> str:
    error, bias = figures[f"depth_err_{estimate}_median_mm"], figures[f"depth_bias_{estimate}_median_mm"]
    return "—" if error is None else f"{error:.2f} ({bias:+.2f}) mm"


def print_summary(figures: dict[str, dict], wall_s: float, out=None) -> None:
    out = out or sys.stdout
    for source, f in figures.items():
        print(f"\n{source} map: {f['tumours']} tumours in {f['phantoms']} phantoms", file=out)
        print("  depth band   tumours  found  sensitivity   depth error (bias), rule / model   covered   "
              "signal z  over threshold", file=out)
        for band, b in f["by_depth"].items():
            print(f"  {band:>10} {b['tumours']:>9} {b['found']:>6}  {_fmt(b['sensitivity_pct'], ' %'):>10}   "
                  f"{_depth_cell(b, 'rule'):>15} / {_depth_cell(b, 'model'):<15} "
                  f"{_fmt(b['depth_interval_coverage_pct'], ' %'):>7}   {_fmt(b.get('signal_z_median')):>8}  "
                  f"{_fmt(b.get('signal_over_threshold_pct'), ' %'):>14}", file=out)
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
