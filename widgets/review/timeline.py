"""The session's timeline: measured and desired force, and the TSI indentation, against the time since
the session started (its first tick; the loop's own clock starts wherever the controller's did).

Zoomed out it draws the file's overview (min and max of every 1000 ticks, a zig-zag that reads as the
signal's envelope), so an hour is a few thousand points; once the visible span is at most
``full_res_span_s`` it reads that stretch of the 1 kHz stream from the file and draws every tick. Reading
follows the view after a short pause (pan and zoom do not read on every mouse event). Recorded levels
are dots on the force curve (click one to open it); faults are red lines.
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from session.format import EventKind
from session.reader import SessionFileError
from widgets.plot_style import DEPTH_COLOUR, F_DESIRED_COLOUR, F_MEASURED_COLOUR, follow_palette

_FIELDS = ["t_s", "force_measured_N", "force_desired_N", "indentation_m"]


def _envelope(t_start: np.ndarray, t_end: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    x = np.empty(2 * len(t_start))
    y = np.empty(2 * len(t_start))
    x[0::2], x[1::2] = t_start, t_end
    y[0::2], y[1::2] = lo, hi
    return x, y


class TimelineWidget(QtWidgets.QWidget):
    """``set_session(session)``; emits ``level_clicked(row)`` with the /levels row of a clicked dot."""

    level_clicked = QtCore.Signal(int)
    range_loaded = QtCore.Signal(str)  # "overview" or "full", after the curves were redrawn

    def __init__(self, parent: QtWidgets.QWidget | None = None, full_res_span_s: float = 20.0,
                 settle_ms: int = 80):
        super().__init__(parent)
        if full_res_span_s <= 0:
            raise ValueError(f"full_res_span_s must be > 0, got {full_res_span_s!r}")
        self.full_res_span_s = float(full_res_span_s)
        self._session = None
        self._mode = "overview"
        self._loaded: tuple[float, float] | None = None  # time span of the full-resolution data drawn
        self._origin_s = 0.0  # the loop time of the session's first tick: t = 0 on the axis
        self._overview = None

        self._layout = pg.GraphicsLayoutWidget()
        self._layout.setObjectName("timelinePlots")
        self._force = self._layout.addPlot(row=0, col=0)
        self._depth = self._layout.addPlot(row=1, col=0)
        self._depth.setXLink(self._force)
        for plot, label in ((self._force, "force (N)"), (self._depth, "indentation (mm)")):
            plot.setMenuEnabled(False)
            plot.showGrid(x=True, y=True, alpha=0.2)
            plot.setLabel("left", label)
            plot.getViewBox().setMouseEnabled(x=True, y=False)
        self._depth.setLabel("bottom", "time since the session started (s)")
        self._f_measured = self._force.plot(pen=pg.mkPen(F_MEASURED_COLOUR, width=1))
        self._f_desired = self._force.plot(pen=pg.mkPen(F_DESIRED_COLOUR, width=1))
        self._indent = self._depth.plot(pen=pg.mkPen(DEPTH_COLOUR, width=1), connect="finite")
        for curve in (self._f_measured, self._f_desired, self._indent):
            curve.setClipToView(True)
            curve.setDownsampling(auto=True, method="peak")
        self._levels = pg.ScatterPlotItem(size=9, brush=pg.mkBrush(255, 255, 255), pen=pg.mkPen("k"), hoverable=True)
        self._levels.setZValue(10)
        self._levels.sigClicked.connect(self._on_level_clicked)
        self._force.addItem(self._levels)
        self._faults: list[pg.InfiniteLine] = []

        self._settle = QtCore.QTimer(self)
        self._settle.setSingleShot(True)
        self._settle.setInterval(settle_ms)
        self._settle.timeout.connect(self._refresh)
        self._force.getViewBox().sigXRangeChanged.connect(lambda *_: self._settle.start())

        self._info = QtWidgets.QLabel("", objectName="timelineInfo")
        # The key sits under the plots, not in them: a legend inside covers a stretch of the ramps.
        key = QtWidgets.QLabel(" ".join(f'<span style="color: rgb{colour}">&#9644; {name}</span>&nbsp;'
                                        for colour, name in ((F_MEASURED_COLOUR, "measured F_ts"),
                                                             (F_DESIRED_COLOUR, "desired F_d"),
                                                             (DEPTH_COLOUR, "TSI indentation"))),
                               objectName="timelineKey")
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self._info, 1)
        row.addWidget(key)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self._layout, 1)
        layout.addLayout(row)
        self._apply_palette()

    # ---- public API ----------------------------------------------------------------------------------

    def mode(self) -> str:
        """"overview" (decimated) or "full" (every tick of the visible span)."""
        return self._mode

    def points_drawn(self) -> int:
        return len(self._f_measured.xData) if self._f_measured.xData is not None else 0

    def set_session(self, session) -> None:
        self._session = session
        self._loaded = None
        t0, t1 = session.time_span_s()
        self._origin_s = t0
        ov = session.overview()
        self._overview = ov
        for line in self._faults:
            self._force.removeItem(line)
        self._faults = []
        levels = session.levels
        self._levels.setData(x=levels["t_s"] - t0, y=levels["force_measured_N"], data=np.arange(len(levels)))
        for row in session.events[session.events["kind"] == EventKind.FAULT.encode()]:
            line = pg.InfiniteLine(pos=float(row["t_s"]) - t0, angle=90, pen=pg.mkPen((230, 60, 60), width=1.5))
            self._force.addItem(line)
            self._faults.append(line)
        self._draw_overview()
        self._force.setXRange(0.0, max(t1 - t0, 1e-3), padding=0.01)
        # The indentation's own scale, from the surface to the deepest press: between areas the probe rises
        # tens of millimetres above its last contact, which would squeeze the presses into a sliver.
        deepest = np.nanmax(ov["indentation_m_max"], initial=0.0) * 1e3 if len(ov) else 0.0
        self._depth.setYRange(-1.0, max(float(deepest), 1.0) * 1.08, padding=0.0)
        self._info.setText(f"{session.n_ticks:,} ticks over {t1 - t0:,.1f} s; zoom in below "
                           f"{self.full_res_span_s:g} s to see every tick")

    def show_range(self, t0_s: float, t1_s: float) -> None:
        """Show seconds ``t0_s`` to ``t1_s`` after the session started."""
        self._force.setXRange(t0_s, t1_s, padding=0.0)

    def visible_range_s(self) -> tuple[float, float]:
        return tuple(self._force.getViewBox().viewRange()[0])  # type: ignore[return-value]

    def clear(self) -> None:
        self._session = None
        self._origin_s = 0.0
        self._overview = None
        for curve in (self._f_measured, self._f_desired, self._indent):
            curve.setData([], [])
        self._levels.setData([], [])
        for line in self._faults:
            self._force.removeItem(line)
        self._faults = []
        self._info.setText("")

    # ---- internals -----------------------------------------------------------------------------------

    def _apply_palette(self) -> None:
        follow_palette(self, [self._layout], [plot.getAxis(side) for plot in (self._force, self._depth)
                                              for side in ("left", "bottom")],
                       background=QtGui.QPalette.ColorRole.Base)

    def changeEvent(self, event: QtCore.QEvent) -> None:
        if event.type() == QtCore.QEvent.Type.PaletteChange:
            self._apply_palette()
        super().changeEvent(event)

    def _draw_overview(self) -> None:
        ov = self._overview
        if ov is None:
            return
        start, end = ov["t_start_s"] - self._origin_s, ov["t_end_s"] - self._origin_s
        self._f_measured.setData(*_envelope(start, end, ov["force_measured_N_min"], ov["force_measured_N_max"]))
        self._f_desired.setData(*_envelope(start, end, ov["force_desired_N_min"], ov["force_desired_N_max"]))
        self._indent.setData(*_envelope(start, end, ov["indentation_m_min"] * 1e3, ov["indentation_m_max"] * 1e3))
        self._mode = "overview"
        self._loaded = None

    def _refresh(self) -> None:
        if self._session is None:
            return
        t0, t1 = self.visible_range_s()
        span = t1 - t0
        if span > self.full_res_span_s:
            if self._mode != "overview":
                self._draw_overview()
            self.range_loaded.emit("overview")
            return
        if self._loaded is not None and self._loaded[0] <= t0 and t1 <= self._loaded[1]:
            self.range_loaded.emit("full")
            return
        margin = min(span, self.full_res_span_s) / 2
        a, b = t0 - margin, t1 + margin
        try:
            rows = self._session.ticks_between(a + self._origin_s, b + self._origin_s, _FIELDS)
        except SessionFileError as err:  # a damaged stretch of the stream: say so, keep the overview
            self._info.setText(f"Cannot show every tick here: {err.problem}")
            self.range_loaded.emit(self._mode)
            return
        t = rows["t_s"] - self._origin_s
        self._f_measured.setData(t, rows["force_measured_N"])
        self._f_desired.setData(t, rows["force_desired_N"])
        self._indent.setData(t, rows["indentation_m"] * 1e3)
        self._mode = "full"
        self._loaded = (a, b)
        self.range_loaded.emit("full")

    def _on_level_clicked(self, _item, points, _event=None) -> None:
        if len(points):
            self.level_clicked.emit(int(points[0].data()))
