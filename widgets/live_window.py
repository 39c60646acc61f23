"""The minimal live window: what the operator glances at between movements.

Left, the live pressure and stiffness maps of the TSI. Right, from top to bottom in the order of the
Fig. 4 flowchart: the S_z switch, the phase with its level and settling error, the "region done" flag, the
forces and the indentation, and the emergency stop. A red banner across the top carries any fault; the
status bar carries the loop's timing health and transient messages (refused commands, timeouts).

The window only talks to a controller object with ``send(command)`` and a ``snapshot(object)`` signal
delivering :class:`control.telemetry.LiveSnapshot` at display rate; it never touches hardware.
"""

from __future__ import annotations

import math

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from control.config import RampSettings
from control.messages import (ClearFault, CommandRefused, EStop, FaultCleared, FaultKind, FaultRaised,
                              LevelTimedOut, Notice, Phase, RegionAborted, SetSz)
from control.telemetry import LiveSnapshot, LoopHealth
from hardware.interfaces import TactileConstraints
from widgets.sz_switch import SzSwitch
from widgets.tactile_map import TactileMapWidget

STATUS_MESSAGE_MS = 8000
# Following colour ranges start at [0, floor] (see tactile_map.auto_levels). Pressure: uniform contact at
# F_max fills two thirds of the scale, so at low levels the map stays blue and a harder spot still has
# colours to climb to (the paper's figures: the tumour turns dark red as the force rises). Stiffness: soft
# tissue (1-50 kPa) reads blue to cyan, tumour-like stiffness (>= ~100 kPa) red.
PRESSURE_FLOOR_FACTOR = 1.5
STIFFNESS_FLOOR_PA = 100e3

# Phase -> (headline, colour, what the operator should do now)
_PHASES: dict[Phase, tuple[str, str, str]] = {
    Phase.APPROACH: ("APPROACH", "#8cc0ff", "Position the TSI over the area, then switch S_z to FORCE"),
    Phase.SEEK_CONTACT: ("SEEKING CONTACT", "#ffc37a", "Force control: lowering the TSI onto the tissue"),
    Phase.SETTLING: ("SETTLING", "#ffc37a", "Force control: hold still while the level settles"),
    Phase.RETRACT: ("RETRACTING", "#c8c8c8", "Lifting the TSI off the tissue"),
    Phase.DONE: ("DONE", "#5fd35f", "Switch S_z to POSITION and move to the next area"),
    Phase.HOLD: ("HOLD", "#ff6b6b", "A fault holds the robot: read the banner, clear it when safe"),
}

# Styled per panel, not on the window: a window-wide style sheet would stop the dark palette from reaching
# the maps, whose plots follow the Qt palette.
_PANEL_STYLE = """
QLabel { color: #ececec; }
QLabel#phaseLabel { font-size: 22pt; font-weight: bold; }
QLabel#phaseHint { color: #c8c8c8; }
QLabel#levelLabel, QLabel#rmseLabel { font-size: 14pt; }
QLabel[class="caption"] { color: #b0b0b0; font-size: 12pt; }
QLabel[class="readout"] { font-size: 22pt; font-weight: bold; color: #f4f4f4; }
QLabel#regionDone { font-size: 18pt; font-weight: bold; border-radius: 6px; padding: 10px;
                    border: 2px solid #4a4a4a; color: #707070; background: #262626; }
QLabel#regionDone[done="true"] { color: white; background: #1f9d3a; border-color: #8ff0a4; }
QPushButton#estopButton { font-size: 20pt; font-weight: bold; color: white; background: #c01c28;
                          border: 3px solid #ff8a8a; border-radius: 8px; padding: 14px; }
QPushButton#estopButton:pressed { background: #8a0f18; }
"""
_BANNER_STYLE = """
QFrame#faultBanner { background: #c01c28; border-radius: 4px; }
QLabel#faultText { color: white; font-size: 15pt; font-weight: bold; }
QPushButton#clearFault { font-size: 12pt; padding: 6px 12px; }
"""
_HEALTH_STYLE = """
QLabel#loopHealth { color: #c8c8c8; }
QLabel#loopHealth[degraded="true"] { color: #ffc37a; font-weight: bold; }
"""


def _fmt(value: float, unit: str, decimals: int = 2, scale: float = 1.0) -> str:
    v = float(value)
    return f"{v * scale:.{decimals}f} {unit}" if math.isfinite(v) else "—"


def _dark_palette() -> QtGui.QPalette:
    palette = QtGui.QPalette()
    role, group = QtGui.QPalette.ColorRole, QtGui.QPalette.ColorGroup
    for r, colour in ((role.Window, "#1e1e1e"), (role.WindowText, "#ececec"), (role.Base, "#2a2a2a"),
                      (role.AlternateBase, "#323232"), (role.Text, "#ececec"), (role.Button, "#3a3a3a"),
                      (role.ButtonText, "#ececec"), (role.ToolTipBase, "#ffffe0"), (role.ToolTipText, "#000000"),
                      (role.Highlight, "#1f6fd1"), (role.HighlightedText, "#ffffff")):
        palette.setColor(r, QtGui.QColor(colour))
    for r in (role.WindowText, role.Text, role.ButtonText):
        palette.setColor(group.Disabled, r, QtGui.QColor("#7a7a7a"))
    return palette


class LiveWindow(QtWidgets.QMainWindow):
    """Live maps, S_z switch, phase, region-done flag, forces, indentation, e-stop and faults.

    ``controller`` needs ``send(command)`` and a ``snapshot`` signal carrying ``LiveSnapshot``. Child
    objectNames: ``pressureMap``, ``stiffnessMap``, ``szSwitch``, ``phaseLabel``, ``phaseHint``,
    ``levelLabel``, ``rmseLabel``, ``regionDone``, ``forceDesired``, ``forceMeasured``, ``indentation``,
    ``estopButton``, ``faultBanner``, ``faultText``, ``clearFault``, ``loopHealth``.
    """

    def __init__(self, controller, *, ramp: RampSettings | None = None, sensor: TactileConstraints | None = None,
                 parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self._controller = controller
        self._sensor = sensor or TactileConstraints()
        ramp = ramp or RampSettings()
        self._eps_N = ramp.rmse_threshold_N
        self._texts: dict[QtWidgets.QLabel, str] = {}
        self._frame_seq: int | None = None
        self._fault_messages: dict[int, str] = {}
        self._fault_shown: int | None = None
        self._region_done: bool | None = None
        self._health_degraded: bool | None = None

        self.setWindowTitle("Palpation Console — live")
        self.setPalette(_dark_palette())
        self.setAutoFillBackground(True)

        pitch_m = self._sensor.pitch_m
        self._pressure = TactileMapWidget("Pressure", pitch_m=pitch_m, auto_floor_pa=self._pressure_floor_pa(ramp),
                                          no_data_text="no sensor frame yet")
        self._pressure.setObjectName("pressureMap")
        self._stiffness = TactileMapWidget("Stiffness (Eq. 1)", pitch_m=pitch_m, auto_floor_pa=STIFFNESS_FLOOR_PA,
                                           no_data_text="no contact")
        self._stiffness.setObjectName("stiffnessMap")
        maps = QtWidgets.QVBoxLayout()
        maps.addWidget(self._pressure, 1)
        maps.addWidget(self._stiffness, 1)

        central = QtWidgets.QWidget()
        outer = QtWidgets.QVBoxLayout(central)
        outer.addWidget(self._build_fault_banner())
        body = QtWidgets.QHBoxLayout()
        body.addLayout(maps, 1)
        body.addWidget(self._build_side_panel())
        outer.addLayout(body, 1)
        self.setCentralWidget(central)

        self._health = QtWidgets.QLabel("loop: waiting for the controller's first report", objectName="loopHealth")
        self._health.setStyleSheet(_HEALTH_STYLE)
        self.statusBar().addPermanentWidget(self._health)

        # Window context: an application-wide Esc would become ambiguous (and fire nowhere) as soon as a
        # second window registers the same key.
        estop = QtGui.QShortcut(QtGui.QKeySequence(QtCore.Qt.Key.Key_Escape), self)
        estop.setContext(QtCore.Qt.ShortcutContext.WindowShortcut)
        estop.activated.connect(self._estop)

        controller.snapshot.connect(self.show_snapshot)

    # ---- construction --------------------------------------------------------------------------------

    def _build_fault_banner(self) -> QtWidgets.QFrame:
        self._fault_banner = QtWidgets.QFrame(objectName="faultBanner")
        self._fault_banner.setStyleSheet(_BANNER_STYLE)
        self._fault_text = QtWidgets.QLabel("", objectName="faultText", wordWrap=True)
        clear = QtWidgets.QPushButton("Clear fault", objectName="clearFault")
        clear.setToolTip("Release the hold once the cause is gone")
        clear.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)  # a deliberate click, never a stray Space
        clear.clicked.connect(lambda: self._controller.send(ClearFault()))
        row = QtWidgets.QHBoxLayout(self._fault_banner)
        row.addWidget(self._fault_text, 1)
        row.addWidget(clear)
        self._fault_banner.hide()
        return self._fault_banner

    def _build_side_panel(self) -> QtWidgets.QWidget:
        panel = QtWidgets.QWidget(objectName="sidePanel")
        panel.setStyleSheet(_PANEL_STYLE)
        panel.setFixedWidth(340)
        col = QtWidgets.QVBoxLayout(panel)
        col.setContentsMargins(8, 0, 0, 0)

        self._sz = SzSwitch()
        self._sz.toggled.connect(lambda position_control: self._controller.send(SetSz(position_control)))
        col.addWidget(self._sz)
        col.addSpacing(14)

        self._phase = QtWidgets.QLabel("—", objectName="phaseLabel")
        self._phase_hint = QtWidgets.QLabel("waiting for the controller", objectName="phaseHint", wordWrap=True)
        self._level = QtWidgets.QLabel("", objectName="levelLabel")
        self._rmse = QtWidgets.QLabel("", objectName="rmseLabel")
        for w in (self._phase, self._phase_hint, self._level, self._rmse):
            col.addWidget(w)
        col.addSpacing(10)

        self._region_done_label = QtWidgets.QLabel("region not done", objectName="regionDone")
        self._region_done_label.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        col.addWidget(self._region_done_label)
        col.addSpacing(10)

        grid = QtWidgets.QGridLayout()
        self._force_desired = self._readout(grid, 0, "F_d (desired)", "forceDesired")
        self._force_measured = self._readout(grid, 1, "F_ts (measured)", "forceMeasured")
        self._indentation = self._readout(grid, 2, "TSI indentation", "indentation")
        col.addLayout(grid)
        col.addStretch(1)

        estop = QtWidgets.QPushButton("STOP   (Esc)", objectName="estopButton")
        estop.setToolTip("Emergency stop: hold the robot where it is")
        estop.clicked.connect(self._estop)
        col.addWidget(estop)
        return panel

    @staticmethod
    def _readout(grid: QtWidgets.QGridLayout, row: int, caption: str, name: str) -> QtWidgets.QLabel:
        cap = QtWidgets.QLabel(caption)
        cap.setProperty("class", "caption")
        value = QtWidgets.QLabel("—", objectName=name)
        value.setProperty("class", "readout")
        value.setAlignment(QtCore.Qt.AlignmentFlag.AlignRight | QtCore.Qt.AlignmentFlag.AlignVCenter)
        grid.addWidget(cap, row, 0)
        grid.addWidget(value, row, 1)
        return value

    # ---- public API ----------------------------------------------------------------------------------

    def set_ramp(self, ramp: RampSettings) -> None:
        """The ramp now in force: eps for the RMSE readout, F_max for the pressure map's colour range."""
        self._eps_N = ramp.rmse_threshold_N
        self._pressure.set_auto_floor_pa(self._pressure_floor_pa(ramp))

    @QtCore.Slot(object)
    def show_snapshot(self, snapshot: LiveSnapshot) -> None:
        """Update every view from one snapshot; only what changed is redrawn (called at ~60 Hz)."""
        for event in snapshot.events:
            self._handle_event(event)
        tick = snapshot.tick
        self._show_phase(tick)
        self._sz.set_state(int(tick["sz"]) == 1)
        self._show_region_done(bool(tick["region_done"]))
        self._set_text(self._force_desired, _fmt(tick["force_desired_N"], "N"))
        self._set_text(self._force_measured, _fmt(tick["force_measured_N"], "N"))
        self._set_text(self._indentation, _fmt(tick["indentation_m"], "mm", decimals=1, scale=1e3))
        self._show_fault(int(tick["fault"]))
        if snapshot.health is not None:
            self._show_health(snapshot.health)
        frame = snapshot.frame
        if frame is not None and int(frame["sensor_seq"]) != self._frame_seq:
            self._frame_seq = int(frame["sensor_seq"])
            self._pressure.set_data(frame["pressure_pa"])
            self._stiffness.set_data(frame["stiffness_pa"])

    # ---- internals -----------------------------------------------------------------------------------

    def _pressure_floor_pa(self, ramp: RampSettings) -> float:
        face_m2 = self._sensor.rows * self._sensor.cols * self._sensor.element_area_m2
        return PRESSURE_FLOOR_FACTOR * ramp.force_max_N / face_m2

    def _estop(self) -> None:
        self._controller.send(EStop())

    def _set_text(self, label: QtWidgets.QLabel, text: str) -> None:
        if self._texts.get(label) != text:
            self._texts[label] = text
            label.setText(text)

    def _handle_event(self, event) -> None:
        if isinstance(event, FaultRaised):
            self._fault_messages[int(event.kind)] = event.message
            self._fault_shown = None  # re-render the banner with the new text
        elif isinstance(event, FaultCleared):
            self._fault_messages.pop(int(event.kind), None)
        elif isinstance(event, CommandRefused):
            self.statusBar().showMessage(f"{event.command} refused: {event.reason}", STATUS_MESSAGE_MS)
        elif isinstance(event, LevelTimedOut):
            self.statusBar().showMessage(event.message, STATUS_MESSAGE_MS)
        elif isinstance(event, RegionAborted):
            self.statusBar().showMessage(f"region {event.region} aborted: {event.reason}", STATUS_MESSAGE_MS)
        elif isinstance(event, Notice):
            self.statusBar().showMessage(event.message, STATUS_MESSAGE_MS)

    def _show_phase(self, tick: np.ndarray) -> None:
        raw = int(tick["phase"])
        try:
            phase = Phase(raw)
        except ValueError:
            self._set_text(self._phase, f"unknown phase {raw}")
            self._set_text(self._phase_hint, "the controller reported a phase this console does not know")
            return
        headline, colour, hint = _PHASES[phase]
        if self._texts.get(self._phase) != headline:
            self._phase.setStyleSheet(f"color: {colour};")
        self._set_text(self._phase, headline)
        self._set_text(self._phase_hint, hint)

        level, n_levels = int(tick["level"]), int(tick["n_levels"])
        if phase == Phase.DONE and n_levels > 0:
            level_text = f"all {n_levels} levels recorded"
        elif level >= 0 and n_levels > 0:
            level_text = f"level {level + 1} of {n_levels}"
        else:
            level_text = ""
        self._set_text(self._level, level_text)

        rmse = float(tick["rmse_N"])
        if phase == Phase.SETTLING and math.isfinite(rmse):
            settled = rmse < self._eps_N
            text = f"RMSE {rmse:.3f} N {'<' if settled else '≥'} ε {self._eps_N:.3f} N"
            colour = "#5fd35f" if settled else "#ffc37a"
            if self._texts.get(self._rmse) != text:
                self._rmse.setStyleSheet(f"color: {colour};")
            self._set_text(self._rmse, text)
        else:
            self._set_text(self._rmse, "")

    def _show_region_done(self, done: bool) -> None:
        if done == self._region_done:
            return
        self._region_done = done
        label = self._region_done_label
        label.setText("REGION DONE\nmove to the next area" if done else "region not done")
        label.setProperty("done", done)
        label.style().unpolish(label)
        label.style().polish(label)

    def _show_fault(self, fault: int) -> None:
        if fault == self._fault_shown:
            return
        self._fault_shown = fault
        if fault == 0:
            self._fault_banner.hide()
            return
        message = self._fault_messages.get(fault)
        self._fault_text.setText(f"FAULT: {_fault_name(fault)}" + (f" — {message}" if message else ""))
        self._fault_banner.show()

    def _show_health(self, health: LoopHealth) -> None:
        text = (f"loop {health.rate_hz:.0f} Hz · late > 0.5 ms: {health.late_over_0_5ms_pct:.2f} % · "
                f"p99 jitter {health.p99_abs_jitter_us:.0f} µs · missed {health.missed_ticks} · "
                f"longest stall {health.longest_stall_ms:.1f} ms · "
                + ("real-time priority" if health.rt_priority else "no real-time priority")
                + (f" · CPU {health.cpu}" if health.cpu is not None else "")
                + (f" · {health.warning}" if health.warning else ""))
        self._set_text(self._health, text)
        degraded = bool(health.warning) or health.late_over_0_5ms_pct > 1.0
        if degraded != self._health_degraded:
            self._health_degraded = degraded
            self._health.setProperty("degraded", degraded)
            self._health.style().unpolish(self._health)
            self._health.style().polish(self._health)


def _fault_name(kind: int) -> str:
    try:
        return FaultKind(kind).name.replace("_", " ").lower()
    except ValueError:
        return f"fault {kind}"
