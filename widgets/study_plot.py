"""The validation study's picture: sensitivity by depth band, and the FROC (sensitivity against false
positives per phantom), for the stiffness map and the force map side by side."""

from __future__ import annotations

from pathlib import Path

from PySide6 import QtCore, QtGui

from widgets.map_painting import ensure_gui_application

_COLOURS = {"stiffness": QtGui.QColor("#1c71d8"), "force": QtGui.QColor("#e66100")}
_SIZE = (1200, 520)


def render_study_png(path: str | Path, doc: dict) -> None:
    """Paint ``doc`` (:func:`app.study.study_document`) into a PNG at ``path``, a row per world the study
    palpated in (ideal, and realistic when it ran both); raises OSError if it cannot be written."""
    ensure_gui_application()
    worlds = [("", doc["maps"])]
    if doc.get("realistic_maps"):
        worlds = [("ideal world: ", doc["maps"]), ("realistic world: ", doc["realistic_maps"])]
    row_height = _SIZE[1] - 40
    image = QtGui.QImage(_SIZE[0], 40 + row_height * len(worlds), QtGui.QImage.Format.Format_RGB32)
    image.fill(QtGui.QColor("white"))
    painter = QtGui.QPainter(image)
    painter.setRenderHint(QtGui.QPainter.RenderHint.Antialiasing)
    font = QtGui.QFont("DejaVu Sans")
    font.setPixelSize(14)
    painter.setFont(font)
    try:
        half = _SIZE[0] / 2
        origin = (f"re-analysed from {doc['reanalysed']}" if doc.get("reanalysed") else f"seed {doc.get('seed')}")
        for row, (world, maps) in enumerate(worlds):
            top = row * row_height
            _sensitivity_by_depth(painter, QtCore.QRectF(70, top + 50, half - 110, row_height - 90), maps, world)
            _froc(painter, QtCore.QRectF(half + 70, top + 50, half - 110, row_height - 90), maps, world)
            painter.setPen(QtGui.QColor("black"))
            stiffness = maps["stiffness"]
            title = (f"Validation study, {world}{stiffness['phantoms']} phantoms, {stiffness['tumours']} palpated "
                     f"tumours, {origin}")
            painter.drawText(QtCore.QPointF(20, top + 24), title)
        x = 20.0
        for source, colour in _COLOURS.items():
            painter.fillRect(QtCore.QRectF(x, image.height() - 30, 14, 14), colour)
            painter.drawText(QtCore.QPointF(x + 20, image.height() - 18), f"{source} map")
            x += 160
    finally:
        painter.end()
    if not image.save(str(path)):
        raise OSError(f"Qt could not save the image at {path}")


def _axes(painter, rect: QtCore.QRectF, title: str, x_label: str, y_label: str) -> None:
    painter.setPen(QtGui.QPen(QtGui.QColor("black"), 1))
    painter.drawRect(rect)
    painter.drawText(QtCore.QPointF(rect.left(), rect.top() - 10), title)
    painter.drawText(QtCore.QRectF(rect.left(), rect.bottom() + 24, rect.width(), 20),
                     QtCore.Qt.AlignmentFlag.AlignHCenter, x_label)
    painter.save()
    painter.translate(rect.left() - 48, rect.center().y())
    painter.rotate(-90)
    painter.drawText(QtCore.QRectF(-rect.height() / 2, -10, rect.height(), 20),
                     QtCore.Qt.AlignmentFlag.AlignHCenter, y_label)
    painter.restore()
    grey = QtGui.QPen(QtGui.QColor("#c0c0c0"), 1, QtCore.Qt.PenStyle.DotLine)
    for pct in (0, 25, 50, 75, 100):
        y = rect.bottom() - pct / 100 * rect.height()
        painter.setPen(grey)
        painter.drawLine(QtCore.QPointF(rect.left(), y), QtCore.QPointF(rect.right(), y))
        painter.setPen(QtGui.QColor("black"))
        painter.drawText(QtCore.QRectF(rect.left() - 40, y - 9, 34, 18), QtCore.Qt.AlignmentFlag.AlignRight, f"{pct}")


def _sensitivity_by_depth(painter, rect: QtCore.QRectF, maps: dict, world: str = "") -> None:
    _axes(painter, rect, f"{world.capitalize()}sensitivity by depth (surface to the tumour's top)", "depth band (mm)",
          "tumours found (%)")
    bands = list(maps["stiffness"]["by_depth"])
    slot = rect.width() / max(1, len(bands))
    bar = slot / 3
    for i, band in enumerate(bands):
        for j, (source, colour) in enumerate(_COLOURS.items()):
            b = maps[source]["by_depth"][band]
            if b["sensitivity_pct"] is None:
                continue
            h = b["sensitivity_pct"] / 100 * rect.height()
            painter.fillRect(QtCore.QRectF(rect.left() + i * slot + bar * (0.5 + j), rect.bottom() - h, bar, h),
                             colour)
        painter.setPen(QtGui.QColor("black"))
        n = maps["stiffness"]["by_depth"][band]["tumours"]
        painter.drawText(QtCore.QRectF(rect.left() + i * slot, rect.bottom() + 2, slot, 20),
                         QtCore.Qt.AlignmentFlag.AlignHCenter, f"{band.removesuffix('mm')} (n={n})")


def _froc(painter, rect: QtCore.QRectF, maps: dict, world: str = "") -> None:
    points = {s: [p for p in maps[s]["froc"] if p["sensitivity_pct"] is not None
                  and p["false_positives_per_phantom"] is not None] for s in _COLOURS}
    x_max = max([1.0] + [p["false_positives_per_phantom"] for ps in points.values() for p in ps]) * 1.1
    _axes(painter, rect, f"{world.capitalize()}FROC (stricter scores to the left)", "false positives per phantom",
          "tumours found (%)")
    for k in range(5):
        value = x_max * k / 4
        x = rect.left() + k / 4 * rect.width()
        painter.drawText(QtCore.QRectF(x - 30, rect.bottom() + 2, 60, 20), QtCore.Qt.AlignmentFlag.AlignHCenter,
                         f"{value:.2g}")
    for source, colour in _COLOURS.items():
        poly = QtGui.QPolygonF([QtCore.QPointF(rect.left() + p["false_positives_per_phantom"] / x_max * rect.width(),
                                               rect.bottom() - p["sensitivity_pct"] / 100 * rect.height())
                                for p in sorted(points[source], key=lambda p: p["false_positives_per_phantom"])])
        painter.setPen(QtGui.QPen(colour, 2))
        painter.drawPolyline(poly)
        for point in poly:
            painter.drawEllipse(point, 3, 3)
