"""Moving the probe without a master device: the jog pad, and the autopilot's controls.

Jog directions follow the live maps: the TSI's long axis (y) runs across the screen and x up it, so the
pad's left/right buttons move along y, its up/down buttons along x, and two more raise and lower the TSI
(z). The keyboard does the same with the arrow keys and Page Up / Page Down; the window owns those
shortcuts (so they work while this panel is hidden behind another tab) and calls :meth:`JogPanel.step`.
A press moves one step; holding a button or key repeats the step no faster than the loop's jog speed
covers it, so the probe stops within one step of letting go instead of working off a queue of presses.
"""

from __future__ import annotations

import math
import time

from PySide6 import QtCore, QtWidgets

STEPS_MM = (0.2, 0.5, 1.0, 2.0, 5.0)
DEFAULT_STEP_MM = 1.0

# (objectName, label, unit direction in the tissue frame)
DIRECTIONS: dict[str, tuple[str, tuple[int, int, int]]] = {
    "jogXPlus": ("▲  +x", (1, 0, 0)),
    "jogXMinus": ("▼  −x", (-1, 0, 0)),
    "jogYMinus": ("◀  −y", (0, -1, 0)),
    "jogYPlus": ("+y  ▶", (0, 1, 0)),
    "jogZPlus": ("▲  +z", (0, 0, 1)),
    "jogZMinus": ("▼  −z", (0, 0, -1)),
}

_STYLE = """
QPushButton { color: #ececec; background: #3a3a3a; border: 1px solid #5a5a5a; border-radius: 4px; padding: 4px 8px; }
QPushButton:pressed { background: #1f6fd1; }
QPushButton:disabled { color: #6a6a6a; background: #2a2a2a; border-color: #3a3a3a; }
QSpinBox, QComboBox { color: #ececec; background: #2a2a2a; border: 1px solid #5a5a5a; border-radius: 3px;
                      padding: 2px 6px; }
QSpinBox:disabled, QComboBox:disabled { color: #6a6a6a; border-color: #3a3a3a; }
QPushButton[class="jog"] { font-size: 12pt; font-weight: bold; min-width: 64px; min-height: 32px; }
QLabel#jogPosition { font-family: monospace; font-size: 11pt; }
QLabel#jogStepCaption { color: #d8d8d8; }
QLabel#jogStepCaption:disabled { color: #9a9a9a; }
QLabel#jogReason, QLabel#autopilotStatus { color: #ffc37a; }
QLabel#autopilotStatus[state="running"] { color: #8cc0ff; font-weight: bold; }
QLabel#autopilotStatus[state="finished"] { color: #6ee07a; font-weight: bold; }
QPushButton#autopilotStart { font-weight: bold; }
QPushButton#autopilotStart:enabled { background: #1f6fd1; border-color: #8cc0ff; color: white; }
"""


class JogPanel(QtWidgets.QWidget):
    """Signal ``jog_requested(dx, dy, dz)`` in m. Child objectNames: the keys of :data:`DIRECTIONS`,
    ``jogStep`` (step size combo), ``jogPosition``, ``jogReason`` (why jogging is unavailable)."""

    jog_requested = QtCore.Signal(float, float, float)

    def __init__(self, jog_speed_m_s: float, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        if not (math.isfinite(jog_speed_m_s) and jog_speed_m_s > 0):
            raise ValueError(f"jog speed must be > 0, got {jog_speed_m_s!r}")
        self.setStyleSheet(_STYLE)
        self._speed = jog_speed_m_s
        self._last_step: dict[str, float] = {}
        self._reason: str | None = "waiting for the controller"
        self._buttons: dict[str, QtWidgets.QPushButton] = {}

        self._step = QtWidgets.QComboBox(objectName="jogStep")
        for mm in STEPS_MM:
            self._step.addItem(f"{mm:g} mm", mm)
        self._step.setCurrentIndex(STEPS_MM.index(DEFAULT_STEP_MM))
        self._step.currentIndexChanged.connect(self._update_repeat)
        self._step.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)  # arrow keys must keep jogging

        pad = QtWidgets.QGridLayout()
        pad.setSpacing(4)
        places = {"jogXPlus": (0, 1), "jogYMinus": (1, 0), "jogYPlus": (1, 2), "jogXMinus": (2, 1),
                  "jogZPlus": (0, 4), "jogZMinus": (2, 4)}
        for name, (label, _) in DIRECTIONS.items():
            button = QtWidgets.QPushButton(label, objectName=name)
            button.setProperty("class", "jog")
            button.setAutoRepeat(True)
            button.setAutoRepeatDelay(350)
            button.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)
            button.clicked.connect(lambda _=False, n=name: self.step(n))
            self._buttons[name] = button
            pad.addWidget(button, *places[name])
        pad.setColumnMinimumWidth(3, 0)
        pad.addItem(QtWidgets.QSpacerItem(16, 1), 1, 3)
        for name, tip in (("jogZPlus", "raise the TSI (Page Up)"), ("jogZMinus", "lower the TSI (Page Down)")):
            self._buttons[name].setToolTip(tip)
        keys = QtWidgets.QLabel("keys: ← → along y · ↑ ↓ along x · Page Up / Down raise / lower")
        keys.setStyleSheet("color: #a0a0a0;")
        keys.setWordWrap(True)

        self._position = QtWidgets.QLabel("TSI  —", objectName="jogPosition")
        self._reason_label = QtWidgets.QLabel("", objectName="jogReason", wordWrap=True)
        step_row = QtWidgets.QHBoxLayout()
        step_row.addWidget(QtWidgets.QLabel("Step", objectName="jogStepCaption"))
        step_row.addWidget(self._step)
        step_row.addStretch(1)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        layout.addLayout(step_row)
        layout.addLayout(pad)
        layout.addWidget(keys)
        layout.addWidget(self._position)
        layout.addWidget(self._reason_label)
        self._update_repeat()
        self.set_unavailable(self._reason)

    def step_m(self) -> float:
        return float(self._step.currentData()) * 1e-3

    def set_step_mm(self, mm: float) -> None:
        index = self._step.findData(mm)
        if index < 0:
            raise ValueError(f"jog step {mm!r} mm is not one of {STEPS_MM}")
        self._step.setCurrentIndex(index)

    def available(self) -> bool:
        return self._reason is None

    def set_unavailable(self, reason: str | None) -> None:
        """``None``: jogging is possible; otherwise the reason it is not, shown under the pad."""
        if reason == self._reason and self._reason_label.text() == (reason or ""):
            return
        self._reason = reason
        for button in self._buttons.values():
            button.setEnabled(reason is None)
        self._reason_label.setText(reason or "")
        self._reason_label.setVisible(reason is not None)

    def set_position(self, x_slave_m) -> None:
        text = "TSI  x {:6.1f}  y {:6.1f}  z {:6.1f} mm".format(*(float(v) * 1e3 for v in x_slave_m))
        if self._position.text() != text:
            self._position.setText(text)

    def step(self, name: str) -> bool:
        """One step in direction ``name`` unless jogging is unavailable or the last one is still under way."""
        if self._reason is not None:
            return False
        now = time.monotonic()
        # a repeat may only ask for the next step once the loop can have covered the previous one
        if now - self._last_step.get(name, -math.inf) < 0.9 * self.step_m() / self._speed:
            return False
        self._last_step[name] = now
        unit = DIRECTIONS[name][1]
        d = self.step_m()
        self.jog_requested.emit(unit[0] * d, unit[1] * d, unit[2] * d)
        return True

    def _update_repeat(self) -> None:
        interval = max(30, round(1000.0 * self.step_m() / self._speed))
        for button in self._buttons.values():
            button.setAutoRepeatInterval(interval)


class AutopilotPanel(QtWidgets.QWidget):
    """Signals ``start_requested(first_area: int)`` (0-based) and ``stop_requested()``. Child objectNames:
    ``autopilotStart``, ``autopilotStop``, ``autopilotFirst`` (1-based area number), ``autopilotStatus``."""

    start_requested = QtCore.Signal(int)
    stop_requested = QtCore.Signal()

    def __init__(self, n_areas: int, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self.setStyleSheet(_STYLE)
        self._state = ""
        self._start = QtWidgets.QPushButton("Start autopilot", objectName="autopilotStart")
        self._start.setToolTip("Palpate the phantom's areas in turn: raise, move above the area, lower, "
                               "switch S_z to force, wait for region done, and on to the next")
        self._stop = QtWidgets.QPushButton("Stop", objectName="autopilotStop")
        self._first = QtWidgets.QSpinBox(objectName="autopilotFirst")
        self._first.setRange(1, max(1, n_areas))
        self._first.setPrefix("from area ")
        self._first.setSuffix(f" of {n_areas}")
        self._status = QtWidgets.QLabel("", objectName="autopilotStatus", wordWrap=True)
        for button in (self._start, self._stop):
            button.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)
        self._start.clicked.connect(lambda: self.start_requested.emit(self._first.value() - 1))
        self._stop.clicked.connect(self.stop_requested)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self._start, 2)
        row.addWidget(self._stop, 1)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        layout.addLayout(row)
        layout.addWidget(self._first)
        layout.addWidget(self._status)
        self.show_state("unavailable", "no plan", can_start=False)

    def first_area(self) -> int:
        return self._first.value() - 1

    def set_first_area(self, index: int) -> None:
        self._first.setValue(index + 1)

    def show_state(self, state: str, message: str, *, can_start: bool) -> None:
        """``state``: idle / running / finished / stopped / unavailable; ``message`` is shown as is."""
        running = state == "running"
        self._start.setEnabled(can_start and not running)
        self._first.setEnabled(can_start and not running)
        self._stop.setEnabled(running)
        text = f"Autopilot {state}: {message}" if message else f"Autopilot {state}"
        if text != self._status.text():
            self._status.setText(text)
        if state != self._state:
            self._state = state
            self._status.setProperty("state", state)
            self._status.style().unpolish(self._status)
            self._status.style().polish(self._status)
