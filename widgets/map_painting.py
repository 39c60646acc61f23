"""Exported pictures of a stitched session, painted with Qt: the maps of every level, and the one-page report.

Images are painted (offscreen when there is no display) in the console's colour scale, with the same
colour mapping as the screen (:mod:`widgets.colormaps`), every map with its own colour range (printed on its
colour bar) so each level shows its own contrast. Markers: white rings for tumours found in that map, dashed
black circles (true size) for a simulated phantom's real tumours. The report's words come from
:func:`session.export.report_lines`.

Every map is drawn as the console and the reviewer draw it: x upwards and y to the right, in mm, with tick
values and the axes named on each map (:mod:`widgets.tissue_view` says why that way), so a tumour up and to
the left on the screen is up and to the left on paper. The tissue's long side (x) then stands upright, so the
levels run across the page in columns and the maps down it in rows: on an A4 page the seven levels of a
0-7 N ramp keep maps about as large as the old rows of wide maps did.
"""

from __future__ import annotations

import math
import os
from datetime import datetime
from pathlib import Path

import numpy as np
from PySide6 import QtCore, QtGui

from session.analysis import SessionAnalysis
from session.detect import Tumour
from session.export import ExportError, report_lines
from session.stitch import LevelMap, StitchResult
from widgets.colormaps import CONTOUR_LUT, colour_range, contrast_range, map_rgb
from widgets.tactile_map import nice_step

# (LevelMap attribute, detection source, title, unit, display scale)
# Each raw map beside its contrast (when the analysis made one): the raw map is what was measured, the
# contrast what is left once the probe's own pattern is divided out.
_PANELS = (("pressure_pa", "force", "force map", "kPa", 1e-3),
           ("force_contrast", "force", "force contrast", "%", 100.0),
           ("stiffness_pa", "stiffness", "stiffness map", "kPa", 1e-3),
           ("stiffness_contrast", "stiffness", "stiffness contrast", "%", 100.0))


def ensure_gui_application():
    """A Qt application to paint with: the running one, or an offscreen one when there is no display."""
    app = QtGui.QGuiApplication.instance()
    if app is None:
        if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
        app = QtGui.QGuiApplication(["palpation-console"])
        globals()["_APP"] = app  # keep it alive as long as the module
    return app


class MapPainter:
    """Paints the per-level maps of a stitched session into a rectangle: a column per force level (the lowest
    on the left), a row per map (:data:`_PANELS`), every map x upwards and y to the right."""

    def __init__(self, stitched: StitchResult, tumours: list[Tumour], ground_truth: list[dict] | None = None):
        self.stitched = stitched
        self.tumours = tumours
        self.ground_truth = ground_truth or []
        known = stitched.levels[0].extra if stitched.levels else {}
        self.panels = [p for p in _PANELS if not p[0].endswith("_contrast") or p[0] in known]

    def natural_size(self, px_per_mm: float) -> tuple[int, int]:
        g = self.stitched.grid
        across_mm, up_mm = g.ny * g.cell_m * 1e3, g.nx * g.cell_m * 1e3
        cell_w = across_mm * px_per_mm + 130
        cell_h = up_mm * px_per_mm + 150
        return int(max(1, len(self.stitched.levels)) * cell_w + 40), int(len(self.panels) * cell_h + 100)

    def paint(self, painter, rect) -> None:
        levels = self.stitched.levels
        g = self.stitched.grid
        if not levels or g.nx == 0:
            painter.drawText(rect, QtCore.Qt.AlignmentFlag.AlignCenter, "No force level was recorded in this session")
            return
        cols, rows = len(levels), len(self.panels)
        cw = rect.width() / cols
        font = QtGui.QFont("DejaVu Sans")
        font.setPixelSize(max(8, int(min(rect.height() / rows * 0.04, cw * 0.065))))
        bold = QtGui.QFont(font)
        bold.setBold(True)
        line = QtGui.QFontMetricsF(font).height()
        header = line * 2.4  # each column's level and TSI indentation, said once above its maps
        ch = (rect.height() - header) / rows
        painter.setPen(QtGui.QColor("black"))
        for c, lm in enumerate(levels):
            left = rect.left() + c * cw
            painter.setFont(bold)
            painter.drawText(QtCore.QPointF(left + 4, rect.top() + line), f"{lm.force_N:g} N")
            painter.setFont(font)
            if math.isfinite(lm.tsi_indentation_m):
                painter.drawText(QtCore.QPointF(left + 4, rect.top() + line * 2),
                                 f"TSI indentation {lm.tsi_indentation_m * 1e3:.2f} mm")
            for r, panel in enumerate(self.panels):
                self._panel(painter, QtCore.QRectF(left, rect.top() + header + r * ch, cw, ch), lm, panel)

    def _panel(self, painter, cell, lm: LevelMap, panel) -> None:
        field, source, title, unit, scale = panel
        g = self.stitched.grid
        metrics = QtGui.QFontMetricsF(painter.font())
        line = metrics.height()
        painter.setPen(QtGui.QColor("black"))
        painter.drawText(QtCore.QPointF(cell.left() + 4, cell.top() + line), title)
        values = lm.quantity(field)
        lo, hi = contrast_range(values) if field.endswith("_contrast") else colour_range(values)
        x_min, x_max, y_min, y_max = (v * 1e3 for v in g.extent_m)
        # room on the left for the rotated "x (mm)" and tick values of up to three digits; under the map for the
        # y ticks, "y (mm)" and the colour bar, which lies flat: beside an upright map it would take the width
        # the map needs on a page of seven columns
        ticks_w = metrics.horizontalAdvance("000") + 6
        left_w = line + ticks_w
        avail = QtCore.QRectF(cell.left() + 4 + left_w, cell.top() + line * 1.4, cell.width() - 16 - left_w,
                              cell.height() - line * 6.3)
        aspect = (y_max - y_min) / (x_max - x_min)  # width over height: y across, x up
        w = min(avail.width(), avail.height() * aspect)
        h = w / aspect
        target = QtCore.QRectF(avail.left(), avail.top(), w, h)
        rgb = map_rgb(values, lo, hi)
        image = QtGui.QImage(rgb.data, rgb.shape[1], rgb.shape[0], rgb.strides[0], QtGui.QImage.Format.Format_RGB888)
        painter.drawImage(target, image)
        painter.setPen(QtGui.QPen(QtGui.QColor("black"), 1))
        painter.setBrush(QtCore.Qt.BrushStyle.NoBrush)
        painter.drawRect(target)

        def to_px(x_m: float, y_m: float) -> QtCore.QPointF:
            return QtCore.QPointF(target.left() + (y_m * 1e3 - y_min) / (y_max - y_min) * w,
                                  target.bottom() - (x_m * 1e3 - x_min) / (x_max - x_min) * h)

        px_per_m = w / (y_max - y_min) * 1e3
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
        self._axes(painter, target, (x_min, x_max), (y_min, y_max), ticks_w)
        self._colour_bar(painter, QtCore.QRectF(target.left(), target.bottom() + line * 2.6, w, line * 0.7),
                         lo * scale, hi * scale, unit)

    @staticmethod
    def _axes(painter, target, x_mm: tuple[float, float], y_mm: tuple[float, float], ticks_w: float) -> None:
        """Tick values in mm along the map's left edge (x, upwards) and under it (y, to the right), and the
        axes' names, so a map cut out of the page still says which way is which."""
        line = QtGui.QFontMetricsF(painter.font()).height()
        painter.setPen(QtGui.QPen(QtGui.QColor("black"), 1))
        align = QtCore.Qt.AlignmentFlag
        # about one tick per three lines of text, so the values never touch
        for t in _ticks(*x_mm, max(1, int(target.height() / (3 * line)))):
            at = target.bottom() - (t - x_mm[0]) / (x_mm[1] - x_mm[0]) * target.height()
            painter.drawLine(QtCore.QLineF(target.left() - 3, at, target.left(), at))
            painter.drawText(QtCore.QRectF(target.left() - ticks_w, at - line / 2, ticks_w - 4, line),
                             align.AlignRight | align.AlignVCenter, f"{t:g}")
        for t in _ticks(*y_mm, max(1, int(target.width() / (3 * line)))):
            at = target.left() + (t - y_mm[0]) / (y_mm[1] - y_mm[0]) * target.width()
            painter.drawLine(QtCore.QLineF(at, target.bottom(), at, target.bottom() + 3))
            painter.drawText(QtCore.QRectF(at - 30, target.bottom() + 3, 60, line), align.AlignHCenter | align.AlignTop,
                             f"{t:g}")
        painter.drawText(QtCore.QRectF(target.left(), target.bottom() + 3 + line, target.width(), line),
                         align.AlignHCenter | align.AlignTop, "y (mm)")
        painter.save()
        painter.translate(target.left() - ticks_w - line * 0.2, target.center().y())
        painter.rotate(-90)
        painter.drawText(QtCore.QRectF(-target.height() / 2, -line, target.height(), line),
                         align.AlignHCenter | align.AlignBottom, "x (mm)")
        painter.restore()

    @staticmethod
    def _colour_bar(painter, rect, lo: float, hi: float, unit: str) -> None:
        """Lowest on the left; each end's value centred under it (the labels may reach past a narrow map, into
        the margin beside it)."""
        strip = np.ascontiguousarray(CONTOUR_LUT[None, :, :].repeat(4, axis=0))
        image = QtGui.QImage(strip.data, strip.shape[1], strip.shape[0], strip.strides[0],
                             QtGui.QImage.Format.Format_RGB888)
        painter.drawImage(rect, image)
        painter.drawRect(rect)
        line = QtGui.QFontMetricsF(painter.font()).height()
        centred = QtCore.Qt.AlignmentFlag.AlignHCenter | QtCore.Qt.AlignmentFlag.AlignTop
        for at, text in ((rect.left(), f"{lo:.1f}"), (rect.right(), f"{hi:.1f} {unit}")):
            painter.drawText(QtCore.QRectF(at - 60, rect.bottom() + 2, 120, line), centred, text)


def _ticks(lo: float, hi: float, count: int) -> list[float]:
    """Round values within [lo, hi], about ``count`` intervals apart."""
    step = nice_step(hi - lo, count)
    return [k * step for k in range(math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9) + 1)]


def _save_image(image, path: Path) -> None:
    if not image.save(str(path)):
        raise ExportError(f"cannot write {path}: Qt could not save the image there (check the folder exists, "
                          "is writable, and the name ends in .png)")


def render_maps_png(path: str | Path, analysis: SessionAnalysis, px_per_mm: float = 6.0) -> tuple[int, int]:
    """Every level's force and stiffness maps in one image; returns its size in pixels."""
    ensure_gui_application()
    maps = MapPainter(analysis.stitched, analysis.tumours, analysis.session.ground_truth)
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


def _draw_table(painter, left: float, top: float, width: float, rows: list[list[str]]) -> float:
    if not rows:
        return top
    normal = QtGui.QFont(painter.font())
    bold = QtGui.QFont(normal)
    bold.setBold(True)
    line = QtGui.QFontMetricsF(normal).height() * 1.25
    widths, header_lines = table_columns(rows, normal, bold, width)
    flags = QtCore.Qt.AlignmentFlag.AlignLeft | QtCore.Qt.AlignmentFlag.AlignTop
    wrap = int(flags) | int(QtCore.Qt.TextFlag.TextWordWrap)
    y = top
    for r, row in enumerate(rows):
        painter.setFont(bold if r == 0 else normal)
        height = line * (header_lines if r == 0 else 1)
        x = left
        for c, text in enumerate(row):
            painter.drawText(QtCore.QRectF(x, y, widths[c] - TABLE_GAP_PX, height), wrap, text)
            x += widths[c]
        y += height
    painter.setFont(normal)
    return y


TABLE_GAP_PX = 6  # between a column's text and the next column


def table_columns(rows: list[list[str]], normal: QtGui.QFont, bold: QtGui.QFont, width: float
                  ) -> tuple[list[float], int]:
    """(each column's width, the header row's lines) of a table ``width`` wide: each column as wide as its
    widest cell, the header (``rows[0]``, bold) wrapping onto a second line at its spaces where it needs more
    than that, and what is left shared out. Equal columns clipped the report's headers and its model depths
    ("depth, model (m", "2.3 [1.1, 3.")). A table too wide even so is shrunk evenly."""
    body, head = QtGui.QFontMetricsF(normal), QtGui.QFontMetricsF(bold)
    natural = []
    for c in range(len(rows[0])):
        cells = max((body.horizontalAdvance(row[c]) for row in rows[1:]), default=0.0)
        word = max(head.horizontalAdvance(w) for w in rows[0][c].split() or [""])
        natural.append(max(cells, word) + TABLE_GAP_PX)
    total = sum(natural)
    if total > width:
        widths = [w * width / total for w in natural]
    else:
        widths = [w + (width - total) / len(natural) for w in natural]
    header_lines = 2 if any(head.horizontalAdvance(text) > w - TABLE_GAP_PX for text, w in zip(rows[0], widths)) else 1
    return widths, header_lines


def write_report(path: str | Path, analysis: SessionAnalysis) -> None:
    """One page: header, the maps at every level, the tumour table and, for simulated sessions, the
    comparison with the phantom's ground truth. PDF (A4) for a ``.pdf`` name, otherwise a PNG."""
    ensure_gui_application()
    path = Path(path)
    session, stitched, tumours = analysis.session, analysis.stitched, analysis.tumours
    header, table, truth = report_lines(analysis)
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
        tables_h = (len(table) + len(truth) + 5) * line * 1.25  # the headers may take two lines each
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
