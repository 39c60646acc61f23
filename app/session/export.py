"""Exports of a stitched session: map images, CSV/JSON of the maps, the tumours as JSON, a one-page report.

Images are painted with Qt (offscreen when there is no display) in the console's colour scale
(:mod:`widgets.colormaps`): x runs to the right, y upwards, in mm, every map with its own colour range
(printed on its colour bar) so each level shows its own contrast. Markers: white rings for tumours found in
that map, dashed black circles (true size) for a simulated phantom's real tumours.

JSON files carry NaN as ``null``; map arrays are nested lists indexed ``[ix][iy]`` (x first, like the grid).
"""

from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import asdict
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from app.session.detect import DetectParams, Tumour, match_ground_truth
from app.session.stitch import LevelMap, StitchParams, StitchResult

MAPS_FORMAT = "palpation-console-maps"
TUMOURS_FORMAT = "palpation-console-tumours"
# (LevelMap attribute, detection source, title, unit, display scale)
_PANELS = (("pressure_pa", "force", "force map", "kPa", 1e-3),
           ("stiffness_pa", "stiffness", "stiffness map", "kPa", 1e-3))


class ExportError(RuntimeError):
    """An export could not be written; the message names the file and why."""


# ---- plain data -----------------------------------------------------------------------------------------


def _clean(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, np.generic):
        return _clean(value.item())
    return value


def _session_block(session) -> dict:
    return {"file": str(session.path), "uuid": session.uuid, "created_utc": session.created_utc,
            "simulated": session.simulated, "phantom": session.phantom_name}


def _params_block(stitch_params: StitchParams, detect_params: DetectParams | None) -> dict:
    out = {"cell_m": stitch_params.cell_m, "l0_source": stitch_params.l0_source.value,
           "l0_fixed_m": stitch_params.l0_fixed_m, "min_indentation_m": stitch_params.min_indentation_m}
    if detect_params is not None:
        out.update(threshold=detect_params.threshold, min_area_m2=detect_params.min_area_m2,
                   merge_radius_m=detect_params.merge_radius_m)
    return out


def maps_document(session, stitched: StitchResult) -> dict:
    g = stitched.grid
    return _clean({
        "format": MAPS_FORMAT, "version": 1, "session": _session_block(session),
        "params": _params_block(stitched.params, None),
        "grid": {"x0_m": g.x0_m, "y0_m": g.y0_m, "cell_m": g.cell_m, "nx": g.nx, "ny": g.ny,
                 "index_order": "[ix][iy]; cell centres at x0_m + (ix + 0.5) * cell_m, likewise y"},
        "levels": [{"force_N": lm.force_N, "tsi_indentation_m": lm.tsi_indentation_m,
                    "regions": int(len(lm.records)), "pressure_pa": lm.pressure_pa, "stiffness_pa": lm.stiffness_pa,
                    "indentation_m": lm.indentation_m, "coverage": lm.coverage} for lm in stitched.levels],
    })


def tumours_document(session, stitched: StitchResult, tumours: list[Tumour], detect_params: DetectParams) -> dict:
    doc: dict[str, Any] = {
        "format": TUMOURS_FORMAT, "version": 1, "session": _session_block(session),
        "params": _params_block(stitched.params, detect_params),
        "tumours": [t.to_json() for t in tumours],
    }
    if session.ground_truth:
        matches, false_positives = match_ground_truth(tumours, session.ground_truth, stitched=stitched)
        doc["ground_truth"] = session.ground_truth
        doc["comparison"] = [asdict(m) for m in matches]
        doc["false_positives"] = false_positives
    return _clean(doc)


def _write_text(path: Path, text: str) -> None:
    try:
        Path(path).write_text(text, encoding="utf-8")
    except OSError as err:
        raise ExportError(f"cannot write {path}: {err.strerror or err}") from None


def write_maps_json(path: str | Path, session, stitched: StitchResult) -> None:
    _write_text(Path(path), json.dumps(maps_document(session, stitched), allow_nan=False))


def write_tumours_json(path: str | Path, session, stitched: StitchResult, tumours: list[Tumour],
                       detect_params: DetectParams) -> None:
    _write_text(Path(path), json.dumps(tumours_document(session, stitched, tumours, detect_params), indent=2,
                                       allow_nan=False))


CSV_COLUMNS = ("force_N", "x_m", "y_m", "coverage", "pressure_pa", "stiffness_pa", "indentation_m")


def write_maps_csv(path: str | Path, stitched: StitchResult) -> None:
    """One row per palpated cell per force level (cells never palpated at that level are left out)."""
    xs, ys = stitched.grid.x_centres_m(), stitched.grid.y_centres_m()
    try:
        with open(path, "w", newline="", encoding="utf-8") as fh:
            out = csv.writer(fh)
            out.writerow(CSV_COLUMNS)
            for lm in stitched.levels:
                ii, jj = np.nonzero(lm.coverage > 0)
                for i, j in zip(ii, jj):
                    values = (lm.coverage[i, j], lm.pressure_pa[i, j], lm.stiffness_pa[i, j], lm.indentation_m[i, j])
                    out.writerow([f"{lm.force_N:g}", f"{xs[i]:.6g}", f"{ys[j]:.6g}"]
                                 + ["" if not math.isfinite(v) else f"{v:.6g}" for v in values])
    except OSError as err:
        raise ExportError(f"cannot write {path}: {err.strerror or err}") from None


# ---- painting -------------------------------------------------------------------------------------------


def ensure_gui_application():
    """A Qt application to paint with: the running one, or an offscreen one when there is no display."""
    from PySide6 import QtGui

    app = QtGui.QGuiApplication.instance()
    if app is None:
        if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
        app = QtGui.QGuiApplication(["palpation-console"])
        globals()["_APP"] = app  # keep it alive as long as the module
    return app


def colour_range(values: np.ndarray) -> tuple[float, float]:
    """[2nd percentile, max] of the finite values: the map's own contrast, robust to a stray low cell."""
    finite = values[np.isfinite(values)]
    if not finite.size:
        return (0.0, 1.0)
    lo, hi = float(np.percentile(finite, 2.0)), float(finite.max())
    if hi <= lo:
        hi = lo + max(abs(lo) * 0.01, 1e-12)
    return lo, hi


def map_rgb(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(ny, nx, 3) uint8 image of an (nx, ny) map, y upwards (row 0 is the highest y)."""
    from widgets.colormaps import CONTOUR_LUT, NO_DATA_RGB

    image = values.T[::-1]
    finite = np.isfinite(image)
    index = np.zeros(image.shape, dtype=np.intp)
    scaled = (image[finite] - lo) / (hi - lo) * (len(CONTOUR_LUT) - 1)
    index[finite] = np.clip(np.round(scaled), 0, len(CONTOUR_LUT) - 1).astype(np.intp)
    rgb = CONTOUR_LUT[index].copy()
    rgb[~finite] = NO_DATA_RGB
    return np.ascontiguousarray(rgb, dtype=np.uint8)


class MapPainter:
    """Paints the per-level force and stiffness maps of a stitched session into a rectangle."""

    def __init__(self, stitched: StitchResult, tumours: list[Tumour], ground_truth: list[dict] | None = None):
        self.stitched = stitched
        self.tumours = tumours
        self.ground_truth = ground_truth or []

    def natural_size(self, px_per_mm: float) -> tuple[int, int]:
        g = self.stitched.grid
        w_mm, h_mm = g.nx * g.cell_m * 1e3, g.ny * g.cell_m * 1e3
        cell_w = w_mm * px_per_mm + 150
        cell_h = h_mm * px_per_mm + 70
        return int(len(_PANELS) * cell_w + 40), int(max(1, len(self.stitched.levels)) * cell_h + 40)

    def paint(self, painter, rect) -> None:
        from PySide6 import QtCore, QtGui

        levels = self.stitched.levels
        g = self.stitched.grid
        if not levels or g.nx == 0:
            painter.drawText(rect, QtCore.Qt.AlignmentFlag.AlignCenter, "No force level was recorded in this session")
            return
        cols, rows = len(_PANELS), len(levels)
        cw, ch = rect.width() / cols, rect.height() / rows
        font = QtGui.QFont("DejaVu Sans")
        font.setPixelSize(max(8, int(min(ch * 0.075, cw * 0.03))))
        painter.setFont(font)
        for r, lm in enumerate(levels):
            for c, panel in enumerate(_PANELS):
                cell = QtCore.QRectF(rect.left() + c * cw, rect.top() + r * ch, cw, ch)
                self._panel(painter, cell, lm, panel)

    def _panel(self, painter, cell, lm: LevelMap, panel) -> None:
        from PySide6 import QtCore, QtGui

        field, source, title, unit, scale = panel
        g = self.stitched.grid
        metrics = QtGui.QFontMetricsF(painter.font())
        line = metrics.height()
        painter.setPen(QtGui.QColor("black"))
        depth = f", TSI indentation {lm.tsi_indentation_m * 1e3:.2f} mm" if math.isfinite(lm.tsi_indentation_m) else ""
        painter.drawText(QtCore.QPointF(cell.left() + 4, cell.top() + line), f"{lm.force_N:g} N — {title}{depth}")
        bar_w = max(40.0, metrics.horizontalAdvance("000.0 kPa") + 16)
        avail = QtCore.QRectF(cell.left() + 4, cell.top() + line * 1.4, cell.width() - bar_w - 12,
                              cell.height() - line * 2.8)
        aspect = (g.nx * g.cell_m) / (g.ny * g.cell_m)
        w = min(avail.width(), avail.height() * aspect)
        h = w / aspect
        target = QtCore.QRectF(avail.left(), avail.top(), w, h)
        values = lm.quantity(field)
        lo, hi = colour_range(values)
        rgb = map_rgb(values, lo, hi)
        image = QtGui.QImage(rgb.data, rgb.shape[1], rgb.shape[0], rgb.strides[0], QtGui.QImage.Format.Format_RGB888)
        painter.drawImage(target, image)
        painter.setPen(QtGui.QPen(QtGui.QColor("black"), 1))
        painter.setBrush(QtCore.Qt.BrushStyle.NoBrush)
        painter.drawRect(target)
        x_min, x_max, y_min, y_max = g.extent_m

        def to_px(x_m: float, y_m: float) -> QtCore.QPointF:
            return QtCore.QPointF(target.left() + (x_m - x_min) / (x_max - x_min) * w,
                                  target.bottom() - (y_m - y_min) / (y_max - y_min) * h)

        px_per_m = w / (x_max - x_min)
        dashed = QtGui.QPen(QtGui.QColor("black"), 1.5, QtCore.Qt.PenStyle.DashLine)
        painter.save()
        painter.setClipRect(target)  # tumours outside the palpated part of the tissue stay off the page
        for truth in self.ground_truth:
            radius = float(truth.get("diameter_m", 8e-3)) / 2 * px_per_m
            painter.setPen(dashed)
            painter.drawEllipse(to_px(float(truth["x_m"]), float(truth["y_m"])), radius, radius)
        ring = QtGui.QPen(QtGui.QColor("white"), 2.5)
        for t in self.tumours:
            if t.source == source and lm.force_N >= t.first_level_N - 1e-9:
                painter.setPen(ring)
                painter.drawEllipse(to_px(t.x_m, t.y_m), 3e-3 * px_per_m, 3e-3 * px_per_m)
        painter.restore()
        painter.setPen(QtGui.QColor("black"))
        painter.drawText(QtCore.QPointF(target.left(), target.bottom() + line),
                         f"x {x_min * 1e3:.0f}–{x_max * 1e3:.0f} mm, y {y_min * 1e3:.0f}–{y_max * 1e3:.0f} mm")
        self._colour_bar(painter, QtCore.QRectF(target.right() + 8, target.top(), 12, h), lo * scale, hi * scale, unit)

    @staticmethod
    def _colour_bar(painter, rect, lo: float, hi: float, unit: str) -> None:
        from PySide6 import QtCore, QtGui

        from widgets.colormaps import CONTOUR_LUT

        strip = np.ascontiguousarray(CONTOUR_LUT[::-1][:, None, :].repeat(4, axis=1))
        image = QtGui.QImage(strip.data, strip.shape[1], strip.shape[0], strip.strides[0],
                             QtGui.QImage.Format.Format_RGB888)
        painter.drawImage(rect, image)
        painter.drawRect(rect)
        line = QtGui.QFontMetricsF(painter.font()).height()
        painter.drawText(QtCore.QPointF(rect.right() + 4, rect.top() + line * 0.7), f"{hi:.1f} {unit}")
        painter.drawText(QtCore.QPointF(rect.right() + 4, rect.bottom()), f"{lo:.1f}")


def _save_image(image, path: Path) -> None:
    if not image.save(str(path)):
        raise ExportError(f"cannot write {path}: Qt could not save the image there (check the folder exists, "
                          "is writable, and the name ends in .png)")


def render_maps_png(path: str | Path, stitched: StitchResult, tumours: list[Tumour],
                    ground_truth: list[dict] | None = None, px_per_mm: float = 6.0) -> tuple[int, int]:
    """Every level's force and stiffness maps in one image; returns its size in pixels."""
    from PySide6 import QtCore, QtGui

    ensure_gui_application()
    maps = MapPainter(stitched, tumours, ground_truth)
    w, h = maps.natural_size(px_per_mm)
    image = QtGui.QImage(w, h, QtGui.QImage.Format.Format_RGB32)
    image.fill(QtGui.QColor("white"))
    painter = QtGui.QPainter(image)
    try:
        painter.setRenderHint(QtGui.QPainter.RenderHint.Antialiasing)
        maps.paint(painter, QtCore.QRectF(20, 20, w - 40, h - 40))
    finally:
        painter.end()
    _save_image(image, Path(path))
    return w, h


# ---- the one-page report -----------------------------------------------------------------------------


def _fmt_mm(value: float, decimals: int = 1) -> str:
    return f"{value * 1e3:.{decimals}f}" if math.isfinite(value) else "—"


def report_lines(session, stitched: StitchResult, tumours: list[Tumour], detect_params: DetectParams
                 ) -> tuple[list[str], list[list[str]], list[list[str]]]:
    """(header lines, tumour table rows, ground-truth table rows) of the report, as text."""
    p = stitched.params
    forces = ", ".join(f"{f:g}" for f in stitched.level_forces_N()) or "none"
    l0 = p.l0_source.value + (f" ({p.l0_fixed_m * 1e3:g} mm)" if p.l0_fixed_m else "")
    header = [
        f"Session {session.path.name}  ·  recorded {session.created_utc}  ·  {session.uuid}",
        f"{'Simulated' if session.simulated else 'Robot'} session"
        + (f", phantom {session.phantom_name!r}" if session.phantom_name else "")
        + f"; {len(session.regions())} regions, force levels {forces} N",
        f"Analysis: cell {p.cell_m * 1e3:g} mm, L0 source {l0}, threshold +{detect_params.threshold * 100:g} % over "
        f"the map's median, spots >= {detect_params.min_area_m2 * 1e6:g} mm²; covered "
        f"{stitched.covered_fraction() * 100:.0f} % of the grid at the highest level",
    ]
    header += [f"Warning: {w}" for w in session.warnings]
    table = [["source", "x (mm)", "y (mm)", "depth (mm)", "first level (N)", "peak rise (%)"]]
    for t in tumours:
        table.append([t.source, _fmt_mm(t.x_m), _fmt_mm(t.y_m), _fmt_mm(t.depth_m, 2), f"{t.first_level_N:g}",
                      f"{t.peak_rise * 100:.0f}"])
    truth_rows: list[list[str]] = []
    if session.ground_truth:
        matches, false_positives = match_ground_truth(tumours, session.ground_truth, stitched=stitched)
        truth_rows.append(["true tumour", "x, y (mm)", "depth (mm)", "map", "found", "error (mm)",
                           "depth est. (mm)", "first level (N)"])
        for m in matches:
            truth_rows.append([str(m.truth_index + 1), f"{m.x_m * 1e3:.1f}, {m.y_m * 1e3:.1f}", _fmt_mm(m.depth_m),
                               m.source, "yes" if m.found else "no" if m.palpated else "not palpated",
                               _fmt_mm(m.error_xy_m),
                               _fmt_mm(m.depth_estimate_m, 2),
                               f"{m.first_level_N:g}" if math.isfinite(m.first_level_N) else "—"])
        header.append("False positives (detections matching no true tumour): "
                      + ", ".join(f"{k} map {v}" for k, v in false_positives.items()))
    return header, table, truth_rows


def _draw_table(painter, left: float, top: float, width: float, rows: list[list[str]]) -> float:
    from PySide6 import QtCore, QtGui

    if not rows:
        return top
    line = QtGui.QFontMetricsF(painter.font()).height() * 1.25
    col_w = width / len(rows[0])
    bold = QtGui.QFont(painter.font())
    bold.setBold(True)
    normal = QtGui.QFont(painter.font())
    for r, row in enumerate(rows):
        painter.setFont(bold if r == 0 else normal)
        for c, text in enumerate(row):
            painter.drawText(QtCore.QRectF(left + c * col_w, top + r * line, col_w - 4, line),
                             QtCore.Qt.AlignmentFlag.AlignLeft | QtCore.Qt.AlignmentFlag.AlignVCenter, text)
    painter.setFont(normal)
    return top + len(rows) * line


def write_report(path: str | Path, session, stitched: StitchResult, tumours: list[Tumour],
                 detect_params: DetectParams) -> None:
    """One page: header, the maps at every level, the tumour table and, for simulated sessions, the
    comparison with the phantom's ground truth. PDF (A4) for a ``.pdf`` name, otherwise a PNG."""
    from PySide6 import QtCore, QtGui

    ensure_gui_application()
    path = Path(path)
    header, table, truth = report_lines(session, stitched, tumours, detect_params)
    pdf = path.suffix.lower() == ".pdf"
    if pdf:
        if not path.parent.is_dir():
            raise ExportError(f"cannot write {path}: the folder {path.parent} does not exist")
        device = QtGui.QPdfWriter(str(path))
        device.setPageSize(QtGui.QPageSize(QtGui.QPageSize.PageSizeId.A4))
        device.setResolution(150)
        device.setTitle(f"Palpation session {session.path.name}")
        device.setCreator("Palpation Console")
        width, height = device.width(), device.height()
    else:
        width, height = 1240, 1754  # A4 at 150 dpi
        device = QtGui.QImage(width, height, QtGui.QImage.Format.Format_RGB32)
        device.fill(QtGui.QColor("white"))
    painter = QtGui.QPainter()
    if not painter.begin(device):
        raise ExportError(f"cannot write {path}: Qt could not open it for painting")
    try:
        painter.setRenderHint(QtGui.QPainter.RenderHint.Antialiasing)
        margin = width * 0.05
        usable = width - 2 * margin
        title = QtGui.QFont("DejaVu Sans")
        title.setPixelSize(int(height * 0.016))
        title.setBold(True)
        painter.setFont(title)
        painter.drawText(QtCore.QPointF(margin, margin), "Palpation session report")
        body = QtGui.QFont("DejaVu Sans")
        body.setPixelSize(int(height * 0.0085))
        painter.setFont(body)
        line = QtGui.QFontMetricsF(body).height() * 1.2
        y = margin + line
        for text in header:
            rect = QtCore.QRectF(margin, y, usable, line * 3)
            bounds = painter.boundingRect(rect, int(QtCore.Qt.TextFlag.TextWordWrap), text)
            painter.drawText(rect, int(QtCore.Qt.TextFlag.TextWordWrap), text)
            y += bounds.height() + line * 0.2
        tables_h = (len(table) + len(truth) + 3) * line * 1.25
        maps_h = max(height * 0.2, height - margin - y - tables_h - line)
        MapPainter(stitched, tumours, session.ground_truth).paint(painter, QtCore.QRectF(margin, y, usable, maps_h))
        painter.setFont(body)
        y += maps_h + line
        painter.drawText(QtCore.QPointF(margin, y), "Tumours found (depth = TSI indentation at the first level)"
                         if len(table) > 1 else "No tumour found with these parameters")
        y = _draw_table(painter, margin, y + line * 0.3, usable, table if len(table) > 1 else [])
        if truth:
            y += line
            painter.drawText(QtCore.QPointF(margin, y), "Against the simulated phantom's ground truth")
            _draw_table(painter, margin, y + line * 0.3, usable, truth)
        stamp = f"Palpation Console {session.software_version} · {datetime.now():%Y-%m-%d %H:%M}"
        painter.drawText(QtCore.QPointF(margin, height - margin * 0.4), stamp)
    finally:
        painter.end()
    if not pdf:
        _save_image(device, path)
