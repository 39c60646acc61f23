"""The messages pane: everything the loop and the console said, newest at the bottom, with timestamps.

Each line carries the wall-clock time it arrived and, for the loop's events, when it happened on the
loop's clock, counted from the origin the window sets (its first tick, as on the force plot). Severity
shows as colour: errors (faults, a stopped controller) red, warnings (refusals, time-outs, aborted areas)
amber, successes (levels recorded, region done, fault cleared) green.
"""

from __future__ import annotations

import enum
import math
from datetime import datetime

from PySide6 import QtCore, QtGui, QtWidgets

from control.console_state import fault_name
from control.messages import (
    CommandApplied,
    CommandRefused,
    FaultCleared,
    FaultRaised,
    LevelRecorded,
    LevelTimedOut,
    Notice,
    PhaseChanged,
    RegionAborted,
    RegionDone,
    Source,
    SzChanged,
)

MAX_LINES = 2000


class Severity(enum.Enum):
    INFO = "info"
    OK = "ok"
    WARNING = "warning"
    ERROR = "error"


COLOURS = {Severity.INFO: "#e0e0e0", Severity.OK: "#6ee07a", Severity.WARNING: "#ffc37a",
           Severity.ERROR: "#ff7b7b"}


def describe_event(event) -> tuple[str, Severity] | None:
    """The messages-pane line for one control event; None for objects that are not events."""
    if isinstance(event, SzChanged):
        mode = "position control" if event.sz else "force control"
        who = {Source.OPERATOR: "by the operator", Source.MASTER: "at the master device",
               Source.CONTROLLER: "by the controller"}.get(event.source, "")
        return f"S_z = {event.sz} ({mode}) {who}".rstrip(), Severity.INFO
    if isinstance(event, PhaseChanged):
        text = f"Phase {event.phase.name}"
        if event.level >= 0:
            text += f", level {event.level + 1} of {event.n_levels}"
        return text, Severity.INFO
    if isinstance(event, LevelRecorded):
        r = event.record
        depth = f"{r.indentation_m * 1e3:.1f} mm" if math.isfinite(r.indentation_m) else "—"
        return (f"Region {r.region + 1}, level {r.level + 1} recorded: F_d {r.force_desired_N:.2f} N, "
                f"F_ts {r.force_measured_N:.2f} N, RMSE {r.rmse_N:.3f} N, depth {depth}, "
                f"settled in {r.settle_time_s:.1f} s"), Severity.OK
    if isinstance(event, RegionDone):
        if event.capped_N == event.capped_N:
            return (f"Region {event.region + 1} done, capped at {event.capped_N:g} N: {event.n_levels} levels "
                    f"recorded; {event.capped_why}"), Severity.WARNING
        return f"Region {event.region + 1} done: all {event.n_levels} levels recorded", Severity.OK
    if isinstance(event, RegionAborted):
        return f"Region {event.region + 1} aborted: {event.reason}", Severity.WARNING
    if isinstance(event, LevelTimedOut):
        return event.message, Severity.WARNING
    if isinstance(event, FaultRaised):
        return f"FAULT ({fault_name(event.kind)}): {event.message}", Severity.ERROR
    if isinstance(event, FaultCleared):
        return f"Fault cleared ({fault_name(event.kind)})", Severity.OK
    if isinstance(event, CommandRefused):
        return f"Refused {event.command_name}: {event.reason}", Severity.WARNING
    if isinstance(event, CommandApplied):
        return event.message, Severity.INFO
    if isinstance(event, Notice):
        return event.message, Severity.WARNING if event.level == "warning" else Severity.INFO
    return None


class MessagesPane(QtWidgets.QWidget):
    """Child objectNames: ``messageList`` (a QListWidget, one item per message), ``clearMessages``."""

    def __init__(self, parent: QtWidgets.QWidget | None = None, max_lines: int = MAX_LINES):
        super().__init__(parent)
        self._max = max_lines
        self._origin_s = 0.0
        self._list = QtWidgets.QListWidget(objectName="messageList")
        self._list.setWordWrap(True)
        self._list.setUniformItemSizes(False)
        self._list.setSelectionMode(QtWidgets.QAbstractItemView.SelectionMode.ExtendedSelection)
        self._list.setVerticalScrollMode(QtWidgets.QAbstractItemView.ScrollMode.ScrollPerPixel)
        # Follow the newest line unless the operator scrolled up to read an older one. Kept as a state the
        # operator's scrolling sets, not read off the scroll bar when a line arrives: the list lays its
        # wrapped lines out later (and not at all before it is shown), so the bar lags behind the lines.
        self._follow = True
        bar = self._list.verticalScrollBar()
        bar.valueChanged.connect(self._scrolled)
        bar.rangeChanged.connect(self._grown)
        font = self._list.font()
        font.setPointSizeF(max(font.pointSizeF(), 10.5))
        self._list.setFont(font)
        clear = QtWidgets.QPushButton("Clear", objectName="clearMessages")
        clear.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)
        clear.clicked.connect(self._list.clear)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(2, 2, 2, 2)
        layout.setSpacing(2)
        layout.addWidget(self._list, 1)
        row = QtWidgets.QHBoxLayout()
        row.addStretch(1)
        row.addWidget(clear)
        layout.addLayout(row)

    def set_time_origin(self, t_s: float) -> None:
        """Loop time shown as t = 0."""
        self._origin_s = t_s

    def add(self, text: str, severity: Severity = Severity.INFO, t_s: float | None = None) -> None:
        """Append one line; ``t_s`` is the loop time it refers to, if any."""
        stamp = datetime.now().strftime("%H:%M:%S")
        loop = f"  t {t_s - self._origin_s:7.2f} s" if t_s is not None and math.isfinite(t_s) else ""
        item = QtWidgets.QListWidgetItem(f"{stamp}{loop}   {text}")
        item.setForeground(QtGui.QBrush(QtGui.QColor(COLOURS[severity])))
        item.setData(QtCore.Qt.ItemDataRole.UserRole, severity.value)
        self._list.addItem(item)
        while self._list.count() > self._max:
            self._list.takeItem(0)
        if self._follow:  # now as well: it lays the new line out, so the bar is current when the operator scrolls
            self._list.scrollToBottom()

    def _scrolled(self, value: int) -> None:
        self._follow = value >= self._list.verticalScrollBar().maximum() - 2

    def _grown(self, _minimum: int, maximum: int) -> None:
        if self._follow:
            self._list.verticalScrollBar().setValue(maximum)

    def add_event(self, event) -> None:
        described = describe_event(event)
        if described is not None:
            self.add(described[0], described[1], getattr(event, "t_s", None))

    def lines(self) -> list[str]:
        return [self._list.item(i).text() for i in range(self._list.count())]

    def severities(self) -> list[str]:
        return [self._list.item(i).data(QtCore.Qt.ItemDataRole.UserRole) for i in range(self._list.count())]
