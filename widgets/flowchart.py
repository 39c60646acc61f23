"""Where the palpation of the current area stands in the Fig. 4 flowchart, readable at a glance.

From top to bottom: the phase in large coloured letters with what the operator should do now; the ladder
of force levels (one box per level with its F_d: green once recorded, orange while settling, grey still to
come); the settling error as a bar against ε; and the "region done" flag, a large block that turns green.

Everything is derived from the tick rows the loop publishes: during SETTLING at level k, levels 0..k-1 are
recorded (the ramp only moves on after recording), and "region done" means all of them are.
"""

from __future__ import annotations

import math

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from control.config import RampSettings
from hardware.interfaces import Phase
from widgets.glossary import GLOSSARY

# Phase -> (headline, colour, what the operator should do now)
PHASES: dict[Phase, tuple[str, str, str]] = {
    Phase.APPROACH: ("APPROACH", "#8cc0ff", "Position the TSI over the area, then switch S_z to FORCE"),
    Phase.SEEK_CONTACT: ("SEEKING CONTACT", "#ffc37a", "Force control: lowering the TSI onto the tissue"),
    Phase.SETTLING: ("SETTLING", "#ffc37a", "Force control: hold still while the level settles"),
    Phase.RETRACT: ("RETRACTING", "#c8c8c8", "Lifting the TSI off the tissue"),
    Phase.DONE: ("DONE", "#5fd35f", "Switch S_z to POSITION and move to the next area"),
    Phase.HOLD: ("HOLD", "#ff6b6b", "A fault holds the robot: read the banner, clear it when safe"),
}
# what to do next when S_z is already back on POSITION (the controller hands z back when the ramp ends): the
# hint "switch S_z to POSITION" stayed up while POSITION was on
HINTS_IN_POSITION = {Phase.DONE: "S_z is on POSITION: move the TSI to the next area, then switch S_z to FORCE"}
SETTLED_COLOUR = "#5fd35f"
UNSETTLED_COLOUR = "#ffc37a"

_STYLE = """
QLabel { color: #ececec; }
QLabel#phaseLabel { font-size: 24pt; font-weight: bold; }
QLabel#phaseHint { color: #c8c8c8; font-size: 11pt; }
QLabel#levelLabel { font-size: 15pt; font-weight: bold; }
QLabel#rmseLabel { font-size: 13pt; }
QLabel#regionDone { font-size: 18pt; font-weight: bold; border-radius: 6px; padding: 8px;
                    border: 2px solid #4a4a4a; color: #808080; background: #262626; }
QLabel#regionDone[done="true"] { color: white; background: #1f9d3a; border: 3px solid #8ff0a4; }
"""


class LevelLadder(QtWidgets.QWidget):
    """One box per force level of the ramp: recorded (green), current (orange), to come (grey)."""

    RECORDED = QtGui.QColor("#2e9e44")
    CURRENT = QtGui.QColor("#e07b00")
    TO_COME = QtGui.QColor("#3a3a3a")

    def __init__(self, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self.setObjectName("levelLadder")
        self._forces: list[float] = []
        self._recorded = 0
        self._current: int | None = None
        self.setMinimumHeight(30)
        self.setSizePolicy(QtWidgets.QSizePolicy.Policy.Expanding, QtWidgets.QSizePolicy.Policy.Fixed)

    def set_ramp(self, ramp: RampSettings) -> None:
        forces = [ramp.level_force_N(k) for k in range(ramp.n_levels)]
        if forces != self._forces:
            self._forces = forces
            self._recorded = min(self._recorded, len(forces))
            self.update()

    def set_progress(self, recorded: int, current: int | None) -> None:
        """``recorded`` levels done; ``current`` the level being settled (None: none)."""
        recorded = max(0, min(recorded, len(self._forces)))
        if (recorded, current) != (self._recorded, self._current):
            self._recorded, self._current = recorded, current
            self.update()

    def forces(self) -> list[float]:
        """F_d of each level, in N."""
        return list(self._forces)

    def recorded(self) -> int:
        return self._recorded

    def current(self) -> int | None:
        return self._current

    def sizeHint(self) -> QtCore.QSize:
        return QtCore.QSize(300, 34)

    def paintEvent(self, event: QtGui.QPaintEvent) -> None:
        n = len(self._forces)
        if not n:
            return
        painter = QtGui.QPainter(self)
        painter.setRenderHint(QtGui.QPainter.RenderHint.Antialiasing)
        gap = 3.0
        w = (self.width() - gap * (n - 1)) / n
        h = float(self.height())
        font = painter.font()
        font.setPointSizeF(9.5)
        font.setBold(True)
        painter.setFont(font)
        labels = w >= QtGui.QFontMetrics(font).horizontalAdvance("10.5") + 4
        for k, force in enumerate(self._forces):
            if k < self._recorded:
                colour = self.RECORDED
            elif k == self._current:
                colour = self.CURRENT
            else:
                colour = self.TO_COME
            rect = QtCore.QRectF(k * (w + gap), 0.0, w, h)
            painter.setPen(QtCore.Qt.PenStyle.NoPen)
            painter.setBrush(colour)
            painter.drawRoundedRect(rect, 3, 3)
            if labels:
                painter.setPen(QtGui.QColor("white" if colour != self.TO_COME else "#a0a0a0"))
                painter.drawText(rect, QtCore.Qt.AlignmentFlag.AlignCenter, f"{force:g}")
        painter.end()


class RmseGauge(QtWidgets.QWidget):
    """The settling error as a bar on [0, 3 ε] with a mark at ε: green once below it."""

    SPAN_EPS = 3.0

    def __init__(self, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self.setObjectName("rmseGauge")
        self._rmse = math.nan
        self._eps = 0.05
        self.setFixedHeight(14)

    def set_value(self, rmse_N: float, eps_N: float) -> None:
        same_rmse = rmse_N == self._rmse or (math.isnan(rmse_N) and math.isnan(self._rmse))
        if not (same_rmse and eps_N == self._eps):
            self._rmse, self._eps = rmse_N, eps_N
            self.update()

    def paintEvent(self, event: QtGui.QPaintEvent) -> None:
        painter = QtGui.QPainter(self)
        w, h = float(self.width()), float(self.height())
        painter.fillRect(QtCore.QRectF(0, 0, w, h), QtGui.QColor("#2b2b2b"))
        if math.isfinite(self._rmse):
            frac = min(self._rmse / (self.SPAN_EPS * self._eps), 1.0)
            colour = SETTLED_COLOUR if self._rmse < self._eps else UNSETTLED_COLOUR
            painter.fillRect(QtCore.QRectF(0, 0, w * frac, h), QtGui.QColor(colour))
        x = w / self.SPAN_EPS
        painter.setPen(QtGui.QPen(QtGui.QColor("white"), 2))
        painter.drawLine(QtCore.QPointF(x, 0), QtCore.QPointF(x, h))
        painter.end()


class FlowchartPanel(QtWidgets.QWidget):
    """Child objectNames: ``phaseLabel``, ``phaseHint``, ``levelLabel``, ``levelLadder``, ``rmseLabel``,
    ``rmseGauge``, ``regionDone``, ``regionFindings`` (what the last finished area showed)."""

    def __init__(self, ramp: RampSettings, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self.setStyleSheet(_STYLE)
        self._texts: dict[QtWidgets.QLabel, str] = {}
        self._eps_N = ramp.rmse_threshold_N
        self._n_levels = ramp.n_levels
        self._recorded = 0  # levels recorded in the current (or last) area
        self._region_done: bool | None = None

        # every text here wraps: one that did not ("SEEKING CONTACT", "seeking contact at F_min, 7 levels to
        # record") widened the side panel past its view at 1280 x 800 and pushed the FORCE button off the screen
        self._phase = QtWidgets.QLabel("—", objectName="phaseLabel", wordWrap=True, toolTip=GLOSSARY["phase"])
        self._hint = QtWidgets.QLabel("waiting for the controller", objectName="phaseHint", wordWrap=True)
        self._level = QtWidgets.QLabel("", objectName="levelLabel", wordWrap=True)
        self._ladder = LevelLadder()
        self._ladder.set_ramp(ramp)
        self._ladder.setToolTip(GLOSSARY["ladder"])
        self._rmse = QtWidgets.QLabel("", objectName="rmseLabel", toolTip=f"{GLOSSARY['epsilon']}. {GLOSSARY['rmse']}")
        self._gauge = RmseGauge()
        self._gauge.setToolTip(self._rmse.toolTip())
        self._done = QtWidgets.QLabel("region not done", objectName="regionDone", toolTip=GLOSSARY["region_done"])
        self._done.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        self._done.setProperty("done", False)
        self._findings = QtWidgets.QLabel("", objectName="regionFindings", wordWrap=True)
        # the hint wraps over one or two lines: reserve both so the panel below never jumps
        self._hint.setMinimumHeight(2 * QtGui.QFontMetrics(self._hint.font()).height() + 6)

        col = QtWidgets.QVBoxLayout(self)
        col.setContentsMargins(0, 0, 0, 0)
        col.setSpacing(4)
        col.addWidget(self._phase)
        col.addWidget(self._hint)
        col.addSpacing(4)
        col.addWidget(self._level)
        col.addWidget(self._ladder)
        col.addWidget(self._rmse)
        col.addWidget(self._gauge)
        col.addSpacing(8)
        col.addWidget(self._done)
        col.addWidget(self._findings)

    def set_ramp(self, ramp: RampSettings) -> None:
        self._eps_N = ramp.rmse_threshold_N
        self._n_levels = ramp.n_levels
        self._ladder.set_ramp(ramp)

    def show_tick(self, tick: np.ndarray) -> None:
        raw = int(tick["phase"])
        try:
            phase = Phase(raw)
        except ValueError:
            self._set_text(self._phase, f"unknown phase {raw}")
            self._set_text(self._hint, "the controller reported a phase this console does not know")
            return
        headline, colour, hint = PHASES[phase]
        if int(tick["sz"]) == 1:
            hint = HINTS_IN_POSITION.get(phase, hint)
        if self._texts.get(self._phase) != headline:
            self._phase.setStyleSheet(f"color: {colour};")
        self._set_text(self._phase, headline)
        self._set_text(self._hint, hint)

        level, n_levels = int(tick["level"]), int(tick["n_levels"])
        done = bool(tick["region_done"])
        current = None
        if phase == Phase.SEEK_CONTACT:
            self._recorded, current = 0, 0
        elif phase == Phase.SETTLING and level >= 0:
            self._recorded, current = level, level
        elif done:
            self._recorded = n_levels
        self._ladder.set_progress(self._recorded, current)

        if done and n_levels > 0:
            level_text = f"all {n_levels} levels recorded"
        elif phase == Phase.SETTLING and level >= 0 and n_levels > 0:
            level_text = f"level {level + 1} of {n_levels}: F_d {float(tick['force_desired_N']):.2f} N"
        elif phase == Phase.SEEK_CONTACT and n_levels > 0:
            level_text = f"seeking contact at F_min, {n_levels} levels to record"
        elif self._recorded and phase in (Phase.RETRACT, Phase.APPROACH, Phase.HOLD):
            level_text = f"{self._recorded} of {n_levels} recorded, not finished"
        else:
            level_text = ""
        self._set_text(self._level, level_text)

        rmse = float(tick["rmse_N"])
        if phase == Phase.SETTLING and math.isfinite(rmse):
            settled = rmse < self._eps_N
            text = f"RMSE {rmse:.3f} N {'<' if settled else '≥'} ε {self._eps_N:.3f} N"
            colour = SETTLED_COLOUR if settled else UNSETTLED_COLOUR
            if self._texts.get(self._rmse) != text:
                self._rmse.setStyleSheet(f"color: {colour};")
            self._set_text(self._rmse, text)
            self._gauge.set_value(rmse, self._eps_N)
        else:
            self._set_text(self._rmse, f"ε {self._eps_N:.3f} N")
            self._gauge.set_value(math.nan, self._eps_N)
            if self._rmse.styleSheet():
                self._rmse.setStyleSheet("")
        self._show_region_done(done)

    def _show_region_done(self, done: bool) -> None:
        if done == self._region_done:
            return
        self._region_done = done
        label = self._done
        # one line: the phase's hint above says what to do next, and at 1366 x 768 a second line pushed F_ts out
        label.setText("REGION DONE" if done else "region not done")
        label.setProperty("done", done)
        label.style().unpolish(label)
        label.style().polish(label)

    def show_findings(self, text: str) -> None:
        """What the area just finished showed (position, first level, depth), or that it showed nothing."""
        self._set_text(self._findings, text)

    def _set_text(self, label: QtWidgets.QLabel, text: str) -> None:
        if self._texts.get(label) != text:
            self._texts[label] = text
            label.setText(text)
