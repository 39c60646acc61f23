"""The operator console: everything the surgeon sees and touches while palpating.

Layout. A red banner across the top carries any fault (and a controller that stopped). The centre holds
the live pressure and stiffness maps of the TSI, the figures a surgeon glances at between movements. The
right column is fixed (it cannot be closed or moved): the S_z switch, where the Fig. 4 flowchart stands
(phase, ladder of force levels, settling error against ε, "region done"), F_d, F_ts and the TSI
indentation depth in large figures, the contact area, centre of pressure and peak pressure, tare and the
emergency stop. Around them, dockable panels that can be rearranged and are restored on the next run: the
whole-tissue view, jog and autopilot, ramp settings and gains, F_d and F_ts over time with the indentation
history, the messages pane, the loop's health and the session panel (where this run is recorded, operator
notes). The status bar keeps one line of loop health in view. The File menu opens recorded sessions
read-only, each in a reviewer window of its own.

Data flow. The window talks to a controller object (:class:`app.bridge.ControllerBridge` or a test double)
through ``send(command)`` and the signals ``snapshot(LiveSnapshot)`` (display rate, never per tick),
``started()``, ``stopped()`` and ``crashed(str)``. It never touches hardware. Each snapshot updates every
view once; views redraw only what changed. Commands are the typed dataclasses of
:mod:`control.messages`; the window shows the state the controller reports, never the one it asked for.
What may be shown and offered (the fault banner's text, whether the TSI may be jogged or the sensor tared,
settings pending, applied or refused) is decided by a :class:`control.console_state.ConsoleState`, which the
window feeds and reads; it keeps no rules of the loop's itself.

Settings. Dock layout and geometry, the maps' view mode and colour locks, the jog step, the whole-tissue
choices, the autopilot's start area and the last ramp the controller accepted are stored in the given
QSettings and restored on the next run. The restored ramp is sent to the controller when it starts, unless
the configuration's own ramp changed since it was stored (then the configuration wins, and the messages
pane says so). Gains are never restored: they come from the configuration.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from control.autopilot import Autopilot, AutopilotError, AutopilotPlan, AutopilotState
from control.config import ControlConfig, RampSettings
from control.console_state import ConsoleState
from control.messages import (
    ClearFault,
    CommandApplied,
    CommandRefused,
    EStop,
    FaultKind,
    Jog,
    LevelRecorded,
    LevelTimedOut,
    Notice,
    RegionAborted,
    RegionDone,
    SetGains,
    SetRamp,
    SetSz,
    Tare,
)
from control.telemetry import LiveSnapshot, LoopHealth
from hardware.array_calibration import ArrayCalibrationError
from hardware.interfaces import Phase, TactileConstraints
from hardware.settings import ConfigError
from session.array_calibration import calibration_from_session
from session.export import depth_model_text
from session.flatfield import MIN_VOUCHING, FlatFieldError, Reference
from widgets.contact import ContactPanel, contact_metrics
from widgets.findings_table import SAME_TUMOUR_M, FindingsPanel
from widgets.flowchart import FlowchartPanel
from widgets.glossary import GLOSSARY
from widgets.health import VERDICT, HealthPanel, health_summary
from widgets.history_plots import HistoryPlots
from widgets.jog import AutopilotPanel, JogPanel
from widgets.messages import MessagesPane, Severity
from widgets.plot_style import dark_palette
from widgets.review import RecentSessions, ReviewWindow
from widgets.session_panel import SessionPanel
from widgets.settings_panel import GainsEditor, RampEditor
from widgets.sz_switch import SzSwitch
from widgets.tactile_map import TactileMapWidget, ViewMode
from widgets.tissue_view import WholeTissueView

STATUS_MESSAGE_MS = 8000
DEFAULT_SIZE = (1600, 1000)
SETTINGS_VERSION = 1  # of the saved dock layout; a layout saved by another version is ignored
# Following colour ranges start at [0, floor] (see tactile_map.auto_levels). Pressure: uniform contact at
# F_max fills two thirds of the scale, so at low levels the map stays blue and a harder spot still has
# colours to climb to (the paper's figures: the tumour turns dark red as the force rises). Stiffness: soft
# tissue (1-50 kPa) reads blue to cyan, tumour-like stiffness (>= ~100 kPa) red.
PRESSURE_FLOOR_FACTOR = 1.5
STIFFNESS_FLOOR_PA = 100e3
# The TSI may only be sent to a double-clicked point while it carries less than this (off the tissue).
MOVE_TO_MAX_FORCE_N = 0.05

_SIDE_STYLE = """
QScrollArea#sideScroll, QWidget#sideReadouts { background: transparent; }
QScrollArea#sideScroll { border-bottom: 1px solid #4a4a4a; }
QLabel { color: #ececec; }
QLabel[class="caption"] { color: #b0b0b0; font-size: 12pt; }
QLabel[class="readout"] { font-size: 20pt; font-weight: bold; color: #f4f4f4; }
QLabel#indentation { font-size: 30pt; font-weight: bold; color: #e68cff; }
QLabel[class="metric"] { font-size: 12pt; font-weight: bold; }
QLabel#indentation[contact="false"] { font-size: 16pt; color: #808080; }
QLabel#healthChip { border-radius: 4px; padding: 2px 6px; font-size: 10pt; }
QLabel#healthChip[level="good"] { color: #6ee07a; border: 1px solid #2e6b36; }
QLabel#healthChip[level="watch"] { color: #ffc37a; border: 1px solid #8a6a2e; }
QLabel#healthChip[level="bad"] { color: white; background: #a01c28; font-weight: bold; }
QPushButton#tareButton { font-size: 12pt; padding: 4px; color: #ececec; background: #3a3a3a;
                         border: 1px solid #5a5a5a; border-radius: 4px; }
QPushButton#tareButton:disabled { color: #707070; background: #2a2a2a; }
QPushButton#estopButton { font-size: 22pt; font-weight: bold; color: white; background: #c01c28;
                          border: 3px solid #ff8a8a; border-radius: 8px; padding: 10px; }
QPushButton#estopButton:pressed { background: #8a0f18; }
"""
_BANNER_STYLE = """
QFrame#faultBanner { background: #c01c28; border-radius: 4px; }
QLabel#faultText { color: white; font-size: 13pt; font-weight: bold; }
QPushButton#clearFault { font-size: 12pt; padding: 4px 12px; }
"""
_HEALTH_STYLE = """
QLabel#loopHealth { color: #c8c8c8; }
QLabel#loopHealth[degraded="true"] { color: #ffc37a; font-weight: bold; }
"""


def _fmt(value: float, unit: str, decimals: int = 2, scale: float = 1.0) -> str:
    v = float(value)
    if not math.isfinite(v):
        return "—"
    # adding 0.0 turns the -0.0 a small negative reading rounds to into 0.0: a sign no digit carries is noise
    return f"{round(v * scale, decimals) + 0.0:.{decimals}f} {unit}"


def console_settings() -> QtCore.QSettings:
    """Where the console keeps its settings between runs (the user's configuration directory)."""
    return QtCore.QSettings(QtCore.QSettings.Format.IniFormat, QtCore.QSettings.Scope.UserScope,
                            "palpation-console", "console")


class LiveWindow(QtWidgets.QMainWindow):
    """The console's main window (see the module docstring).

    Child objectNames, besides those of the panels it is built from (``pressureMap``, ``stiffnessMap``,
    ``szSwitch``, :class:`~widgets.flowchart.FlowchartPanel`, :class:`~widgets.settings_panel.RampEditor`,
    :class:`~widgets.settings_panel.GainsEditor`, :class:`~widgets.jog.JogPanel`,
    :class:`~widgets.jog.AutopilotPanel`, :class:`~widgets.tissue_view.WholeTissueView`,
    :class:`~widgets.history_plots.HistoryPlots`, :class:`~widgets.contact.ContactPanel`,
    :class:`~widgets.messages.MessagesPane`, :class:`~widgets.health.HealthPanel`): ``forceDesired``,
    ``forceMeasured``, ``indentation``, ``healthChip``, ``tareButton``, ``estopButton``, ``faultBanner``, ``faultText``,
    ``clearFault``, ``loopHealth``; docks ``controlDock``, ``tissueDock``, ``jogDock``, ``settingsDock``,
    ``historyDock``, ``messagesDock``, ``healthDock``, ``sessionDock`` (a
    :class:`~widgets.session_panel.SessionPanel`); File menu actions ``openSessionAction``,
    ``recentSessionsMenu`` (the submenu's action), ``loadReferenceAction``, ``saveReferenceAction``,
    ``clearReferenceAction`` (a reference palpation of tumour-free tissue for the live flat field, see
    :meth:`save_reference`), ``quitAction``.

    Recorded sessions are opened read-only, each in a :class:`~widgets.review.ReviewWindow` of its own;
    ``sessions_folder`` is where the Open dialog starts, ``recent`` the shared recent-sessions list.

    ``findings_told(text)`` says each finding as the surgeon was told it (an area's at "region done", and
    tumours that show later), for the composition root to record in the session.
    """

    findings_told = QtCore.Signal(str)

    def __init__(self, controller, *, config: ControlConfig | None = None, sensor: TactileConstraints | None = None,
                 plan: AutopilotPlan | None = None, settings: QtCore.QSettings | None = None,
                 sessions_folder: str | Path | None = None, recent: RecentSessions | None = None,
                 parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self._sessions_folder = Path(sessions_folder) if sessions_folder is not None else Path.home()
        self._recent = recent if recent is not None else RecentSessions()
        self._reviews: list[ReviewWindow] = []
        self._controller = controller
        self._config = config or ControlConfig()
        self._sensor = sensor or TactileConstraints()
        self._settings = settings if settings is not None else console_settings()
        self.autopilot = Autopilot(plan) if plan is not None else None
        self._texts: dict[QtWidgets.QLabel, str] = {}
        self._frame_seq: int | None = None
        self._state = ConsoleState(self._config)
        self._new_session = True  # the next tick is t = 0 in the messages: each run is a session of its own
        self._fault_shown: tuple[int, str] | None = None
        self._physics = None  # the live flat field's physics (set_live_physics), if the composition root has it
        self._findings_pending: set[int] = set()  # areas done whose findings wait for that physics
        self._told_areas: set[int] = set()  # areas whose findings were told
        self._told: list = []  # (area, tumour) for every tumour told of, oldest first
        self._health_degraded: bool | None = None
        self._ramp_to_restore: RampSettings | None = None

        self.setWindowTitle("Palpation Console")
        self.setPalette(dark_palette())
        self.setAutoFillBackground(True)
        self.setDockOptions(QtWidgets.QMainWindow.DockOption.AnimatedDocks
                            | QtWidgets.QMainWindow.DockOption.AllowTabbedDocks)
        for corner, area in ((QtCore.Qt.Corner.TopRightCorner, QtCore.Qt.DockWidgetArea.RightDockWidgetArea),
                             (QtCore.Qt.Corner.BottomRightCorner, QtCore.Qt.DockWidgetArea.RightDockWidgetArea),
                             (QtCore.Qt.Corner.TopLeftCorner, QtCore.Qt.DockWidgetArea.LeftDockWidgetArea),
                             (QtCore.Qt.Corner.BottomLeftCorner, QtCore.Qt.DockWidgetArea.LeftDockWidgetArea)):
            self.setCorner(corner, area)

        ramp = self._config.ramp
        pitch_m = self._sensor.pitch_m
        self._pressure = TactileMapWidget("Pressure", pitch_m=pitch_m, auto_floor_pa=self._pressure_floor_pa(ramp),
                                          no_data_text="no sensor frame yet")
        self._pressure.setObjectName("pressureMap")
        self._stiffness = TactileMapWidget("Stiffness (Eq. 1)", pitch_m=pitch_m, auto_floor_pa=STIFFNESS_FLOOR_PA,
                                           no_data_text="no contact")
        self._stiffness.setObjectName("stiffnessMap")
        central = QtWidgets.QWidget(objectName="maps")
        maps = QtWidgets.QVBoxLayout(central)
        maps.setContentsMargins(2, 2, 2, 2)
        maps.addWidget(self._pressure, 1)
        maps.addWidget(self._stiffness, 1)
        self.setCentralWidget(central)

        self._build_banner()
        self._build_control_dock()
        self._build_docks()
        self._build_menu()

        self._health = QtWidgets.QLabel("loop: waiting for the controller's first report", objectName="loopHealth")
        self._health.setStyleSheet(_HEALTH_STYLE)
        # the whole line would set the window's minimum width; what does not fit is in the health panel
        self._health.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Preferred)
        self.statusBar().addPermanentWidget(self._health, 1)
        self._build_shortcuts()
        # Within the screen, once every dock is in (docks added later widen the window past a size set
        # before them), until a saved geometry says otherwise.
        screen = QtGui.QGuiApplication.primaryScreen()
        room = screen.availableGeometry().size() if screen is not None else QtCore.QSize(*DEFAULT_SIZE)
        self.resize(min(DEFAULT_SIZE[0], room.width()), min(DEFAULT_SIZE[1], room.height()))
        self._default_state = self.saveState(SETTINGS_VERSION)
        self._restore_settings()

        controller.snapshot.connect(self.show_snapshot)
        controller.started.connect(self._on_started)
        controller.stopped.connect(self._on_stopped)
        controller.crashed.connect(self._on_crashed)
        controller.silent.connect(self._on_silent)
        controller.answering.connect(self._on_answering)
        self._messages.add("Console ready; waiting for the controller to start.")
        self._update_controls()

    # ---- construction --------------------------------------------------------------------------------

    def _build_banner(self) -> None:
        # A toolbar spans the whole window above every dock: the banner cannot be covered or missed.
        self._banner_bar = QtWidgets.QToolBar("Fault", objectName="faultBar")
        self._banner_bar.setMovable(False)
        self._banner_bar.setFloatable(False)
        self._banner_bar.toggleViewAction().setVisible(False)
        self._fault_banner = QtWidgets.QFrame(objectName="faultBanner")
        self._fault_banner.setStyleSheet(_BANNER_STYLE)
        self._fault_banner.setSizePolicy(QtWidgets.QSizePolicy.Policy.Expanding,
                                         QtWidgets.QSizePolicy.Policy.Preferred)
        self._fault_text = QtWidgets.QLabel("", objectName="faultText", wordWrap=True)
        self._clear_fault = QtWidgets.QPushButton("Clear fault", objectName="clearFault")
        self._clear_fault.setToolTip("Release the hold once the cause is gone")
        self._clear_fault.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)  # a deliberate click, never a stray Space
        self._clear_fault.clicked.connect(lambda: self._send(ClearFault()))
        row = QtWidgets.QHBoxLayout(self._fault_banner)
        row.setContentsMargins(10, 2, 10, 2)  # the maps below need the height more than the banner's border
        row.addWidget(self._fault_text, 1)
        row.addWidget(self._clear_fault)
        self._banner_bar.addWidget(self._fault_banner)
        self.addToolBar(QtCore.Qt.ToolBarArea.TopToolBarArea, self._banner_bar)
        self._banner_bar.hide()

    def _build_control_dock(self) -> None:
        panel = QtWidgets.QWidget(objectName="sidePanel")
        panel.setStyleSheet(_SIDE_STYLE)
        outer = QtWidgets.QVBoxLayout(panel)
        outer.setContentsMargins(0, 0, 0, 4)
        outer.setSpacing(6)
        # On a short screen the readouts scroll, over a line; the forces, the depth, the loop's health, tare and
        # STOP stay in view below it.
        readouts = QtWidgets.QWidget(objectName="sideReadouts")
        scroll = QtWidgets.QScrollArea(objectName="sideScroll")
        scroll.setWidgetResizable(True)
        scroll.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
        scroll.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        scroll.setWidget(readouts)
        scroll.viewport().setAutoFillBackground(False)
        outer.addWidget(scroll, 1)
        col = QtWidgets.QVBoxLayout(readouts)
        col.setContentsMargins(8, 0, 8, 0)
        col.setSpacing(6)

        self._sz = SzSwitch()
        self._sz.toggled.connect(lambda position_control: self._request(SetSz(position_control)))
        col.addWidget(self._sz)
        self._flow = FlowchartPanel(self._config.ramp)
        col.addWidget(self._flow)
        col.addSpacing(8)

        self._contact = ContactPanel()
        col.addWidget(self._contact)
        col.addStretch(1)
        col = QtWidgets.QVBoxLayout()
        col.setContentsMargins(8, 0, 8, 0)
        col.setSpacing(4)
        outer.addLayout(col)
        # The forces and the depth stay in view whatever the readouts above need on a short screen (at
        # 1280 x 800 a fault banner scrolled first the depth, then F_d and F_ts away), beside the loop's health
        # and STOP. F_d and F_ts side by side, each caption over its figure: a row each took the height the
        # flag above needs under a fault banner at 1366 x 768.
        forces = QtWidgets.QGridLayout()
        forces.setVerticalSpacing(0)
        self._force_desired = self._readout(forces, 0, "F_d (desired)", "forceDesired", GLOSSARY["F_d"])
        self._force_measured = self._readout(forces, 1, "F_ts (measured)", "forceMeasured", GLOSSARY["F_ts"])
        col.addLayout(forces)
        depth = QtWidgets.QHBoxLayout()
        caption = QtWidgets.QLabel("TSI indentation\ndepth", toolTip=GLOSSARY["indentation"])
        caption.setProperty("class", "caption")
        self._indentation = QtWidgets.QLabel("—", objectName="indentation", toolTip=GLOSSARY["indentation"])
        self._indentation.setAlignment(QtCore.Qt.AlignmentFlag.AlignRight | QtCore.Qt.AlignmentFlag.AlignVCenter)
        depth.addWidget(caption)
        depth.addWidget(self._indentation, 1)
        col.addLayout(depth)
        # wrapped between its figures: a late loop's line ("LOOP / DEVICE PROBLEM · 987 Hz · late 3.27 % · missed
        # 128 (stall 45 ms)") is half again as wide as the column at 1280 x 800, and was cut after "late 3.2"
        self._health_chip = QtWidgets.QLabel("loop: no report yet", objectName="healthChip", wordWrap=True)
        self._health_chip.setToolTip("Loop health and the age of each device's newest reading; details in the "
                                     "Loop health panel")
        self._health_chip.setProperty("level", "watch")
        col.addWidget(self._health_chip)

        self._tare = QtWidgets.QPushButton("Tare sensor", objectName="tareButton")
        self._tare.setToolTip("Take the current reading as zero (only with the TSI off the tissue)")
        self._tare.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)
        self._tare.setEnabled(False)
        self._tare.clicked.connect(lambda: self._send(Tare()))
        col.addWidget(self._tare)
        estop = QtWidgets.QPushButton("STOP   (Esc)", objectName="estopButton")
        estop.setToolTip("Emergency stop: hold the robot where it is")
        estop.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)
        estop.clicked.connect(self._estop)
        col.addWidget(estop)

        dock = QtWidgets.QDockWidget("Control", objectName="controlDock")
        dock.setWidget(panel)
        dock.setFeatures(QtWidgets.QDockWidget.DockWidgetFeature.NoDockWidgetFeatures)
        dock.setTitleBarWidget(QtWidgets.QWidget())  # nothing to drag, nothing to close
        dock.setFixedWidth(350)
        self.addDockWidget(QtCore.Qt.DockWidgetArea.RightDockWidgetArea, dock)

    @staticmethod
    def _readout(grid: QtWidgets.QGridLayout, column: int, caption: str, name: str, meaning: str) -> QtWidgets.QLabel:
        cap = QtWidgets.QLabel(caption, toolTip=meaning)
        cap.setProperty("class", "caption")
        value = QtWidgets.QLabel("—", objectName=name, toolTip=meaning)
        value.setProperty("class", "readout")
        grid.addWidget(cap, 0, column)
        grid.addWidget(value, 1, column)
        return value

    def _dock(self, title: str, name: str, widget: QtWidgets.QWidget, area: QtCore.Qt.DockWidgetArea
              ) -> QtWidgets.QDockWidget:
        dock = QtWidgets.QDockWidget(title, objectName=name)
        dock.setWidget(widget)
        dock.setFeatures(QtWidgets.QDockWidget.DockWidgetFeature.DockWidgetClosable
                         | QtWidgets.QDockWidget.DockWidgetFeature.DockWidgetMovable
                         | QtWidgets.QDockWidget.DockWidgetFeature.DockWidgetFloatable)
        self.addDockWidget(area, dock)
        self._docks.append(dock)
        return dock

    def _build_docks(self) -> None:
        cfg = self._config
        left, bottom = QtCore.Qt.DockWidgetArea.LeftDockWidgetArea, QtCore.Qt.DockWidgetArea.BottomDockWidgetArea
        self._docks: list[QtWidgets.QDockWidget] = []
        plan = self.autopilot.plan if self.autopilot is not None else None

        self._tissue = WholeTissueView(
            self._sensor, min_indentation_m=cfg.contact.min_indentation_m,
            pressure_floor_pa=self._pressure_floor_pa(cfg.ramp), stiffness_floor_pa=STIFFNESS_FLOOR_PA,
            extent_m=plan.phantom_extent_m if plan is not None else None,
            areas=tuple((a.x_m, a.y_m) for a in plan.areas) if plan is not None else ())
        self._tissue.move_requested.connect(self._move_to)
        tissue_dock = self._dock("Whole tissue", "tissueDock", self._tissue, left)

        self._jog = JogPanel(cfg.master.jog_speed_m_s)
        self._jog.jog_requested.connect(lambda dx, dy, dz: self._send(Jog((dx, dy, dz))))
        self._autopilot_panel = AutopilotPanel(len(plan.areas) if plan is not None else 0)
        self._autopilot_panel.start_requested.connect(self.start_autopilot)
        self._autopilot_panel.stop_requested.connect(self._stop_autopilot)
        jog_page = QtWidgets.QWidget()
        jog_layout = QtWidgets.QVBoxLayout(jog_page)
        jog_layout.setContentsMargins(0, 0, 0, 0)
        jog_layout.addWidget(self._jog)
        jog_layout.addWidget(self._autopilot_panel)
        jog_layout.addStretch(1)
        jog_dock = self._dock("Jog and autopilot", "jogDock", jog_page, left)

        self._ramp_editor = RampEditor(cfg.ramp)
        self._ramp_editor.apply_requested.connect(lambda ramp: self._request(SetRamp(ramp)))
        self._gains_editor = GainsEditor(cfg.gains, lambda gains: cfg.gains_problem(
            gains, self._sensor.frame_rate_hz, self._sensor.latency_s))
        self._gains_editor.apply_requested.connect(lambda gains: self._request(SetGains(gains)))
        settings_page = QtWidgets.QWidget()
        settings_layout = QtWidgets.QVBoxLayout(settings_page)
        settings_layout.setContentsMargins(0, 0, 0, 0)
        for title, editor in (("Ramp (Fig. 4)", self._ramp_editor), ("Impedance gains (Eq. 2)", self._gains_editor)):
            box = QtWidgets.QGroupBox(title)
            QtWidgets.QVBoxLayout(box).addWidget(editor)
            settings_layout.addWidget(box)
        settings_layout.addStretch(1)
        scroll = QtWidgets.QScrollArea()
        scroll.setWidgetResizable(True)
        scroll.setWidget(settings_page)
        settings_dock = self._dock("Ramp and gains", "settingsDock", scroll, left)

        self._history = HistoryPlots(force_max_N=cfg.ramp.force_max_N,
                                     depth_limit_m=cfg.safety.indentation_ceiling_m)
        history_dock = self._dock("Force and depth history", "historyDock", self._history, bottom)
        self._messages = MessagesPane()
        messages_dock = self._dock("Messages", "messagesDock", self._messages, bottom)
        self._health_panel = HealthPanel(cfg.safety, cfg.rate_hz)
        health_dock = self._dock("Loop health", "healthDock", self._health_panel, bottom)
        self._session_panel = SessionPanel()
        session_dock = self._dock("Session recording", "sessionDock", self._session_panel, bottom)
        self._findings = FindingsPanel()
        self._findings.table.move_requested.connect(self._move_to)
        self._findings_dock = self._dock("Findings", "findingsDock", self._findings, left)

        self.tabifyDockWidget(jog_dock, settings_dock)
        self.tabifyDockWidget(jog_dock, self._findings_dock)
        jog_dock.raise_()
        self.splitDockWidget(history_dock, messages_dock, QtCore.Qt.Orientation.Horizontal)
        self.tabifyDockWidget(messages_dock, health_dock)
        self.tabifyDockWidget(messages_dock, session_dock)
        messages_dock.raise_()
        self.resizeDocks([tissue_dock, jog_dock], [470, 360], QtCore.Qt.Orientation.Vertical)
        self.resizeDocks([tissue_dock], [380], QtCore.Qt.Orientation.Horizontal)
        self.resizeDocks([history_dock, messages_dock], [560, 420], QtCore.Qt.Orientation.Horizontal)
        self.resizeDocks([history_dock], [320], QtCore.Qt.Orientation.Vertical)

    def _build_menu(self) -> None:
        file = self.menuBar().addMenu("&File")
        open_action = file.addAction("&Open session…")
        open_action.setObjectName("openSessionAction")
        open_action.setShortcut(QtGui.QKeySequence.StandardKey.Open)
        open_action.triggered.connect(self._open_session_dialog)
        self._recent_menu = file.addMenu("&Recent sessions")
        self._recent_menu.menuAction().setObjectName("recentSessionsMenu")
        self._recent_menu.aboutToShow.connect(lambda: self._recent.fill_menu(self._recent_menu, self.open_session))
        file.addSeparator()
        for name, label, slot in (("loadReferenceAction", "&Load reference palpation…", self._load_reference_dialog),
                                  ("saveReferenceAction", "Save these levels as a &reference palpation…",
                                   self._save_reference_dialog),
                                  ("clearReferenceAction", "Clear the reference palpation", self.clear_reference),
                                  ("calibrateArrayAction", "&Calibrate the array from presses on a cushion…",
                                   self._calibrate_dialog)):
            action = file.addAction(label)
            action.setObjectName(name)
            action.triggered.connect(slot)
        file.addSeparator()
        quit_action = file.addAction("&Quit")
        quit_action.setObjectName("quitAction")
        quit_action.setShortcut(QtGui.QKeySequence.StandardKey.Quit)
        quit_action.triggered.connect(self.close)
        view = self.menuBar().addMenu("&View")
        for dock in self._docks:
            view.addAction(dock.toggleViewAction())
        view.addSeparator()
        reset = view.addAction("Restore the default layout")
        reset.setObjectName("resetLayout")
        reset.triggered.connect(self.reset_layout)

    def _build_shortcuts(self) -> None:
        # Window context: an application-wide key would become ambiguous (and fire nowhere) as soon as a
        # second window registers it.
        def shortcut(key, slot) -> None:
            s = QtGui.QShortcut(QtGui.QKeySequence(key), self)
            s.setContext(QtCore.Qt.ShortcutContext.WindowShortcut)
            s.activated.connect(slot)

        Key = QtCore.Qt.Key
        shortcut(Key.Key_Escape, self._estop)
        for key, name in ((Key.Key_Up, "jogXPlus"), (Key.Key_Down, "jogXMinus"), (Key.Key_Left, "jogYMinus"),
                          (Key.Key_Right, "jogYPlus"), (Key.Key_PageUp, "jogZPlus"), (Key.Key_PageDown, "jogZMinus")):
            shortcut(key, lambda n=name: self._jog.step(n))

    # ---- settings ------------------------------------------------------------------------------------

    def _restore_settings(self) -> None:
        s = self._settings
        geometry = s.value("window/geometry")
        if isinstance(geometry, QtCore.QByteArray):
            self.restoreGeometry(geometry)
        state = s.value("window/state")
        if isinstance(state, QtCore.QByteArray):
            self.restoreState(state, SETTINGS_VERSION)
        for key, tmap in (("pressure", self._pressure), ("stiffness", self._stiffness)):
            mode = s.value(f"maps/{key}/mode")
            if mode in (m.value for m in ViewMode):
                tmap.set_view_mode(ViewMode(mode))
            tmap.set_iso_lines(_bool(s.value(f"maps/{key}/iso"), tmap.iso_lines()))
            locked = s.value(f"maps/{key}/locked_pa")
            if locked:
                try:
                    low, high = (float(v) for v in json.loads(locked))
                    tmap.lock_levels(low, high)
                except (TypeError, ValueError):
                    self._messages.add(f"Ignored the saved colour range of the {key} map: {locked!r}",
                                       Severity.WARNING)
        step = s.value("jog/step_mm")
        if step is not None:
            try:
                self._jog.set_step_mm(float(step))
            except (TypeError, ValueError):
                pass  # a step size this version does not offer: keep the default
        quantity = s.value("tissue/quantity")
        if quantity is not None:
            try:
                self._tissue.set_quantity(str(quantity))
            except ValueError:
                pass
        first = s.value("autopilot/first_area")
        if first is not None and self.autopilot is not None:
            try:
                self._autopilot_panel.set_first_area(int(first))
            except (TypeError, ValueError):
                pass
        self._restore_ramp()
        self._banner_bar.hide()  # a layout saved while a fault showed must not bring back its banner

    def _restore_ramp(self) -> None:
        s = self._settings
        saved, base = s.value("ramp/applied"), s.value("ramp/config")
        if not saved:
            return
        try:
            ramp = RampSettings.from_mapping(json.loads(saved))
            config_then = RampSettings.from_mapping(json.loads(base)) if base else None
        except (ConfigError, TypeError, ValueError) as err:
            self._messages.add(f"The ramp saved by the last run was ignored: {err}", Severity.WARNING)
            return
        if ramp == self._config.ramp:
            return
        if config_then != self._config.ramp:
            self._messages.add("The configuration's ramp changed since the last run, so the ramp applied then "
                               "is not restored.", Severity.INFO)
            return
        self._ramp_to_restore = ramp
        self._ramp_editor.show_ramp(ramp)

    def save_settings(self) -> None:
        s = self._settings
        s.setValue("window/geometry", self.saveGeometry())
        s.setValue("window/state", self.saveState(SETTINGS_VERSION))
        for key, tmap in (("pressure", self._pressure), ("stiffness", self._stiffness)):
            s.setValue(f"maps/{key}/mode", tmap.view_mode().value)
            s.setValue(f"maps/{key}/iso", tmap.iso_lines())
            s.setValue(f"maps/{key}/locked_pa", json.dumps(list(tmap.levels_pa())) if tmap.is_locked() else "")
        s.setValue("jog/step_mm", self._jog.step_m() * 1e3)
        s.setValue("tissue/quantity", self._tissue.quantity())
        if self.autopilot is not None:
            s.setValue("autopilot/first_area", self._autopilot_panel.first_area())
        applied = self._ramp_editor.applied()
        if applied != self._config.ramp:
            s.setValue("ramp/applied", json.dumps(applied.to_mapping()))
            s.setValue("ramp/config", json.dumps(self._config.ramp.to_mapping()))
        else:
            s.remove("ramp")
        s.sync()

    def reset_layout(self) -> None:
        self.restoreState(self._default_state, SETTINGS_VERSION)
        self._banner_bar.setVisible(self._fault_shown is not None)

    def closeEvent(self, event: QtGui.QCloseEvent) -> None:
        self.save_settings()
        for review in self.review_windows():
            review.close()
        super().closeEvent(event)

    # ---- public API ----------------------------------------------------------------------------------

    def set_ramp(self, ramp: RampSettings) -> None:
        """The ramp now in force: ε for the flowchart, F_max for the force plot and the pressure colour range."""
        self._flow.set_ramp(ramp)
        self._history.set_force_max_N(ramp.force_max_N)
        self._pressure.set_auto_floor_pa(self._pressure_floor_pa(ramp))

    @QtCore.Slot(object)
    def show_snapshot(self, snapshot: LiveSnapshot) -> None:
        """Update every view from one snapshot; only what changed is redrawn (called at ~60 Hz)."""
        if self._ramp_to_restore is not None and self._state.running:
            ramp, self._ramp_to_restore = self._ramp_to_restore, None
            self._messages.add(f"Restoring the ramp applied in the last run: {ramp.force_min_N:g} to "
                               f"{ramp.force_max_N:g} N in {ramp.force_step_N:g} N steps.")
            self._ramp_editor.request(ramp)
        tick = snapshot.tick
        if self._new_session:  # the run's (and its session file's) first tick is t = 0 for the operator
            self._new_session = False
            self._messages.set_time_origin(float(snapshot.ticks[0]["t_s"]) if len(snapshot.ticks)
                                           else float(tick["t_s"]))
        self._state.on_tick(tick)
        for event in snapshot.events:
            self._handle_event(event)
        self._show_settings()
        if self.autopilot is not None:
            for command in self.autopilot.update(tick, snapshot.events):
                self._send(command)
        self._show_tick(tick)
        self._history.add_ticks(snapshot.ticks)
        self._history.refresh()
        frame = snapshot.frame
        if frame is not None and int(frame["sensor_seq"]) != self._frame_seq:
            self._frame_seq = int(frame["sensor_seq"])
            self._show_frame(frame)
        if snapshot.health is not None:
            self._show_health(snapshot.health)
        self._tissue.refresh()

    def messages(self) -> MessagesPane:
        return self._messages

    def session_panel(self) -> SessionPanel:
        return self._session_panel

    def recent_sessions(self) -> RecentSessions:
        return self._recent

    def review_windows(self) -> list[ReviewWindow]:
        """The session reviewers opened from this console that are still open."""
        return list(self._reviews)

    def open_session(self, path: str | Path) -> ReviewWindow | None:
        """Open a recorded session read-only in a reviewer window of its own; None (and the reason in the
        messages pane) if the file is not a readable session."""
        review = ReviewWindow(start_folder=self._sessions_folder)
        review.setAttribute(QtCore.Qt.WidgetAttribute.WA_DeleteOnClose)
        problems: list[str] = []
        review.open_failed.connect(problems.append)
        if not review.open_file(path):
            self._messages.add(f"Cannot open the session: {problems[-1] if problems else path}", Severity.ERROR)
            review.deleteLater()
            return None
        self._reviews.append(review)
        review.destroyed.connect(lambda _=None, w=review: self._reviews.remove(w) if w in self._reviews else None)
        review.show()
        return review

    def latest_tick(self) -> np.ndarray | None:
        """The newest tick row shown (None before the first snapshot)."""
        return self._state.tick

    def _open_session_dialog(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Open a recorded session", str(self._sessions_folder),
                                                        "Palpation sessions (*.h5);;All files (*)")
        if path:
            self.open_session(path)

    # ---- controller ----------------------------------------------------------------------------------

    def _send(self, command) -> None:
        self._controller.send(command)

    def _request(self, command) -> None:
        """Send a command that changes a setting; it shows as pending until the controller answers."""
        self._send(self._state.request(command))
        self._show_settings()

    def _estop(self) -> None:
        self._send(EStop())
        if self.autopilot is not None and self.autopilot.running:
            # Its move-cancelling jog is not sent: the loop refuses jogs in HOLD, and clearing the fault
            # drops whatever jog was left.
            self.autopilot.stop("emergency stop")

    @QtCore.Slot()
    def _on_started(self) -> None:
        self._state.started()
        self._new_session = True
        self._messages.add("Controller running.", Severity.OK)

    @QtCore.Slot()
    def _on_stopped(self) -> None:
        self._state.stopped()
        self._show_settings()
        self._messages.add("Controller stopped.")

    @QtCore.Slot(str)
    def _on_crashed(self, message: str) -> None:
        self._state.crashed(message)
        self._show_settings()
        if self.autopilot is not None and self.autopilot.running:
            self.autopilot.stop("the controller stopped")
        self._messages.add(f"CONTROLLER STOPPED: {message}", Severity.ERROR)
        self._show_controller_health()

    @QtCore.Slot(float)
    def _on_silent(self, seconds: float) -> None:
        if not self._state.silence_s:
            self._messages.add("The controller stopped answering: the console's figures are frozen at its last "
                               "report.", Severity.ERROR)
        self._state.silent(seconds)
        self._show_controller_health()

    @QtCore.Slot(float)
    def _on_answering(self, seconds: float) -> None:
        self._state.answering()
        self._messages.add(f"The controller answers again, after {seconds * 1e3:.0f} ms without a report.",
                           Severity.WARNING)
        self._show_controller_health()

    def _show_controller_health(self) -> None:
        """The banner, the health chip and the status line say the same about the controller itself."""
        problem = self._state.controller_problem()
        self._health_panel.show_controller_problem(problem)
        self._show_health_chip()
        level, text = self._health_panel.overall()
        self._show_status_line(level, text.replace("\n", " · "))
        self._show_fault()
        self._update_controls()

    def start_autopilot(self, first_area: int = 0) -> None:
        """Start the autopilot at area ``first_area`` (0-based); why it cannot goes to the messages pane."""
        if self.autopilot is None:
            self._messages.add("Autopilot not started: this rig has no phantom file to plan the areas from",
                               Severity.WARNING)
            return
        try:
            self._send_all(self.autopilot.start(first_area))
        except AutopilotError as err:
            self._messages.add(f"Autopilot not started: {err}", Severity.WARNING)
            return
        self._messages.add(f"Autopilot started at area {first_area + 1} of {len(self.autopilot.plan.areas)}.")
        self._update_controls()

    def _stop_autopilot(self) -> None:
        if self.autopilot is not None and self.autopilot.running:
            self._send_all(self.autopilot.stop())
            self._update_controls()

    def _send_all(self, commands) -> None:
        for command in commands:
            self._send(command)

    def _move_to(self, x_m: float, y_m: float) -> None:
        """Double-click on the whole-tissue view: move the TSI there at its current height."""
        tick = self._state.tick
        if not self._jog.available() or tick is None:
            self.statusBar().showMessage("The TSI cannot be moved from here now: "
                                         f"{self._jog_unavailable() or 'no reading yet'}", STATUS_MESSAGE_MS)
            return
        if float(tick["force_measured_N"]) > MOVE_TO_MAX_FORCE_N:
            self.statusBar().showMessage("Lift the TSI off the tissue before moving it across", STATUS_MESSAGE_MS)
            return
        x_des = tick["x_des_m"]
        self._send(Jog((x_m - float(x_des[0]), y_m - float(x_des[1]), 0.0)))
        self._messages.add(f"Moving the TSI to x {x_m * 1e3:.1f} mm, y {y_m * 1e3:.1f} mm.")

    # ---- events --------------------------------------------------------------------------------------

    def _handle_event(self, event) -> None:
        self._state.on_event(event)
        self._messages.add_event(event)
        if isinstance(event, LevelRecorded):
            self._history.mark_recorded(event.record.t_s, event.record.force_measured_N)
            self._tissue.add_record(event.record)
        elif isinstance(event, CommandRefused):
            self.statusBar().showMessage(f"{event.command_name} refused: {event.reason}", STATUS_MESSAGE_MS)
        elif isinstance(event, LevelTimedOut):
            self.statusBar().showMessage(event.message, STATUS_MESSAGE_MS)
        elif isinstance(event, RegionDone):
            self._ask_physics()
            self._tell_findings(event.region)
        elif isinstance(event, RegionAborted):
            self._ask_physics()
            self.statusBar().showMessage(f"Region {event.region + 1} aborted: {event.reason}", STATUS_MESSAGE_MS)
        elif isinstance(event, (Notice, CommandApplied)):
            self.statusBar().showMessage(event.message, STATUS_MESSAGE_MS)

    def set_live_physics(self, physics) -> None:
        """The physics of the live flat field (``app.live_physics.LivePhysics``: ``request(levels)``, signals
        ``ready(records, patterns, description)`` and ``failed(reason)``), asked for after every area; the
        contrast, the tumours and each area's findings wait for it."""
        self._physics = physics
        physics.ready.connect(self._physics_ready)
        physics.failed.connect(self._physics_failed)
        physics.progress.connect(self._physics_progress)
        self._tissue.expect_physics(True)

    def _ask_physics(self) -> None:
        if self._physics is not None and self._tissue.record_count():
            self._physics.request(self._tissue.levels())

    def _physics_progress(self, records: int, fraction: float, what: str) -> None:
        """The tissue model of the first ``records`` levels is being computed: the findings panel shows how far,
        the flag's line the same for the area waiting, and Messages says once that it started."""
        areas = self._areas_palpated(records)
        self._findings.show_progress(fraction, f"Tissue model of the {areas} areas palpated: {what}")
        if fraction == 0.0:
            self._messages.add(f"Computing the findings: the tissue model of the {areas} areas palpated…")
        if self._findings_pending and self._findings_can_come():
            self._flow.show_findings(f"Area {max(self._findings_pending) + 1}: computing findings… {fraction:.0%}")

    def _areas_palpated(self, records: int | None = None) -> int:
        """Areas among the first ``records`` levels recorded (None: all)."""
        return len(np.unique(self._tissue.levels()[:records]["region"]))

    def _findings_can_come(self) -> bool:
        """Whether the next answer of the physics can give findings (enough areas to vouch for each other)."""
        return self._areas_palpated() > MIN_VOUCHING

    def _physics_ready(self, records: int, patterns: dict, description: str) -> None:
        if not self._physics.busy:
            self._findings.show_progress(None)
        self._tissue.set_physics(records, patterns, description)
        self._tell_pending_findings()
        self._tell_later_findings()

    def _physics_failed(self, reason: str) -> None:
        self._physics = None
        self._findings.show_progress(None)
        self._tissue.expect_physics(False)
        self._messages.add(f"Tissue model of the palpated areas unavailable: {reason}; the probe's pattern now comes "
                           "from the areas alone (the tissue's ends may read as tumours)", Severity.WARNING)
        self._tell_pending_findings()

    def _tell_pending_findings(self) -> None:
        for region in sorted(self._findings_pending):
            if not self._tissue.findings_pending(region):
                self._findings_pending.discard(region)
                self._tell_findings(region)

    def set_depth_model(self, model) -> None:
        """Give the findings told at "region done" a model-based depth (:class:`session.analysis.DepthModel`;
        the composition root has the library of solves), or None for the paper's rule alone."""
        self._tissue.set_depth_model(model)

    # ---- reference palpation -----------------------------------------------------------------------------

    def load_reference(self, path: str | Path) -> bool:
        """Use the reference palpation at ``path`` for the live flat field; says why in the messages if not."""
        try:
            reference = Reference.load(path, (self._sensor.rows, self._sensor.cols))
            self._tissue.set_reference(reference)
        except FlatFieldError as err:
            self._messages.add(f"Reference palpation not loaded: {err}", Severity.WARNING)
            return False
        self._messages.add(f"Reference palpation {Path(path).name} loaded ({reference.areas} areas, "
                           f"{len(reference.forces_N)} levels): contrast and findings from the first area on")
        return True

    def save_reference(self, path: str | Path) -> bool:
        """Save the levels recorded so far (tumour-free tissue) as a reference palpation at ``path``."""
        try:
            reference = self._tissue.reference_from_levels(
                f"reference palpation recorded {time.strftime('%Y-%m-%d %H:%M')} in the console")
            reference.save(path)
        except FlatFieldError as err:
            self._messages.add(f"Reference palpation not saved: {err}", Severity.WARNING)
            return False
        except OSError as err:
            self._messages.add(f"Reference palpation not saved: cannot write {path}: {err.strerror or err}",
                               Severity.WARNING)
            return False
        self._messages.add(f"Reference palpation saved to {path} ({reference.areas} areas, "
                           f"{len(reference.forces_N)} levels)")
        return True

    def clear_reference(self) -> None:
        self._tissue.set_reference(None)
        self._messages.add("Reference palpation cleared: the flat field comes from the areas palpated")

    def _load_reference_dialog(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Load reference palpation", str(self._sessions_folder),
                                                        "Reference palpation (*.json)")
        if path:
            self.load_reference(path)

    def _save_reference_dialog(self) -> None:
        path, _ = QtWidgets.QFileDialog.getSaveFileName(self, "Save reference palpation", str(self._sessions_folder),
                                                        "Reference palpation (*.json)")
        if path:
            self.save_reference(path)

    def calibrate_array(self, session_path: str | Path, out_path: str | Path) -> bool:
        """Fit the array's calibration from a recorded session of presses on a uniform cushion and save it to
        ``out_path`` (docs/hardware.md, "The array's element pattern"); says in the messages what came of it."""
        try:
            calibration = calibration_from_session(session_path)
            calibration.save(out_path)
        except ArrayCalibrationError as err:
            self._messages.add(f"Array not calibrated: {err}", Severity.WARNING)
            return False
        # the running rig was built with the calibration it started with: this one serves the next run
        self._messages.add(f"Array calibration saved to {out_path} ({calibration.summary()}). The next run takes "
                           f"it out of every frame with `run --calibration {out_path}` or [rig] calibration.")
        return True

    def _calibrate_dialog(self) -> None:
        session, _ = QtWidgets.QFileDialog.getOpenFileName(
            self, "The session of presses on the calibration cushion", str(self._sessions_folder),
            "Palpation sessions (*.h5)")
        if not session:
            return
        out, _ = QtWidgets.QFileDialog.getSaveFileName(self, "Save the array's calibration",
                                                       str(self._sessions_folder.parent / "tsi-calibration.toml"),
                                                       "Array calibration (*.toml)")
        if out:
            self.calibrate_array(session, out)

    def _tell_findings(self, region: int) -> None:
        """At "region done": what that area showed, in the messages and under the flowchart's flag."""
        if self._tissue.findings_pending(region):
            self._findings_pending.add(region)
            if self._findings_can_come():
                text = f"Area {region + 1}: computing findings…"
            else:
                text = (f"Area {region + 1}: findings once {MIN_VOUCHING + 1} areas are palpated and the tissue "
                        "model of the areas is computed")
            self._messages.add(text)
            self._flow.show_findings(text)
            return
        findings = self._tissue.findings_in(region)
        f_max = self._ramp_editor.applied().force_max_N
        if findings is None:
            text = (f"Area {region + 1}: findings from the 4th area on (the probe's pattern is estimated from the "
                    "other areas), or load a reference palpation")
        elif not findings:
            text = f"Area {region + 1}: nothing significant up to {f_max:g} N"
            if self._physics is not None and not self._physics.ends_known:
                text += (" so far (where the tissue ends is not known: a tumour near this area's edges may show "
                         "once the areas beside it are palpated)")
        else:
            text = f"Area {region + 1}: " + "; ".join(_finding_text(t) for t in findings)
        if findings is not None:
            self._told_areas.add(region)
            self._tell([(region, t) for t in findings])
            self.findings_told.emit(text)
        self._messages.add(text, Severity.WARNING if findings else Severity.INFO)
        if findings is not None:
            text = _flag_text(region, findings, f_max, self._physics is not None and not self._physics.ends_known)
        self._flow.show_findings(text)

    def _tell(self, told: list) -> None:
        """Add (area, tumour) pairs to what the surgeon has been told: the map's labels and the table follow."""
        self._told += told
        self._tissue.set_told([t for _, t in self._told])
        self._findings.table.set_findings(self._told)
        if told:
            # a tumour told: its row (position, both depths, double-click to go there) comes into view; the jog
            # and autopilot tab is a click away, and STOP stays in view whatever is raised
            self._findings_dock.raise_()

    def _tell_later_findings(self) -> None:
        """Tumours that areas already told of show only now (the areas beside them palpated since, or the
        tissue model of more of them): said once each, in the messages."""
        for region in sorted(self._told_areas):
            for tumour in self._tissue.findings_in(region, [t for _, t in self._told]) or []:
                self._tell([(region, tumour)])
                text = f"Area {region + 1}, with the areas palpated since: {_finding_text(tumour)}"
                self._messages.add(text, Severity.WARNING)
                self.findings_told.emit(text)

    def _show_settings(self) -> None:
        """The S_z switch, ramp and gains as the controller has them, with what is pending or refused."""
        state = self._state
        self._sz.set_state(state.sz.applied, state.sz.pending)
        if state.ramp.applied != self._ramp_editor.applied():
            self.set_ramp(state.ramp.applied)
        self._ramp_editor.show_setting(state.ramp)
        self._gains_editor.show_setting(state.gains)

    # ---- display -------------------------------------------------------------------------------------

    def _show_tick(self, tick: np.ndarray) -> None:
        if self._physics is not None:
            self._physics.hold(not Phase(int(tick["phase"])).idle)
        self._flow.show_tick(tick)
        self._set_text(self._force_desired, _fmt(tick["force_desired_N"], "N"))
        self._set_text(self._force_measured, _fmt(tick["force_measured_N"], "N"))
        self._show_indentation(float(tick["indentation_m"]))
        self._show_fault()
        self._health_panel.show_ages(tick)
        self._show_health_chip()
        position = tick["x_slave_m"]
        self._jog.set_position(position)
        self._tissue.set_tsi_position(float(position[0]), float(position[1]))
        self._update_controls()

    def _show_indentation(self, depth_m: float) -> None:
        contact = math.isfinite(depth_m)
        self._set_text(self._indentation, f"{depth_m * 1e3:.1f} mm" if contact else "no contact")
        if self._indentation.property("contact") != contact:
            self._indentation.setProperty("contact", contact)
            self._indentation.style().unpolish(self._indentation)
            self._indentation.style().polish(self._indentation)

    def _show_frame(self, frame: np.ndarray) -> None:
        pressure = frame["pressure_pa"]
        metrics = contact_metrics(pressure, self._config.contact.confirm_threshold_pa, self._sensor)
        # In the air the array reads its own noise: shown in colour it looks like a light touch (a dark blue
        # map, "max 0.1 kPa"); below the contact threshold everywhere, the map is the grey no-contact state.
        self._pressure.set_no_data_text("no contact" if np.isfinite(pressure).any() else "no sensor frame yet")
        self._pressure.set_data(pressure if metrics.elements else np.full_like(pressure, np.nan))
        self._stiffness.set_data(frame["stiffness_pa"])
        if self._pressure.contrast_view() or self._stiffness.contrast_view():
            self._show_frame_contrast(frame)
        self._contact.show_metrics(metrics, frame["tsi_position_m"])
        self._pressure.set_marker_m(metrics.centre_m)

    def _show_frame_contrast(self, frame: np.ndarray) -> None:
        """Each map in its contrast view gets the frame flat-fielded, with its significant spots."""
        in_contact = np.isfinite(frame["dL_m"])  # the elements Eq. 1 has, as in a level record
        pressure = np.where(in_contact, frame["pressure_pa"], np.nan)
        force_N = float(np.nansum(pressure)) * self._sensor.element_area_m2
        for widget, name, values in ((self._pressure, "force", pressure), (self._stiffness, "stiffness",
                                                                           frame["stiffness_pa"])):
            if widget.contrast_view():
                found = self._tissue.frame_contrast(values, name, force_N)
                if found is None:
                    widget.set_contrast(None)
                else:
                    widget.set_contrast(found.contrast, found.spots, found.sigma)

    def _jog_unavailable(self) -> str | None:
        return self._state.jog_unavailable(self.autopilot is not None and self.autopilot.running)

    def _update_controls(self) -> None:
        reason = self._jog_unavailable()
        self._jog.set_unavailable(reason)
        self._tare.setEnabled(self._state.can_tare())
        if self.autopilot is None:
            self._autopilot_panel.show_state("unavailable", "this rig has no phantom file to plan the areas from",
                                             can_start=False)
            return
        ap = self.autopilot
        blocked = reason if reason and ap.state is not AutopilotState.RUNNING else None
        message = ap.message if ap.state is not AutopilotState.IDLE or blocked is None else blocked
        self._autopilot_panel.show_state(ap.state.value, message, can_start=blocked is None)

    def _show_fault(self) -> None:
        shown = self._state.fault()
        if shown == self._fault_shown:
            return
        self._fault_shown = shown
        if shown is None:
            self._banner_bar.hide()
            return
        kind, text = shown
        self._fault_text.setText(text)
        self._clear_fault.setVisible(kind != FaultKind.CONTROLLER)
        self._banner_bar.show()

    def _show_health_chip(self) -> None:
        level, text = self._health_panel.overall()
        self._set_text(self._health_chip, text)
        if self._health_chip.property("level") != level:
            self._health_chip.setProperty("level", level)
            self._health_chip.style().unpolish(self._health_chip)
            self._health_chip.style().polish(self._health_chip)

    def _show_health(self, health: LoopHealth) -> None:
        self._health_panel.show_health(health)
        self._show_health_chip()
        level, _ = self._health_panel.overall()
        self._show_status_line(level, f"{VERDICT[level]} · {health_summary(health)}")

    def _show_status_line(self, level: str, text: str) -> None:
        self._set_text(self._health, text)
        degraded = level != "good"
        if degraded != self._health_degraded:
            self._health_degraded = degraded
            self._health.setProperty("degraded", degraded)
            self._health.style().unpolish(self._health)
            self._health.style().polish(self._health)

    def _pressure_floor_pa(self, ramp: RampSettings) -> float:
        face_m2 = self._sensor.rows * self._sensor.cols * self._sensor.element_area_m2
        return PRESSURE_FLOOR_FACTOR * ramp.force_max_N / face_m2

    def _set_text(self, label: QtWidgets.QLabel, text: str) -> None:
        if self._texts.get(label) != text:
            self._texts[label] = text
            label.setText(text)


def _bool(value, default: bool) -> bool:
    """QSettings' INI files give booleans back as the strings "true" / "false"."""
    if value is None:
        return default
    if isinstance(value, bool):
        return value
    return str(value).lower() == "true"


def _flag_text(region: int, findings: list, f_max_N: float, so_far: bool) -> str:
    """An area's findings in a line or two under the region-done flag: the whole sentence of each tumour (the
    messages and the Findings tab have it) pushed F_d, F_ts and the depth out of a laptop's view."""
    if not findings:
        return f"Area {region + 1}: nothing significant up to {f_max_N:g} N" + (" so far" if so_far else "")
    spots: list[list] = []  # a tumour shows on both maps: one spot (the detector's own merge radius)
    for t in findings:
        spot = next((s for s in spots if math.hypot(s[0].x_m - t.x_m, s[0].y_m - t.y_m) <= SAME_TUMOUR_M), None)
        if spot is None:
            spots.append([t])
        else:
            spot.append(t)
    if len(spots) > 1:
        return f"Area {region + 1}: {len(spots)} tumours, in the Findings tab and on the map"
    t = next((t for t in spots[0] if math.isfinite(t.depth_model_m)), spots[0][0])
    depth = (f"{depth_model_text(t)} mm deep (model)" if math.isfinite(t.depth_model_m)
             else f"{t.depth_m * 1e3:.1f} mm deep (paper's rule)")
    return f"Area {region + 1}: tumour at x {t.x_m * 1e3:.1f}, y {t.y_m * 1e3:.1f} mm, {depth}"


def _finding_text(t) -> str:
    """One tumour as the messages tell it (``session.detect.Tumour``, with its model-based depth if any)."""
    return (f"{t.source} map: tumour at x {t.x_m * 1e3:.1f} mm, y {t.y_m * 1e3:.1f} mm, first at "
            f"{t.first_level_N:g} N, depth {t.depth_m * 1e3:.1f} mm (paper's rule)"
            + (f", {depth_model_text(t)} mm (model, 90 % interval)" if math.isfinite(t.depth_model_m) else "")
            + f", z {t.score:.1f}")
