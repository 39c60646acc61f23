"""F_d against F_ts, and the TSI indentation depth, over the last tens of seconds.

The time axis does not scroll: samples are plotted against time since the start of a window of fixed
length, and when the newest sample reaches the window's end the window jumps forwards, keeping its last
quarter in view. Between jumps the axes, their ticks and the plot's layout stay put, so a new sample
repaints the curves and nothing else (a range that moves every frame makes pyqtgraph lay out and paint the
whole plot twice per frame). The y ranges are fixed too: forces from 0 to a margin above F_max, depth from
0 to a margin above the safety ceiling, drawn as a dashed line.

Times are shown from the first tick seen (the loop's clock is the host's monotonic clock, whose zero is
meaningless to an operator). Ticks arrive at 1 kHz; the plot keeps one sample per ``1 / SAMPLE_HZ`` (half
the tactile frame rate: a glance needs no more), so a 30 s window holds about 1500 points per curve.

What is repainted per frame is kept small on purpose: the grid is one static line item rather than the
axes' grid (which makes pyqtgraph repaint both axes whenever a curve changes), and the legend is a label
above the plot, outside the scene, rather than an item on top of the curves.
"""

from __future__ import annotations

import math

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from widgets.plot_style import (
    DEPTH_COLOUR,
    F_DESIRED_COLOUR,
    F_MEASURED_COLOUR,
    LIMIT_COLOUR,
    RECORDED_COLOUR,
    follow_palette,
)
from widgets.tactile_map import nice_step

SAMPLE_HZ = 50.0
KEEP_FRACTION = 0.25  # of the window still in view after a jump
_FORCE_MARGIN = 1.2


def _hex(rgb: tuple[int, int, int]) -> str:
    return "#%02x%02x%02x" % rgb


class _Series:
    """Columns of samples in preallocated arrays; drop everything before a time in one slice."""

    def __init__(self, capacity: int, columns: int):
        self._data = np.empty((capacity, columns))
        self.n = 0

    def extend(self, rows: np.ndarray) -> None:
        k = len(rows)
        if self.n + k > len(self._data):
            keep = max(0, len(self._data) - k)
            self._data[:keep] = self._data[self.n - keep:self.n]
            self.n = keep
            rows = rows[-len(self._data):]
            k = len(rows)
        self._data[self.n:self.n + k] = rows
        self.n += k

    def drop_before(self, t_s: float) -> None:
        view = self._data[: self.n]
        first = int(np.searchsorted(view[:, 0], t_s))
        if first:
            self._data[: self.n - first] = view[first:]
            self.n -= first

    def column(self, i: int) -> np.ndarray:
        return self._data[: self.n, i]

    def clear(self) -> None:
        self.n = 0


class HistoryPlots(QtWidgets.QWidget):
    """Call :meth:`add_ticks` with TICK_DTYPE rows and :meth:`mark_recorded` for each recorded level.

    Child objectNames: ``forceLegend``, ``forcePlot``, ``depthPlot``; scene items ``forceDesiredCurve``,
    ``forceMeasuredCurve``, ``recordedMarkers``, ``depthCurve``, ``depthLimit``.
    """

    def __init__(self, *, window_s: float = 30.0, force_max_N: float = 7.0, depth_limit_m: float = 0.016,
                 parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        if not (math.isfinite(window_s) and window_s >= 2.0):
            raise ValueError(f"history window must be at least 2 s, got {window_s!r}")
        self._window_s = window_s
        self._window_start: float | None = None  # in loop time
        self._origin_s: float | None = None  # loop time shown as 0
        self._last_t = -math.inf
        self._last_sample_k = -1
        self._series = _Series(int(window_s * SAMPLE_HZ * 1.2) + 64, 4)  # t, F_d, F_ts, depth
        self._marks = _Series(256, 2)
        self._dirty = False
        self._marks_dirty = False

        font = QtGui.QFont()
        font.setPointSize(10)
        self._force_plot = self._make_plot("forcePlot", "force (N)", font)
        self._depth_plot = self._make_plot("depthPlot", "depth (mm)", font)
        self._depth_plot.getPlotItem().setXLink(self._force_plot.getPlotItem())
        self._force_plot.getPlotItem().getAxis("bottom").setStyle(showValues=False)
        self._depth_plot.getPlotItem().setLabel("bottom", "time (s)")
        self._grids = {name: self._add_grid(plot) for name, plot in
                       (("force", self._force_plot), ("depth", self._depth_plot))}

        fitem = self._force_plot.getPlotItem()
        self._f_desired = pg.PlotCurveItem(pen=pg.mkPen(F_DESIRED_COLOUR, width=2.5), connect="finite")
        self._f_measured = pg.PlotCurveItem(pen=pg.mkPen(F_MEASURED_COLOUR, width=1.5), connect="finite")
        self._recorded = pg.ScatterPlotItem(size=10, symbol="o", pen=pg.mkPen("k"), brush=pg.mkBrush(RECORDED_COLOUR))
        for obj, name in ((self._f_desired, "forceDesiredCurve"), (self._f_measured, "forceMeasuredCurve"),
                          (self._recorded, "recordedMarkers")):
            obj.setObjectName(name)
            fitem.addItem(obj)
        self._legend = QtWidgets.QLabel(objectName="forceLegend", wordWrap=True)
        self._legend.setText(
            f"<span style='color:{_hex(F_DESIRED_COLOUR)}'>━━ F_d desired</span>&nbsp;&nbsp;&nbsp;"
            f"<span style='color:{_hex(F_MEASURED_COLOUR)}'>━━ F_ts measured</span>&nbsp;&nbsp;&nbsp;"
            f"<span style='color:{_hex(RECORDED_COLOUR)}'>●</span> level recorded&nbsp;&nbsp;&nbsp;"
            f"<span style='color:{_hex(DEPTH_COLOUR)}'>━━ TSI indentation depth</span>")

        ditem = self._depth_plot.getPlotItem()
        self._depth = pg.PlotCurveItem(pen=pg.mkPen(DEPTH_COLOUR, width=2), connect="finite")
        self._depth.setObjectName("depthCurve")
        ditem.addItem(self._depth)
        self._limit = pg.InfiniteLine(angle=0, movable=False,
                                      pen=pg.mkPen(LIMIT_COLOUR, width=1.5, style=QtCore.Qt.PenStyle.DashLine),
                                      label="limit", labelOpts={"position": 0.97, "color": LIMIT_COLOUR,
                                                                "anchors": [(1, 0), (1, 0)]})  # below it
        self._limit.setObjectName("depthLimit")
        ditem.addItem(self._limit)

        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.setSpacing(0)
        layout.addWidget(self._legend)
        layout.addWidget(self._force_plot, 3)
        layout.addWidget(self._depth_plot, 2)

        self.set_force_max_N(force_max_N)
        self.set_depth_limit_m(depth_limit_m)
        self._show_window_axes(0.0)
        self._apply_palette()

    # ---- construction --------------------------------------------------------------------------------

    def _make_plot(self, name: str, label: str, font: QtGui.QFont) -> pg.PlotWidget:
        plot = pg.PlotWidget()
        plot.setObjectName(name)
        item = plot.getPlotItem()
        item.setMenuEnabled(False)
        item.hideButtons()
        item.setMouseEnabled(x=False, y=False)
        item.setLabel("left", label)
        for side in ("left", "bottom"):
            item.getAxis(side).setTickFont(font)
        item.getAxis("left").setWidth(52)  # both plots' data areas line up
        item.getViewBox().setDefaultPadding(0.0)
        return plot

    @staticmethod
    def _add_grid(plot: pg.PlotWidget) -> pg.PlotCurveItem:
        grid = pg.PlotCurveItem(pen=pg.mkPen((255, 255, 255, 45), width=1), connect="pairs")
        grid.setZValue(-5)
        plot.getPlotItem().addItem(grid, ignoreBounds=True)
        return grid

    def _set_grid(self, name: str, top: float) -> list[float]:
        """Grid lines every 5 s and at round values up to ``top``; returns the values (the axis ticks)."""
        step = nice_step(top)
        ys = list(np.arange(0.0, top + 1e-9, step))
        xs = np.arange(0.0, self._window_s + 1e-9, 5.0)
        px = np.concatenate([np.repeat(xs, 2), np.tile([0.0, self._window_s], len(ys))])
        py = np.concatenate([np.tile([0.0, top], len(xs)), np.repeat(ys, 2)])
        self._grids[name].setData(px, py)
        return ys

    def _apply_palette(self) -> None:
        plots = (self._force_plot, self._depth_plot)
        follow_palette(self, plots, [plot.getPlotItem().getAxis(side) for plot in plots for side in ("left", "bottom")],
                       background=QtGui.QPalette.ColorRole.Base)

    def changeEvent(self, event: QtCore.QEvent) -> None:
        if event.type() == QtCore.QEvent.Type.PaletteChange:
            self._apply_palette()
        super().changeEvent(event)

    # ---- public API ----------------------------------------------------------------------------------

    def window_s(self) -> float:
        return self._window_s

    def window_start_s(self) -> float | None:
        """Loop time at the left edge of the plots (None before the first sample)."""
        return self._window_start

    def time_origin_s(self) -> float | None:
        """Loop time shown as 0 on the time axis: the first tick seen."""
        return self._origin_s

    def set_force_max_N(self, force_max_N: float) -> None:
        """Fix the force axis at [0, a margin above F_max]."""
        if not (math.isfinite(force_max_N) and force_max_N > 0):
            raise ValueError(f"force axis: F_max must be > 0, got {force_max_N!r}")
        top = force_max_N * _FORCE_MARGIN
        ticks = self._set_grid("force", top)
        item = self._force_plot.getPlotItem()
        item.getAxis("left").setTicks([[(v, f"{v:g}") for v in ticks], []])
        item.setYRange(-0.03 * top, top, padding=0.0)  # room for the "0" label at the bottom edge

    def set_depth_limit_m(self, limit_m: float) -> None:
        """The indentation ceiling: drawn as a dashed line, with the axis a little above it."""
        if not (math.isfinite(limit_m) and limit_m > 0):
            raise ValueError(f"depth axis: the limit must be > 0, got {limit_m!r}")
        mm = limit_m * 1e3
        self._limit.setValue(mm)
        self._limit.label.setFormat(f"limit {mm:g} mm")
        ticks = self._set_grid("depth", mm * 1.1)
        item = self._depth_plot.getPlotItem()
        item.getAxis("left").setTicks([[(v, f"{v:g}") for v in ticks], []])
        item.setYRange(-0.03 * mm * 1.1, mm * 1.1, padding=0.0)

    def add_ticks(self, ticks: np.ndarray) -> None:
        """Append TICK_DTYPE rows (oldest first); the curves are redrawn by :meth:`refresh`."""
        if not len(ticks):
            return
        t = ticks["t_s"]
        if t[0] < self._last_t:  # a new controller run: its clock starts again
            self.clear()
        # one sample per 1/SAMPLE_HZ of loop time, chosen by sample slot so chunk borders do not matter
        slot = np.floor(t * SAMPLE_HZ).astype(np.int64)
        first = np.ones(len(slot), dtype=bool)
        first[1:] = slot[1:] != slot[:-1]
        first &= slot > self._last_sample_k
        if first.any():
            rows = ticks[first]
            block = np.column_stack([rows["t_s"], rows["force_desired_N"], rows["force_measured_N"],
                                     rows["indentation_m"] * 1e3])
            self._series.extend(block)
            self._last_sample_k = int(slot[first][-1])
            self._dirty = True
        self._last_t = float(t[-1])
        if self._window_start is None:
            self._origin_s = float(t[0])
            self._set_window(self._origin_s)
        elif self._last_t > self._window_start + self._window_s:
            # whole seconds after the origin, so the tick labels stay round numbers
            shown = math.floor(self._last_t - self._origin_s - KEEP_FRACTION * self._window_s)
            self._set_window(self._origin_s + shown)

    def mark_recorded(self, t_s: float, force_N: float) -> None:
        """A level was recorded at loop time t_s with mean measured force force_N."""
        self._marks.extend(np.array([[t_s, force_N]]))
        self._marks_dirty = True

    def refresh(self) -> None:
        """Redraw the curves if new samples arrived (call once per display frame)."""
        start = self._window_start or 0.0
        if self._dirty:
            self._dirty = False
            s = self._series
            x = s.column(0) - start
            self._f_desired.setData(x, s.column(1))
            self._f_measured.setData(x, s.column(2))
            self._depth.setData(x, s.column(3))
        if self._marks_dirty:
            self._marks_dirty = False
            self._recorded.setData(self._marks.column(0) - start, self._marks.column(1))

    def clear(self) -> None:
        self._series.clear()
        self._marks.clear()
        self._window_start = None
        self._origin_s = None
        self._last_t = -math.inf
        self._last_sample_k = -1
        self._dirty = self._marks_dirty = True

    def sample_count(self) -> int:
        return self._series.n

    # ---- internals -----------------------------------------------------------------------------------

    def _set_window(self, start_s: float) -> None:
        self._window_start = start_s
        self._series.drop_before(start_s)
        self._marks.drop_before(start_s)
        self._show_window_axes(start_s)
        self._dirty = self._marks_dirty = True

    def _show_window_axes(self, start_s: float) -> None:
        self._force_plot.getPlotItem().setXRange(0.0, self._window_s, padding=0.0)
        step = 5.0 if self._window_s <= 40 else 10.0
        first = start_s - (self._origin_s if self._origin_s is not None else start_s)
        ticks = [(v, f"{first + v:.0f}") for v in np.arange(0.0, self._window_s + 1e-9, step)]
        for plot in (self._force_plot, self._depth_plot):
            plot.getPlotItem().getAxis("bottom").setTicks([ticks, []])
