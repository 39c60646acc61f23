"""Data exports of an analysed session: the stitched maps as CSV and JSON, the tumours as JSON, and the text
of the one-page report (painted by :mod:`widgets.map_painting`, with the maps as images).

JSON files carry NaN as ``null``; map arrays are nested lists indexed ``[ix][iy]`` (x first, like the grid).
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from session.analysis import SessionAnalysis
from session.detect import MATCH_RADIUS_M, DepthParams, DetectParams
from session.stitch import StitchParams, StitchResult

MAPS_FORMAT = "palpation-console-maps"
TUMOURS_FORMAT = "palpation-console-tumours"


class ExportError(RuntimeError):
    """An export could not be written; the message names the file and why."""


def json_ready(value: Any) -> Any:
    """``value`` with NumPy types as Python ones and NaN and infinities as None, for ``json.dumps``."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if isinstance(value, np.generic):
        return json_ready(value.item())
    return value


def _session_block(session) -> dict:
    return {"file": str(session.path), "uuid": session.uuid, "created_utc": session.created_utc,
            "simulated": session.simulated, "phantom": session.phantom_name}


def _params_block(stitch_params: StitchParams, detect_params: DetectParams | None = None,
                  depth_params: DepthParams | None = None) -> dict:
    out = {"cell_m": stitch_params.cell_m, "l0_source": stitch_params.l0_source.value,
           "l0_fixed_m": stitch_params.l0_fixed_m, "min_indentation_m": stitch_params.min_indentation_m}
    if detect_params is not None:
        out.update(false_alarm_per_area=detect_params.false_alarm_per_area, accuracy=detect_params.accuracy,
                   merge_radius_m=detect_params.merge_radius_m, fit_radius_m=detect_params.fit_radius_m,
                   kernel_widths_m=list(detect_params.kernel_widths_m))
    if depth_params is not None:
        out["depth_model_error"] = depth_params.model_error
        out["depth_scale_error"] = depth_params.scale_error
        out["depth_law_spread"] = depth_params.law_spread
    return out


def maps_document(analysis: SessionAnalysis) -> dict:
    stitched = analysis.stitched
    g = stitched.grid
    return json_ready({
        "format": MAPS_FORMAT, "version": 1, "session": _session_block(analysis.session),
        "params": _params_block(stitched.params),
        "grid": {"x0_m": g.x0_m, "y0_m": g.y0_m, "cell_m": g.cell_m, "nx": g.nx, "ny": g.ny,
                 "index_order": "[ix][iy]; cell centres at x0_m + (ix + 0.5) * cell_m, likewise y"},
        "levels": [{"force_N": lm.force_N, "tsi_indentation_m": lm.tsi_indentation_m,
                    "regions": int(len(lm.records)), "pressure_pa": lm.pressure_pa, "stiffness_pa": lm.stiffness_pa,
                    "indentation_m": lm.indentation_m, "coverage": lm.coverage, **lm.extra}
                   for lm in stitched.levels],
        "flat_field": analysis.flat_field,
    })


def tumours_document(analysis: SessionAnalysis) -> dict:
    session = analysis.session
    doc: dict[str, Any] = {
        "format": TUMOURS_FORMAT, "version": 1, "session": _session_block(session),
        "params": _params_block(analysis.params.stitch, analysis.params.detect, analysis.params.depth),
        "flat_field": analysis.flat_field,
        "tumours": [t.to_json() for t in analysis.tumours],
    }
    if analysis.has_ground_truth:
        doc["ground_truth"] = session.ground_truth
        doc["comparison"] = [asdict(m) for m in analysis.matches]
        doc["false_positives"] = analysis.false_positives
    return json_ready(doc)


def _write_text(path: Path, text: str) -> None:
    try:
        Path(path).write_text(text, encoding="utf-8")
    except OSError as err:
        raise ExportError(f"cannot write {path}: {err.strerror or err}") from None


def write_maps_json(path: str | Path, analysis: SessionAnalysis) -> None:
    _write_text(Path(path), json.dumps(maps_document(analysis), allow_nan=False))


def write_tumours_json(path: str | Path, analysis: SessionAnalysis) -> None:
    _write_text(Path(path), json.dumps(tumours_document(analysis), indent=2, allow_nan=False))


CSV_COLUMNS = ("force_N", "x_m", "y_m", "coverage", "pressure_pa", "stiffness_pa", "indentation_m")


def write_maps_csv(path: str | Path, stitched: StitchResult) -> None:
    """One row per palpated cell per force level (cells never palpated at that level are left out), the
    contrast maps (when analysed) as further columns after :data:`CSV_COLUMNS`."""
    xs, ys = stitched.grid.x_centres_m(), stitched.grid.y_centres_m()
    extra = list(stitched.levels[0].extra) if stitched.levels else []
    try:
        with open(path, "w", newline="", encoding="utf-8") as fh:
            out = csv.writer(fh)
            out.writerow(CSV_COLUMNS + tuple(extra))
            for lm in stitched.levels:
                ii, jj = np.nonzero(lm.coverage > 0)
                for i, j in zip(ii, jj):
                    values = (lm.coverage[i, j], lm.pressure_pa[i, j], lm.stiffness_pa[i, j], lm.indentation_m[i, j],
                              *(lm.extra[name][i, j] for name in extra))
                    out.writerow([f"{lm.force_N:g}", f"{xs[i]:.6g}", f"{ys[j]:.6g}"]
                                 + ["" if not math.isfinite(v) else f"{v:.6g}" for v in values])
    except OSError as err:
        raise ExportError(f"cannot write {path}: {err.strerror or err}") from None


# ---- the one-page report's text ------------------------------------------------------------------------


def _fmt_mm(value: float, decimals: int = 1) -> str:
    return f"{value * 1e3:.{decimals}f}" if math.isfinite(value) else "—"


def depth_model_text(t) -> str:
    """The model-based depth with its 90 % interval, or a dash while there is none."""
    if not math.isfinite(t.depth_model_m):
        return "—"
    return f"{_fmt_mm(t.depth_model_m)} [{_fmt_mm(t.depth_low_m)}, {_fmt_mm(t.depth_high_m)}]"


def report_lines(analysis: SessionAnalysis) -> tuple[list[str], list[list[str]], list[list[str]]]:
    """(header lines, tumour table rows, ground-truth table rows) of the report, as text."""
    session, stitched, tumours = analysis.session, analysis.stitched, analysis.tumours
    detect_params = analysis.params.detect
    p = stitched.params
    forces = ", ".join(f"{f:g}" for f in stitched.level_forces_N()) or "none"
    l0 = p.l0_source.value + (f" ({p.l0_fixed_m * 1e3:g} mm)" if p.l0_fixed_m else "")
    header = [
        f"Session {session.path.name}  ·  recorded {session.created_utc}  ·  {session.uuid}",
        f"{'Simulated' if session.simulated else 'Robot'} session"
        + (f", phantom {session.phantom_name!r}" if session.phantom_name else "")
        + f"; {len(session.regions())} regions, force levels {forces} N",
        f"Analysis: cell {p.cell_m * 1e3:g} mm, L0 source {l0}; spots where the contrast is significant at a "
        f"false-alarm rate of {detect_params.false_alarm_per_area:g} per palpated area (accuracy "
        f"{detect_params.accuracy * 100:g} %); {stitched.coverage_text(session.tissue_extent_m)} at the highest "
        f"level",
        f"Flat field: {analysis.flat_field}",
    ]
    header += [f"Warning: {w}" for w in session.warnings]
    table = [["source", "x (mm)", "y (mm)", "score (z)", "contrast (%)", "first level (N)", "depth, rule (mm)",
              "depth, model (mm)"]]
    for t in tumours:
        table.append([t.source, _fmt_mm(t.x_m), _fmt_mm(t.y_m), f"{t.score:.1f}", f"{t.contrast * 100:+.0f}",
                      f"{t.first_level_N:g}", _fmt_mm(t.depth_m, 2), depth_model_text(t)])
    truth_rows: list[list[str]] = []
    if analysis.has_ground_truth:
        truth_rows.append(["true tumour", "x, y (mm)", "depth (mm)", "map", "found", "error (mm)",
                           "depth, rule (mm)", "depth, model (mm)", "first level (N)"])
        for m in analysis.matches:
            truth_rows.append([str(m.truth_index + 1), f"{m.x_m * 1e3:.1f}, {m.y_m * 1e3:.1f}", _fmt_mm(m.depth_m),
                               m.source, "yes" if m.found else "no" if m.palpated else "not palpated",
                               _fmt_mm(m.error_xy_m),
                               _fmt_mm(m.depth_estimate_m, 2), depth_model_text(m),
                               f"{m.first_level_N:g}" if math.isfinite(m.first_level_N) else "—"])
        header.append(f"Ground truth matched within {MATCH_RADIUS_M * 1e3:g} mm. False positives (detections "
                      "matching no true tumour): "
                      + ", ".join(f"{k} map {v}" for k, v in analysis.false_positives.items()))
    return header, table, truth_rows
