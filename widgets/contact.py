"""Contact area, centre of pressure and peak pressure of one tactile frame, and the panel that shows them.

An element is in contact when its pressure reaches the loop's confirm threshold
(``ContactSettings.confirm_threshold_pa``), the level at which the Fig. 4 flowchart takes a touch for real
rather than noise; the lower onset threshold is crossed by sensor noise and creep while the TSI hangs in the
air, and a centre of pressure drawn there would point at nothing. The centre of pressure is the
pressure-weighted mean of the contact elements' centres, on the TSI face (x along its 4-element axis, y
along its 15-element axis, from its centre) and, given the TSI position, in the tissue frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from PySide6 import QtCore, QtWidgets

from hardware.interfaces import TactileConstraints
from widgets.glossary import GLOSSARY


@dataclass(frozen=True)
class ContactMetrics:
    elements: int  # elements in contact
    area_m2: float
    centre_m: tuple[float, float] | None  # centre of pressure (x, y) on the TSI face; None without contact
    peak_pa: float  # highest element pressure (NaN for an empty frame)
    peak_element: tuple[int, int] | None  # (row, column) of the peak


def contact_metrics(pressure_pa: np.ndarray, threshold_pa: float, sensor: TactileConstraints) -> ContactMetrics:
    p = np.asarray(pressure_pa, dtype=float)
    if p.shape != sensor.shape:
        raise ValueError(f"contact metrics: expected a {sensor.shape} pressure array, got shape {p.shape}")
    finite = np.isfinite(p)
    if not finite.any():
        return ContactMetrics(0, 0.0, None, math.nan, None)
    masked = np.where(finite, p, -np.inf)
    peak = np.unravel_index(int(np.argmax(masked)), p.shape)
    contact = finite & (p >= threshold_pa)
    n = int(contact.sum())
    centre = None
    if n:
        w = p[contact]
        offsets = sensor.element_offsets_m()[contact]  # (n, 2): x, y
        cx, cy = (offsets * w[:, None]).sum(axis=0) / w.sum()
        centre = (float(cx), float(cy))
    return ContactMetrics(n, n * sensor.element_area_m2, centre, float(p[peak]), (int(peak[0]), int(peak[1])))


class ContactPanel(QtWidgets.QWidget):
    """Three compact rows, caption left, value right. Child objectNames: ``contactArea``,
    ``centreOfPressure``, ``peakPressure``."""

    def __init__(self, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self._texts: dict[QtWidgets.QLabel, str] = {}
        grid = QtWidgets.QGridLayout(self)
        grid.setContentsMargins(0, 0, 0, 0)
        grid.setVerticalSpacing(2)
        grid.setColumnStretch(1, 1)
        self._area = self._row(grid, 0, "Contact area", "contactArea", GLOSSARY["contact_area"])
        self._peak = self._row(grid, 1, "Peak pressure", "peakPressure", GLOSSARY["peak_pressure"])
        self._centre = self._row(grid, 2, "Centre of pressure", "centreOfPressure", GLOSSARY["centre_of_pressure"],
                                 below=True)

    @staticmethod
    def _row(grid: QtWidgets.QGridLayout, row: int, caption: str, name: str, meaning: str, below: bool = False
             ) -> QtWidgets.QLabel:
        cap = QtWidgets.QLabel(caption, toolTip=meaning)
        cap.setProperty("class", "caption")
        cap.setAlignment(QtCore.Qt.AlignmentFlag.AlignLeft | QtCore.Qt.AlignmentFlag.AlignTop)
        value = QtWidgets.QLabel("—", objectName=name, toolTip=meaning)
        value.setProperty("class", "metric")
        value.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        value.setAlignment(QtCore.Qt.AlignmentFlag.AlignRight | QtCore.Qt.AlignmentFlag.AlignTop)
        grid.addWidget(cap, row, 0)
        if below:  # two lines of figures: under the caption, the panel's full width
            grid.addWidget(value, row + 1, 0, 1, 2)
        else:
            grid.addWidget(value, row, 1)
        return value

    def show_metrics(self, metrics: ContactMetrics | None, tsi_position_m=None) -> None:
        """``None``: no frame yet. ``tsi_position_m`` (x, y, z) adds the centre in the tissue frame."""
        if metrics is None:
            texts = ("—", "—", "—")
        else:
            area = f"{metrics.area_m2 * 1e6:.0f} mm²  ({metrics.elements} el.)"
            if metrics.centre_m is None:
                centre = "no contact"
            else:
                cx, cy = metrics.centre_m
                centre = f"on the TSI   x {cx * 1e3:+.1f}   y {cy * 1e3:+.1f} mm"
                if tsi_position_m is not None:
                    centre += (f"\non the tissue   x {(tsi_position_m[0] + cx) * 1e3:.1f}   "
                               f"y {(tsi_position_m[1] + cy) * 1e3:.1f} mm")
            peak = f"{metrics.peak_pa / 1e3:.1f} kPa" if math.isfinite(metrics.peak_pa) else "—"
            texts = (area, centre, peak)
        for label, text in zip((self._area, self._centre, self._peak), texts):
            if self._texts.get(label) != text:
                self._texts[label] = text
                label.setText(text)
