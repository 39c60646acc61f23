"""The reviewer: reopen a recorded session, browse what was recorded, stitch it and find the tumours.

Top, the timeline over the whole stream. Below, two tabs:

* **Regions × levels**: one row per palpated area, one column per force level; selecting a cell shows that
  record's pressure, stiffness (Eq. 1) and per-element indentation maps and its numbers.
* **Whole tissue**: the stitched map of the chosen force level and quantity, with the tumours found and,
  for a simulated session, the phantom's real ones, beside the same map's contrast (the probe's own pattern
  divided out, :mod:`session.flatfield`); the analysis parameters (cell size, false-alarm rate, accuracy, the
  detector's blob widths and radii, the physics and reference of the flat field, source of L0, the depth
  model's error), applied as they are edited, without touching the
  recording; the tumour table with each tumour's score and both depths.

The analysis runs in a worker (:mod:`widgets.review.analysis_worker`): the timeline, the table and the record
maps show as soon as the file is read, the status bar says what the analysis is doing, and the window turns to
the whole tissue's findings when they arrive, unless the reviewer has gone somewhere else meanwhile.

Read-only: the file is opened read-only and never written (exports go to other files).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from session.analysis import CONTRAST_MAPS, AnalysisParams, DepthModel, SessionAnalysis
from session.detect import SOURCES, DepthParams, DetectError, DetectParams, Tumour, widths_from_mm, widths_text_mm
from session.export import ExportError, depth_model_text
from session.flatfield import FlatFieldError, Reference
from session.format import FINDINGS_TOLD, EventKind
from session.reader import Session, SessionFileError, open_session
from session.stitch import L0Source, StitchError, StitchParams, StitchResult, level_groups
from tissue.face import element_offsets_m
from widgets.colormaps import colour_range
from widgets.map_painting import render_maps_png, write_report
from widgets.plot_style import dark_palette
from widgets.review.analysis_worker import AnalysisRequest, AnalysisWorker, PhysicsFactory, SessionModels
from widgets.review.map_view import GridMapView
from widgets.review.recent import RecentSessions
from widgets.review.timeline import TimelineWidget
from widgets.tactile_map import TactileMapWidget

# (label, LevelMap attribute, unit, display scale, detection source whose markers it shows)
QUANTITIES = (
    ("Force (pressure)", "pressure_pa", "kPa", 1e-3, "force"),
    ("Stiffness (Eq. 1)", "stiffness_pa", "kPa", 1e-3, "stiffness"),
    ("Indentation dL", "indentation_m", "mm", 1e3, "stiffness"),
    ("Coverage", "coverage", "x", 1.0, "stiffness"),
)
_L0_LABELS = {L0Source.ELEMENT: "each element's onset", L0Source.REGION: "one per region",
              L0Source.FIXED: "fixed thickness"}
_BANNER_STYLE = {"error": "background: #c01c28; color: white; padding: 6px; font-weight: bold;",
                 "warning": "background: #e5a50a; color: black; padding: 6px;"}


def _mm(value: float, decimals: int = 1) -> str:
    return f"{value * 1e3:.{decimals}f}" if math.isfinite(value) else "—"


class ReviewWindow(QtWidgets.QMainWindow):
    """Signals: ``session_opened(path)``, ``open_failed(message)``, ``analysis_done()`` (a new analysis is
    shown), ``analysing_changed(busy)``.

    Child objectNames: ``banner``, ``timeline``, ``tabs``, ``regionTable``, ``recordInfo``, ``pressureMap``,
    ``stiffnessMap``, ``indentationMap``, ``levelCombo``, ``quantityCombo``, ``stitchedMap``, ``cellSpin``,
    ``contrastMap``, ``falseAlarmSpin``, ``accuracySpin``, ``physicsCombo``, ``referenceButton``,
    ``referenceLabel``, ``l0Combo``, ``l0FixedSpin``, ``analysisSummary``, ``tumourTable``, and in the status
    bar ``analysisState`` and ``analysisProgress``.

    ``physics`` names the ways of knowing the probe's pattern on homogeneous tissue the composition root
    offers (label -> ``factory(session, progress)``, ``progress(fraction, message)`` as in
    :mod:`tissue.mechanics.progress`; the first is the default); without any, the flat field is the session's own
    baseline alone. ``depth_model`` makes the model-based depth estimator for a session (without it, or if it
    cannot be had, only the paper's rule gives depths). Both are called in the analysis worker's thread.
    """

    session_opened = QtCore.Signal(str)
    open_failed = QtCore.Signal(str)
    analysis_done = QtCore.Signal()
    analysing_changed = QtCore.Signal(bool)

    def __init__(self, path: str | Path | None = None, *, start_folder: str | Path | None = None,
                 settings: QtCore.QSettings | None = None,
                 physics: Mapping[str, PhysicsFactory] | None = None,
                 depth_model: Callable[[Session], DepthModel] | None = None,
                 parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self._physics_factories = dict(physics or {})
        self._depth_factory = depth_model
        self._models: SessionModels | None = None  # the open session's physics and depth model, made once
        self._worker = AnalysisWorker()
        self._generation = 0  # of the newest request: an older one's result is never shown
        self._analysing = False
        # whether the first analysis of the open session may still turn the window to its findings and the
        # record maps to their contrast: not once the reviewer has chosen where to look
        self._land_on_findings = False
        self._contrast_chosen = False
        self._reference: Reference | None = None
        self.setWindowTitle("Palpation Console — session review")
        self.setPalette(dark_palette())  # the console's scheme: a trace reads as the operator saw it
        self.recent = RecentSessions(settings)
        self._start_folder = Path(start_folder) if start_folder else Path.home()
        self._session: Session | None = None
        self._analysis: SessionAnalysis | None = None
        self._record: int | None = None  # the /levels row shown in the browser
        self._analysis_timer = QtCore.QTimer(self)
        self._analysis_timer.setSingleShot(True)
        self._analysis_timer.setInterval(150)
        self._analysis_timer.timeout.connect(self.reanalyse)
        # a session's first analysis starts from the event loop, once its maps have had the chance to paint
        self._open_timer = QtCore.QTimer(self)
        self._open_timer.setSingleShot(True)
        self._open_timer.setInterval(0)
        self._open_timer.timeout.connect(self.reanalyse)
        self._poll = QtCore.QTimer(self)  # the worker's progress and results, read at a rate the eye follows
        self._poll.setInterval(100)
        self._poll.timeout.connect(self._poll_analysis)
        self._build()
        self._build_menu()
        if path is not None:
            self.open_file(path)

    # ---- construction --------------------------------------------------------------------------------

    def _build(self) -> None:
        self._banner = QtWidgets.QLabel("", objectName="banner", wordWrap=True)
        self._banner.hide()
        self._timeline = TimelineWidget()
        self._timeline.setObjectName("timeline")
        self._timeline.setMinimumHeight(200)
        self._timeline.level_clicked.connect(self._looked_elsewhere)
        self._timeline.level_clicked.connect(self.select_record)

        self._tabs = QtWidgets.QTabWidget(objectName="tabs")
        self._tabs.addTab(self._build_browser(), "Regions × levels")
        self._tabs.addTab(self._build_stitched(), "Whole tissue")
        self._tabs.tabBarClicked.connect(self._looked_elsewhere)

        split = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        split.addWidget(self._timeline)
        split.addWidget(self._tabs)
        split.setStretchFactor(0, 1)
        split.setStretchFactor(1, 3)
        split.setSizes([260, 640])
        central = QtWidgets.QWidget()
        layout = QtWidgets.QVBoxLayout(central)
        layout.setContentsMargins(4, 4, 4, 4)
        layout.addWidget(self._banner)
        layout.addWidget(split, 1)
        self.setCentralWidget(central)
        # which file, and whether its array was calibrated, stay in view while the analysis says what it does
        self._file_info = QtWidgets.QLabel(objectName="fileInfo")
        self._file_info.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Preferred)
        self.statusBar().addPermanentWidget(self._file_info, 1)
        self._analysis_state = QtWidgets.QLabel(objectName="analysisState")
        self._analysis_progress = QtWidgets.QProgressBar(objectName="analysisProgress")
        self._analysis_progress.setMaximumWidth(160)
        for widget in (self._analysis_state, self._analysis_progress):
            widget.hide()
            self.statusBar().addPermanentWidget(widget)
        self.statusBar().showMessage("File > Open a session (.h5)")

    def _build_browser(self) -> QtWidgets.QWidget:
        self._region_table = QtWidgets.QTableWidget(objectName="regionTable")
        self._region_table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self._region_table.setSelectionMode(QtWidgets.QAbstractItemView.SelectionMode.SingleSelection)
        self._region_table.currentCellChanged.connect(lambda r, c, *_: self._cell_selected(r, c))
        self._region_table.cellPressed.connect(self._looked_elsewhere)
        self._record_info = QtWidgets.QLabel("", objectName="recordInfo", wordWrap=True)
        self._pressure_map = TactileMapWidget("Pressure", auto_floor_pa=1e3)
        self._pressure_map.setObjectName("pressureMap")
        self._stiffness_map = TactileMapWidget("Stiffness (Eq. 1)")
        self._stiffness_map.setObjectName("stiffnessMap")
        self._indentation_map = GridMapView("Indentation dL per element", unit="mm", scale=1e3, on_tsi=True)
        self._indentation_map.setObjectName("indentationMap")
        for record_map in (self._pressure_map, self._stiffness_map):
            record_map.findChild(QtWidgets.QCheckBox, "contrastView").clicked.connect(self._contrast_was_chosen)

        maps = QtWidgets.QWidget()
        grid = QtWidgets.QVBoxLayout(maps)
        grid.setContentsMargins(0, 0, 0, 0)
        grid.addWidget(self._record_info)
        grid.addWidget(self._pressure_map, 1)
        grid.addWidget(self._stiffness_map, 1)
        # dL under the table, where a short table leaves room: the two maps the paper reads get the height
        table_box = QtWidgets.QWidget()
        table_layout = QtWidgets.QVBoxLayout(table_box)
        table_layout.setContentsMargins(0, 0, 0, 0)
        table_layout.addWidget(QtWidgets.QLabel("TSI indentation (mm) per region and force level"))
        table_layout.addWidget(self._region_table, 1)
        self._indentation_map.setMaximumHeight(230)  # a 4 x 15 map on a column this wide needs no more
        table_layout.addWidget(self._indentation_map)
        split = QtWidgets.QSplitter(QtCore.Qt.Orientation.Horizontal)
        split.addWidget(table_box)
        split.addWidget(maps)
        split.setStretchFactor(1, 2)
        split.setSizes([440, 900])
        return split

    def _build_stitched(self) -> QtWidgets.QWidget:
        self._level_combo = QtWidgets.QComboBox(objectName="levelCombo")
        self._level_combo.currentIndexChanged.connect(lambda _: self._show_stitched())
        self._quantity_combo = QtWidgets.QComboBox(objectName="quantityCombo")
        for label, *_ in QUANTITIES:
            self._quantity_combo.addItem(label)
        self._quantity_combo.setCurrentIndex(1)
        self._quantity_combo.currentIndexChanged.connect(lambda _: self._show_stitched())
        self._stitched_map = GridMapView("Whole tissue")
        self._stitched_map.setObjectName("stitchedMap")
        self._contrast_map = GridMapView("Contrast", unit="%", scale=100.0, contrast=True)
        self._contrast_map.setObjectName("contrastMap")

        def spin(name: str, lo: float, hi: float, value: float, step: float, suffix: str, decimals: int = 2):
            box = QtWidgets.QDoubleSpinBox(objectName=name)
            box.setRange(lo, hi)
            box.setDecimals(decimals)
            box.setSingleStep(step)
            box.setValue(value)
            box.setSuffix(suffix)
            box.setKeyboardTracking(False)
            box.valueChanged.connect(lambda _: self._analysis_timer.start())
            return box

        self._cell_spin = spin("cellSpin", 0.1, 20.0, 1.0, 0.25, " mm")
        self._false_alarm_spin = spin("falseAlarmSpin", 0.01, 50.0, DetectParams.false_alarm_per_area * 100, 0.05,
                                      " % of areas", 2)
        self._false_alarm_spin.setToolTip("Chance that a palpated area of healthy tissue raises a spot")
        self._accuracy_spin = spin("accuracySpin", 0.1, 50.0, DetectParams.accuracy * 100, 0.5, " %", 1)
        self._accuracy_spin.setToolTip("The least relative scatter of healthy tissue from one loading to the next")
        self._widths_edit = QtWidgets.QLineEdit(widths_text_mm(DetectParams.kernel_widths_m),
                                                objectName="blobWidthsEdit")
        self._widths_edit.setToolTip("Widths (Gaussian sigma, mm, comma-separated) of the blobs the detector looks for")
        self._widths_edit.editingFinished.connect(self._analysis_timer.start)
        self._merge_spin = spin("mergeRadiusSpin", 0.5, 50.0, DetectParams.merge_radius_m * 1e3, 0.5, " mm", 1)
        self._merge_spin.setToolTip("Spots this close are one tumour, across areas and levels")
        self._fit_spin = spin("fitRadiusSpin", 2.0, 50.0, DetectParams.fit_radius_m * 1e3, 0.5, " mm", 1)
        self._fit_spin.setToolTip("The contrast this close to a tumour's strongest spot places it")
        self._depth_error_spin = spin("depthErrorSpin", 1.0, 200.0, DepthParams.model_error * 100, 5.0, " %", 0)
        self._depth_error_spin.setToolTip("The depth model's error in a tumour's predicted contrast: larger widens "
                                          "the depth intervals")
        self._depth_scale_spin = spin("depthScaleSpin", 0.0, 200.0, DepthParams.scale_error * 100, 5.0, " %", 0)
        self._depth_scale_spin.setToolTip("The part of the depth model's error every element near a tumour "
                                          "shares (one scale on all it predicts): larger widens the depth intervals")
        self._depth_law_spin = spin("depthLawSpin", 0.0, 100.0, DepthParams.law_spread * 100, 10.0, " %", 0)
        self._depth_law_spin.setToolTip("How unsure the depth model is of the tissue's law: a tumour's contrast "
                                        "taken to grow with the press this much slower to this much faster than "
                                        "its finite-strain model says; 0 trusts that model")
        self._physics_combo = QtWidgets.QComboBox(objectName="physicsCombo")
        for label in self._physics_factories:
            self._physics_combo.addItem(label)
        self._physics_combo.addItem("none (session baseline only)")
        self._physics_combo.currentIndexChanged.connect(lambda _: self._analysis_timer.start())
        self._reference_button = QtWidgets.QPushButton("Reference palpation…", objectName="referenceButton")
        self._reference_button.clicked.connect(self._reference_dialog)
        self._reference_label = QtWidgets.QLabel("none: baseline from this session", objectName="referenceLabel",
                                                 wordWrap=True)
        self._l0_combo = QtWidgets.QComboBox(objectName="l0Combo")
        for source in L0Source:
            self._l0_combo.addItem(_L0_LABELS[source], source.value)
        self._l0_fixed_spin = spin("l0FixedSpin", 0.5, 200.0, 25.0, 0.5, " mm")
        self._l0_fixed_spin.setEnabled(False)
        self._l0_combo.currentIndexChanged.connect(self._l0_changed)
        for combo in (self._physics_combo, self._l0_combo):  # long option names elide rather than widen the panel
            combo.setSizeAdjustPolicy(QtWidgets.QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
            combo.setMinimumContentsLength(16)
        form = QtWidgets.QFormLayout()
        form.addRow("Grid cell", self._cell_spin)
        form.addRow("False alarms", self._false_alarm_spin)
        form.addRow("Accuracy", self._accuracy_spin)
        form.addRow("Blob widths (mm)", self._widths_edit)
        form.addRow("Merge radius", self._merge_spin)
        form.addRow("Fit radius", self._fit_spin)
        form.addRow("Depth model error", self._depth_error_spin)
        form.addRow("Depth scale error", self._depth_scale_spin)
        form.addRow("Depth law spread", self._depth_law_spin)
        form.addRow("Flat-field physics", self._physics_combo)
        form.addRow(self._reference_button, self._reference_label)
        form.addRow("L0 (Eq. 1) from", self._l0_combo)
        form.addRow("Fixed L0", self._l0_fixed_spin)
        analysis = QtWidgets.QGroupBox("Analysis (the recording is not changed)", objectName="analysis")
        analysis.setLayout(form)
        self._summary = QtWidgets.QLabel("", objectName="analysisSummary", wordWrap=True)
        # beside this analysis, what the console told the surgeon while palpating (its notes in the session)
        self._told = QtWidgets.QLabel("", objectName="findingsTold", wordWrap=True)
        self._told.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        self._tumour_table = QtWidgets.QTableWidget(objectName="tumourTable")
        self._tumour_table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self._tumour_table.setSelectionBehavior(QtWidgets.QAbstractItemView.SelectionBehavior.SelectRows)
        self._tumour_table.verticalHeader().hide()
        # compact rows: three tumours and their header in the height a laptop screen leaves under the maps
        self._tumour_table.verticalHeader().setDefaultSectionSize(self.fontMetrics().height() + 8)
        self._tumour_table.horizontalHeader().setStretchLastSection(True)
        self._tumour_table.setToolTip("Select a tumour to see its map at the level where it first shows")
        self._tumour_table.currentCellChanged.connect(lambda r, *_: self._tumour_selected(r))

        side = QtWidgets.QWidget()
        side_layout = QtWidgets.QVBoxLayout(side)
        side_layout.setContentsMargins(0, 0, 0, 0)
        side_layout.addWidget(analysis)
        side_layout.addWidget(self._summary)
        side_layout.addWidget(self._told)
        side_layout.addStretch(1)
        # no wider than the form needs: the long summary wraps instead of taking the table's width
        side.setMaximumWidth(analysis.minimumSizeHint().width() + 2 * self.fontMetrics().height())
        # The tumour table spans the maps' width, where its nine columns are read without scrolling sideways.
        table_box = QtWidgets.QWidget()
        table_layout = QtWidgets.QVBoxLayout(table_box)
        table_layout.setContentsMargins(0, 0, 0, 0)
        table_layout.addWidget(QtWidgets.QLabel("Tumours (score: z over healthy tissue; depth by the paper's rule = "
                                                "TSI indentation at the first level; select one to see where it "
                                                "first shows)", wordWrap=True))
        table_layout.addWidget(self._tumour_table, 1)

        bar = QtWidgets.QHBoxLayout()
        bar.addWidget(QtWidgets.QLabel("Force level"))
        bar.addWidget(self._level_combo)
        bar.addSpacing(12)
        bar.addWidget(QtWidgets.QLabel("Map"))
        bar.addWidget(self._quantity_combo)
        bar.addStretch(1)
        left = QtWidgets.QWidget()
        left_layout = QtWidgets.QVBoxLayout(left)
        left_layout.setContentsMargins(0, 0, 0, 0)
        left_layout.addLayout(bar)
        maps = QtWidgets.QWidget()
        maps_layout = QtWidgets.QHBoxLayout(maps)
        maps_layout.setContentsMargins(0, 0, 0, 0)
        maps_layout.addWidget(self._stitched_map, 1)
        maps_layout.addWidget(self._contrast_map, 1)
        maps_over_table = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        maps_over_table.addWidget(maps)
        maps_over_table.addWidget(table_box)
        maps_over_table.setStretchFactor(0, 3)
        maps_over_table.setStretchFactor(1, 2)
        maps_over_table.setSizes([300, 170])
        left_layout.addWidget(maps_over_table, 1)
        page = QtWidgets.QWidget()
        page_layout = QtWidgets.QHBoxLayout(page)
        page_layout.setContentsMargins(0, 0, 0, 0)
        page_layout.addWidget(left, 1)
        page_layout.addWidget(side)  # the analysis form keeps its own width; the maps and table get the rest
        return page

    def _build_menu(self) -> None:
        menu = self.menuBar().addMenu("&File")
        menu.addAction("&Open…", QtGui.QKeySequence.StandardKey.Open, self._open_dialog)
        self._recent_menu = menu.addMenu("Open &Recent")
        self._recent_menu.aboutToShow.connect(lambda: self.recent.fill_menu(self._recent_menu, self.open_file))
        menu.addSeparator()
        self._export_maps_action = menu.addAction("Export &maps (PNG)…", self._export_maps_dialog)
        self._export_report_action = menu.addAction("Export &report (PDF)…", self._export_report_dialog)
        menu.addSeparator()
        menu.addAction("&Close session", QtGui.QKeySequence.StandardKey.Close, self.close_session)
        # the reviewer's window is the whole application under `review`, one of the console's windows in it
        quit_action = menu.addAction("&Quit", QtGui.QKeySequence.StandardKey.Quit, self.close)
        quit_action.setObjectName("quitAction")
        self._set_exports_enabled(False)

    def _set_exports_enabled(self, on: bool) -> None:
        self._export_maps_action.setEnabled(on)
        self._export_report_action.setEnabled(on)

    # ---- public API ----------------------------------------------------------------------------------

    @property
    def session(self) -> Session | None:
        return self._session

    @property
    def analysis(self) -> SessionAnalysis | None:
        return self._analysis

    @property
    def stitched(self) -> StitchResult | None:
        return self._analysis.stitched if self._analysis is not None else None

    @property
    def tumours(self) -> list[Tumour]:
        return list(self._analysis.tumours) if self._analysis is not None else []

    @property
    def analysing(self) -> bool:
        """Whether an analysis of the open session is on its way."""
        return self._analysing

    def open_file(self, path: str | Path) -> bool:
        """Open a session (closing the one shown); on a bad file, say why and keep the current one."""
        try:
            session = open_session(path)
            try:
                session.overview()  # the timeline's data: damage there is found before anything is replaced
            except SessionFileError:
                session.close()
                raise
        except SessionFileError as err:
            self._show_banner(f"Cannot open the session: {err}", "error")
            self.open_failed.emit(str(err))
            return False
        self.close_session()
        self._session = session
        self._show_session()
        self.session_opened.emit(str(session.path))
        return True

    def _show_session(self) -> None:
        session = self._session
        self.recent.add(session.path)
        self.setWindowTitle(f"{session.path.name} — session review")
        cal = session.array_calibration
        # whether the frames had the array's element pattern taken out says how far a small contrast can be
        # trusted: the reviewer sees it beside the file
        calibrated = (f"array calibrated {cal.created_utc[:10]} ({cal.presses} presses)" if cal is not None
                      else "array not calibrated")
        self.statusBar().clearMessage()
        self._file_info.setText(f"{session.path.name}  ·  {session.created_utc}  ·  {calibrated}")
        self._file_info.setToolTip(f"{session.path}\nformat v{session.format_version}, Palpation Console "
                                   f"{session.software_version}" + (f"\nArray calibration: {cal.summary()}"
                                                                    if cal is not None else ""))
        if session.warnings:
            self._show_banner("  ".join(session.warnings), "warning")
        else:
            self._banner.hide()
        self._fill_region_table()
        if len(session.levels):
            self.select_record(0)
        else:
            self._record_info.setText("No force level was recorded in this session.")
        self._timeline.set_session(session)
        self._show_told(session)
        for record_map in (self._pressure_map, self._stiffness_map):  # the readings, until there is a contrast
            record_map.set_contrast_view(False)
        self._models = SessionModels(session, self._physics_factories, self._depth_factory)
        self._land_on_findings, self._contrast_chosen = True, False
        self._summary.setText("")
        self._set_analysing(True, "starting", None)
        self._open_timer.start()

    def _show_told(self, session: Session) -> None:
        told = [(float(e["t_s"]), str(e["text"])[len(FINDINGS_TOLD):].strip()) for e in session.event_dicts()
                if e["kind"] == EventKind.NOTE and str(e["text"]).startswith(FINDINGS_TOLD)]
        self._told.setVisible(bool(told))
        self._told.setText("What the console told the surgeon:\n" + "\n".join(f"t = {t:.0f} s: {text}"
                                                                           for t, text in told))

    def close_session(self) -> None:
        self._analysis_timer.stop()
        self._open_timer.stop()
        self._worker.cancel()
        self._generation += 1  # whatever the worker still finishes is for this session: never shown
        self._set_analysing(False)
        if self._session is not None:
            self._session.close()  # the worker uses only what the reader loaded into memory
        self._session = None
        self._models = None
        self._analysis = None
        self._record = None
        self._timeline.clear()
        self._region_table.clear()
        self._region_table.setRowCount(0)
        self._region_table.setColumnCount(0)
        self._tumour_table.setRowCount(0)
        self._level_combo.clear()
        self._stitched_map.clear()
        self._contrast_map.clear()
        self._indentation_map.clear()
        for record_map in (self._pressure_map, self._stiffness_map):  # with their "max ..." headings
            record_map.set_data(np.full(record_map.data_pa().shape, np.nan))
            record_map.set_contrast(None)
        self._summary.setText("")
        self._record_info.setText("")
        self._banner.hide()
        self._set_exports_enabled(False)
        self.setWindowTitle("Palpation Console — session review")
        self._file_info.setText("")
        self._file_info.setToolTip("")
        self.statusBar().showMessage("File > Open a session (.h5)")

    def analysis_params(self) -> AnalysisParams:
        """The parameters in the analysis panel; raises StitchError / DetectError naming a bad one."""
        source = L0Source(self._l0_combo.currentData())
        stitch = StitchParams(cell_m=self._cell_spin.value() * 1e-3, l0_source=source,
                              l0_fixed_m=self._l0_fixed_spin.value() * 1e-3 if source is L0Source.FIXED else None)
        try:
            widths = widths_from_mm(self._widths_edit.text())
        except DetectError as err:
            raise DetectError(f"blob widths: {err}") from None
        detect = DetectParams(false_alarm_per_area=self._false_alarm_spin.value() / 100.0,
                              accuracy=self._accuracy_spin.value() / 100.0,
                              merge_radius_m=self._merge_spin.value() * 1e-3,
                              fit_radius_m=self._fit_spin.value() * 1e-3,
                              kernel_widths_m=widths)
        return AnalysisParams(stitch, detect, DepthParams(self._depth_error_spin.value() / 100.0,
                                                          self._depth_scale_spin.value() / 100.0,
                                                          self._depth_law_spin.value() / 100.0))

    def set_analysis(self, stitch: StitchParams, detect: DetectParams, depth: DepthParams = DepthParams()) -> None:
        """Put parameters into the panel and ask for their analysis now (``analysis_done`` when it is shown)."""
        widgets = (self._cell_spin, self._false_alarm_spin, self._accuracy_spin, self._l0_combo, self._l0_fixed_spin,
                   self._widths_edit, self._merge_spin, self._fit_spin, self._depth_error_spin,
                   self._depth_scale_spin, self._depth_law_spin)
        blocked = [w.blockSignals(True) for w in widgets]
        self._cell_spin.setValue(stitch.cell_m * 1e3)
        self._false_alarm_spin.setValue(detect.false_alarm_per_area * 100)
        self._accuracy_spin.setValue(detect.accuracy * 100)
        self._widths_edit.setText(widths_text_mm(detect.kernel_widths_m))
        self._merge_spin.setValue(detect.merge_radius_m * 1e3)
        self._fit_spin.setValue(detect.fit_radius_m * 1e3)
        self._depth_error_spin.setValue(depth.model_error * 100)
        self._depth_scale_spin.setValue(depth.scale_error * 100)
        self._depth_law_spin.setValue(depth.law_spread * 100)
        self._l0_combo.setCurrentIndex(self._l0_combo.findData(stitch.l0_source.value))
        if stitch.l0_fixed_m is not None:
            self._l0_fixed_spin.setValue(stitch.l0_fixed_m * 1e3)
        self._l0_fixed_spin.setEnabled(stitch.l0_source is L0Source.FIXED)
        for w, b in zip(widgets, blocked):
            w.blockSignals(b)
        self.reanalyse()

    def reanalyse(self) -> None:
        """Ask for the analysis with the panel's parameters (the file is only read); it replaces any still on its
        way, and ``analysis_done`` says when it is shown."""
        self._analysis_timer.stop()
        self._open_timer.stop()
        if self._session is None:
            return
        try:
            params = self.analysis_params()
        except (StitchError, DetectError) as err:
            self._summary.setText(f"<b>Not applied:</b> {err}")
            return
        label = self._physics_combo.currentText()
        self._generation += 1
        self._worker.submit(AnalysisRequest(self._generation, self._models,
                                            label if label in self._physics_factories else None, params,
                                            self._reference))
        self._set_analysing(True, "waiting for the previous analysis", None)

    def _poll_analysis(self) -> None:
        for request in self._worker.take_finished():
            if request.generation == self._generation:
                self._finish(request)
        request = self._worker.running()
        if self._analysing and request is not None and request.generation == self._generation:
            self._set_analysing(True, *request.progress)

    def _finish(self, request: AnalysisRequest) -> None:
        outcome = request.outcome
        self._set_analysing(False)
        if outcome is None:
            return
        if outcome.error is not None:
            self._summary.setText(f"<b>The analysis failed:</b> {outcome.error}")
            raise outcome.error
        if outcome.not_applied:
            self._summary.setText(f"<b>Not applied:</b> {outcome.not_applied}")
            return
        first = self._analysis is None
        self._analysis = outcome.analysis
        session = self._session
        if outcome.problems:  # after what the file itself said (truncated, did not end cleanly), not in its place
            self._show_banner("  ".join([*session.warnings, *outcome.problems]), "warning")
        stitched = self._analysis.stitched
        keep = self._level_combo.currentIndex()
        blocked = self._level_combo.blockSignals(True)
        self._level_combo.clear()
        for lm in stitched.levels:
            self._level_combo.addItem(f"{lm.force_N:g} N", lm.index)
        if stitched.levels:
            last = len(stitched.levels) - 1
            self._level_combo.setCurrentIndex(keep if 0 <= keep <= last else last)
        self._level_combo.blockSignals(blocked)
        self._fill_tumour_table()
        self._show_stitched()
        if first and not self._contrast_chosen:
            # The raw maps' brightest elements are the face's own edge rows; what a reviewer looks for is what
            # differs from healthy tissue, so the record maps turn to the contrast once there is one.
            for record_map in (self._pressure_map, self._stiffness_map):
                record_map.set_contrast_view(True)
        if self._record is not None:
            self._show_record(self._record)  # its stiffness depends on the L0 source
        if self._land_on_findings:  # what the reviewer opened the session for, unless they went elsewhere first
            self._tabs.setCurrentIndex(1)
        self._land_on_findings = False
        self._set_exports_enabled(True)
        self.analysis_done.emit()

    def _set_analysing(self, busy: bool, step: str = "", fraction: float | None = None) -> None:
        """The status bar's account of the analysis: what it is doing and how far, while it works."""
        if busy:
            self._analysis_state.setText(f"Analysing… ({step})")
            bar = self._analysis_progress
            if fraction is None:
                bar.setRange(0, 0)  # busy, no measure of how far
            else:
                bar.setRange(0, 100)
                bar.setValue(round(fraction * 100))
            if self._analysis is None:
                self._summary.setText("Analysing… the tumours and the whole-tissue maps show here when it is done.")
            if not self._poll.isActive():
                self._poll.start()
        else:
            self._poll.stop()
        self._analysis_state.setVisible(busy)
        self._analysis_progress.setVisible(busy)
        if busy != self._analysing:
            self._analysing = busy
            self._tabs.setTabText(1, "Whole tissue (analysing…)" if busy else "Whole tissue")
            self.analysing_changed.emit(busy)

    def _looked_elsewhere(self, *_) -> None:
        self._land_on_findings = False

    def _contrast_was_chosen(self) -> None:
        self._contrast_chosen = True

    def set_reference(self, path: str | Path | None) -> bool:
        """Use a saved reference palpation as the flat field's baseline (None: the session's own); False,
        with the reason in the banner, when the file is not a reference for this array."""
        if path is None:
            self._reference = None
            self._reference_label.setText("none: baseline from this session")
        else:
            shape = ((tuple(self._session.levels.dtype["pressure_pa"].shape)) if self._session is not None
                     else (4, 15))
            try:
                self._reference = Reference.load(path, shape)
            except FlatFieldError as err:
                self._show_banner(str(err), "error")
                return False
            self._reference_label.setText(f"{Path(path).name}: {self._reference.areas} areas, "
                                          f"{len(self._reference.forces_N)} levels")
        self.reanalyse()
        return True

    def _reference_dialog(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Reference palpation", str(self._start_folder),
                                                        "Reference palpation (*.json);;All files (*)")
        if path:
            self.set_reference(path)

    def select_record(self, row: int) -> None:
        """Show /levels row ``row`` in the regions × levels browser."""
        session = self._session
        if session is None or not 0 <= row < len(session.levels):
            return
        for r in range(self._region_table.rowCount()):
            for c in range(self._region_table.columnCount()):
                item = self._region_table.item(r, c)
                if item is not None and item.data(QtCore.Qt.ItemDataRole.UserRole) == row:
                    if (self._region_table.currentRow(), self._region_table.currentColumn()) != (r, c):
                        self._region_table.setCurrentCell(r, c)
                    self._tabs.setCurrentIndex(0)
                    break
        self._show_record(row)

    def select_level(self, index: int) -> None:
        self._level_combo.setCurrentIndex(index)

    def set_quantity(self, attribute: str) -> None:
        names = [q[1] for q in QUANTITIES]
        if attribute not in names:
            raise ValueError(f"unknown map {attribute!r} (known: {', '.join(names)})")
        self._quantity_combo.setCurrentIndex(names.index(attribute))

    def export_maps(self, path: str | Path) -> None:
        if self._analysis is not None:
            render_maps_png(path, self._analysis)

    def export_report(self, path: str | Path) -> None:
        if self._analysis is not None:
            write_report(path, self._analysis)

    # ---- internals -----------------------------------------------------------------------------------

    def _show_banner(self, text: str, kind: str) -> None:
        self._banner.setText(text)
        self._banner.setStyleSheet(_BANNER_STYLE[kind])
        self._banner.show()

    def _open_dialog(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Open a session", str(self._start_folder),
                                                        "Sessions (*.h5 *.hdf5);;All files (*)")
        if path:
            self.open_file(path)

    def _export_maps_dialog(self) -> None:
        self._export_dialog("Export maps", "maps.png", "PNG images (*.png)", self.export_maps)

    def _export_report_dialog(self) -> None:
        self._export_dialog("Export report", "report.pdf", "PDF (*.pdf);;PNG images (*.png)", self.export_report)

    def _export_dialog(self, title: str, name: str, filters: str, write) -> None:
        base = self._session.path.with_suffix("") if self._session else self._start_folder / "session"
        path, _ = QtWidgets.QFileDialog.getSaveFileName(self, title, f"{base}-{name}", filters)
        if not path:
            return
        try:
            write(path)
        except ExportError as err:
            self._show_banner(str(err), "error")
            return
        self.statusBar().showMessage(f"Wrote {path}", 8000)

    def _l0_changed(self) -> None:
        self._l0_fixed_spin.setEnabled(self._l0_combo.currentData() == L0Source.FIXED.value)
        self._analysis_timer.start()

    def _fill_region_table(self) -> None:
        session = self._session
        table = self._region_table
        groups = level_groups(session.levels)
        column_of = {}
        for c, (_force, rows) in enumerate(groups):
            for row in rows:
                column_of[int(row)] = c
        regions = session.regions()
        table.setRowCount(len(regions))
        table.setColumnCount(len(groups))
        table.setHorizontalHeaderLabels([f"{force:g} N" for force, _ in groups])
        table.setVerticalHeaderLabels([f"R{e.region + 1} ({e.centre_xy_m[0] * 1e3:.0f}, "
                                       f"{e.centre_xy_m[1] * 1e3:.0f}) {e.outcome}" for e in regions])
        depth = session.levels["indentation_m"]
        for r, entry in enumerate(regions):
            for row in entry.rows:
                item = QtWidgets.QTableWidgetItem(_mm(float(depth[row]), 2))
                item.setData(QtCore.Qt.ItemDataRole.UserRole, int(row))
                item.setToolTip("TSI indentation at this level; select to see the maps")
                table.setItem(r, column_of[int(row)], item)
        table.resizeColumnsToContents()

    def _cell_selected(self, r: int, c: int) -> None:
        item = self._region_table.item(r, c) if r >= 0 and c >= 0 else None
        if item is not None:
            self._show_record(int(item.data(QtCore.Qt.ItemDataRole.UserRole)))

    def _show_record(self, row: int) -> None:
        session = self._session
        self._record = row
        rec = session.levels[row]
        stitched = self.stitched
        stiffness_all = stitched.stiffness_pa if stitched is not None else session.levels["stiffness_pa"]
        # One colour range for every record at this force (pressure) or in the session (stiffness), so
        # records compare at a glance; the operator can still unlock it.
        same_force = np.isclose(session.levels["force_desired_N"], rec["force_desired_N"], atol=5e-4)
        pressures = session.levels["pressure_pa"][same_force]
        for widget, values, pool in ((self._pressure_map, rec["pressure_pa"], pressures),
                                     (self._stiffness_map, stiffness_all[row], stiffness_all)):
            lo, hi = colour_range(pool)
            widget.lock_levels(lo, hi)
            widget.set_data(values)
        for widget, source in ((self._pressure_map, "force"), (self._stiffness_map, "stiffness")):
            if self._analysis is None:
                widget.set_contrast(None)
            else:
                found = self._analysis.contrasts[source]
                widget.set_contrast(found.contrast[row], self._spots_on(row, source), found.sigma[row])
        x, y, z = (float(v) for v in rec["tsi_position_m"])
        rows, cols = rec["dL_m"].shape
        half_x, half_y = rows * session.pitch_m / 2, cols * session.pitch_m / 2
        # on the TSI, as the pressure and stiffness maps above it
        self._indentation_map.set_map(rec["dL_m"], (-half_x, half_x, -half_y, half_y))
        n_levels = int(np.count_nonzero(session.levels["region"] == rec["region"]))
        self._record_info.setText(
            f"<b>Region {int(rec['region']) + 1}, level {int(rec['level']) + 1}</b> ({n_levels} recorded): "
            f"F_d {rec['force_desired_N']:.2f} N, F_ts {rec['force_measured_N']:.3f} N, RMSE {rec['rmse_N']:.3f} N, "
            f"settled in {rec['settle_time_s']:.2f} s, {rec['t_s'] - session.time_span_s()[0]:.2f} s into the session; "
            f"TSI at ({x * 1e3:.1f}, {y * 1e3:.1f}, "
            f"{z * 1e3:.1f}) mm; TSI indentation {_mm(float(rec['indentation_m']), 2)} mm")

    def _spots_on(self, row: int, source: str) -> tuple[tuple[int, int], ...]:
        """The elements (row, col) of record ``row`` nearest the spots of the ``source`` map's tumours there."""
        rec = self._session.levels[row]
        rows, cols = rec["pressure_pa"].shape
        centres = element_offsets_m(rows, cols, self._session.pitch_m) + np.asarray(rec["tsi_position_m"][:2])
        out = []
        for tumour in self._analysis.tumours:
            for spot in tumour.spots:
                if tumour.source == source and spot.record == row:
                    nearest = np.argmin(np.hypot(centres[..., 0] - spot.x_m, centres[..., 1] - spot.y_m))
                    out.append(tuple(int(i) for i in np.unravel_index(nearest, (rows, cols))))
        return tuple(out)

    def _show_stitched(self) -> None:
        stitched = self.stitched
        if stitched is None or not stitched.levels:
            self._stitched_map.clear()
            self._contrast_map.clear()
            return
        index = max(0, self._level_combo.currentIndex())
        lm = stitched.levels[index]
        label, attribute, unit, scale, source = QUANTITIES[self._quantity_combo.currentIndex()]
        self._stitched_map.set_unit(unit, scale)
        self._stitched_map.set_map(lm.quantity(attribute), stitched.grid.extent_m)
        self._stitched_map.set_title(f"{label} at {lm.force_N:g} N — {len(lm.records)} regions, TSI indentation "
                                     f"{_mm(lm.tsi_indentation_m, 2)} mm, "
                                     f"{stitched.coverage_text(self._session.tissue_extent_m, index)}")
        found = [(t.x_m, t.y_m) for t in self._analysis.tumours
                 if t.source == source and lm.force_N >= t.first_level_N - 1e-9]
        truth = [(float(g["x_m"]), float(g["y_m"]), float(g.get("diameter_m", 8e-3)))
                 for g in (self._session.ground_truth if self._session else [])]
        self._stitched_map.set_markers(found, truth)
        contrast = lm.extra.get(CONTRAST_MAPS[source])
        if contrast is None:
            self._contrast_map.clear()
        else:
            self._contrast_map.set_map(contrast, stitched.grid.extent_m)
            self._contrast_map.set_title(f"{source.capitalize()} contrast at {lm.force_N:g} N (measured / expected "
                                         "on homogeneous tissue − 1)")
            self._contrast_map.set_markers(found, truth)

    def _fill_tumour_table(self) -> None:
        analysis = self._analysis
        session, tumours = analysis.session, analysis.tumours
        # units on a second line: the columns are as wide as their figures, and all fit beside the maps
        headers = ["Map", "x\n(mm)", "y\n(mm)", "Score\n(z)", "Contrast\n(%)", "First level\n(N)",
                   "Depth, rule\n(mm)", "Depth, model\n(mm, 90 %)"]
        if analysis.has_ground_truth:
            headers.append("True tumour")
            found, fp = analysis.found_count(), analysis.false_positives
            truth_text = (f" Ground truth: of the {analysis.palpated_count()} palpated tumours (of "
                          f"{len(session.ground_truth)}), the stiffness map found {found['stiffness']} and the force "
                          f"map {found['force']}; false positives {fp['stiffness']} and {fp['force']}.")
        else:
            truth_text = ""
        table = self._tumour_table
        table.setColumnCount(len(headers))
        table.setHorizontalHeaderLabels(headers)
        table.setRowCount(len(tumours))
        for k, t in enumerate(tumours):
            cells = [t.source, _mm(t.x_m), _mm(t.y_m), f"{t.score:.1f}", f"{t.contrast * 100:+.0f}",
                     f"{t.first_level_N:g}", _mm(t.depth_m, 2), depth_model_text(t)]
            if analysis.has_ground_truth:
                m = analysis.truth_of(k)
                cells.append(f"#{m.truth_index + 1}, {m.depth_m * 1e3:.1f} mm deep, {m.error_xy_m * 1e3:.1f} mm off"
                             if m is not None else "none (false positive)")
            for c, text in enumerate(cells):
                table.setItem(k, c, QtWidgets.QTableWidgetItem(text))
        table.resizeColumnsToContents()
        counts = {s: sum(1 for t in tumours if t.source == s) for s in SOURCES}
        self._summary.setText(f"{counts['stiffness']} tumour(s) in the stiffness map, {counts['force']} in the force "
                              f"map, over {len(analysis.stitched.levels)} force levels.{truth_text} Flat field: "
                              f"{analysis.flat_field}.")

    def _tumour_selected(self, row: int) -> None:
        tumours = self.tumours
        if not 0 <= row < len(tumours):
            return
        tumour = tumours[row]
        self.set_quantity("pressure_pa" if tumour.source == "force" else "stiffness_pa")
        forces = self.stitched.level_forces_N()
        self.select_level(int(np.argmin(np.abs(np.asarray(forces) - tumour.first_level_N))))

    def closeEvent(self, event: QtGui.QCloseEvent) -> None:
        self.close_session()
        super().closeEvent(event)
