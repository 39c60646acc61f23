"""The tumours the console has told the surgeon of, one row each; a double-click sends the TSI over one."""

from __future__ import annotations

import math

from PySide6 import QtCore, QtWidgets

from session.detect import DetectParams
from session.export import depth_model_text

# headings on two lines: the table shares a laptop's left column with the jog, about 380 px
COLUMNS = ("Area", "Map", "x, y\n(mm)", "First\nat (N)", "Depth\nrule", "Depth, model\n(90 %, mm)", "z")
# Two tellings of one map this close are one tumour: the detector's own merge radius
SAME_TUMOUR_M = DetectParams().merge_radius_m
TOOLTIPS = (
    "The palpation areas whose findings told of it, numbered as on the whole-tissue map and in Messages",
    "Which map showed it: stiffness (Eq. 1, the paper's better detector) or force",
    "Where it lies: x along the tissue's length from its start, y across it (along the TSI's 15 elements)",
    "The lowest force level of the ramp at which it showed",
    "The depth by the paper's rule, in mm: the TSI indentation at that level (reads deep tumours shallow)",
    "The model-based depth: the sphere that best explains what the tumour did to the elements, with the range "
    "that holds the true depth 9 times in 10",
    "How many standard deviations of healthy tissue its strongest spot stood out by",
)


class FindingsTable(QtWidgets.QTableWidget):
    """Rows of :class:`session.detect.Tumour`, in the order told; ``move_requested(x_m, y_m)`` on a double-click."""

    move_requested = QtCore.Signal(float, float)

    def __init__(self, parent: QtWidgets.QWidget | None = None):
        super().__init__(0, len(COLUMNS), parent, objectName="findingsTable")
        self.setHorizontalHeaderLabels(COLUMNS)
        for column, tip in enumerate(TOOLTIPS):
            self.horizontalHeaderItem(column).setToolTip(tip)
        self.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.setSelectionBehavior(QtWidgets.QAbstractItemView.SelectionBehavior.SelectRows)
        self.verticalHeader().setVisible(False)
        self.horizontalHeader().setStretchLastSection(True)
        self.setToolTip("Double-click a tumour to move the TSI over it (lift the probe off the tissue first)")
        self._positions: list[tuple[float, float]] = []
        self.cellDoubleClicked.connect(lambda row, _: self.move_requested.emit(*self._positions[row]))

    def set_findings(self, told: list[tuple[int, object]]) -> None:
        """``told``: (area index from 0, tumour) for every tumour told, oldest first. The areas beside a tumour
        each tell of it: one row per tumour and map, with the newest telling's figures and every area that
        told it (the first screenshots listed the paper's three tumours eight times)."""
        rows: list[tuple[list[int], object]] = []
        for area, t in told:
            same = next((r for r in rows if r[1].source == t.source
                         and math.hypot(r[1].x_m - t.x_m, r[1].y_m - t.y_m) <= SAME_TUMOUR_M), None)
            if same is None:
                rows.append(([area], t))
            else:
                rows[rows.index(same)] = (sorted({*same[0], area}), t)
        self.setRowCount(len(rows))
        self._positions = [(t.x_m, t.y_m) for _, t in rows]
        for row, (areas, t) in enumerate(rows):
            rule = f"{t.depth_m * 1e3:.1f}" if math.isfinite(t.depth_m) else "—"
            model = depth_model_text(t) if math.isfinite(t.depth_model_m) else "—"
            cells = (", ".join(str(a + 1) for a in areas), t.source, f"{t.x_m * 1e3:.1f}, {t.y_m * 1e3:.1f}",
                     f"{t.first_level_N:g}", rule, model, f"{t.score:.1f}")
            for column, text in enumerate(cells):
                item = QtWidgets.QTableWidgetItem(text)
                if column != 1:
                    item.setTextAlignment(QtCore.Qt.AlignmentFlag.AlignRight | QtCore.Qt.AlignmentFlag.AlignVCenter)
                self.setItem(row, column, item)
        self.resizeColumnsToContents()


class FindingsPanel(QtWidgets.QWidget):
    """The findings table under what the tissue model behind them is doing while it is computed (the findings
    of an area wait for it: app/live_physics.py)."""

    def __init__(self, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self.table = FindingsTable()
        self._bar = QtWidgets.QProgressBar(objectName="findingsProgress")
        self._bar.setRange(0, 100)
        self._bar.setFormat("Computing findings… %p %")
        self._what = QtWidgets.QLabel(objectName="findingsProgressText", wordWrap=True)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        for widget in (self._bar, self._what, self.table):
            layout.addWidget(widget)
        self.show_progress(None)

    def show_progress(self, fraction: float | None, what: str = "") -> None:
        """``fraction`` of the tissue model computed, and what it is doing; None: none under way."""
        computing = fraction is not None
        self._bar.setVisible(computing)
        self._what.setVisible(computing)
        if computing:
            self._bar.setValue(round(100 * min(max(fraction, 0.0), 1.0)))
            self._what.setText(what)

    def progress_text(self) -> str | None:
        """What the bar and the line under it say; None while nothing is computed."""
        return f"{self._bar.text()}: {self._what.text()}" if self._bar.isVisibleTo(self) else None
