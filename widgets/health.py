"""Loop health at a glance: is the 1 kHz loop keeping its period, and is every device still talking?

The controller's driver reports :class:`~control.telemetry.LoopHealth` twice a second (rate, late ticks,
jitter, stalls, whether it got real-time priority); the tick rows carry the age of the newest reading of
each device. Each figure turns amber when it is worth a look and red when it is out of bounds: a device
older than the safety supervisor's timeout is what trips a stale-data fault.
"""

from __future__ import annotations

import math

import numpy as np
from PySide6 import QtWidgets

from control.config import SafetyLimits
from control.telemetry import LoopHealth

GOOD, WATCH, BAD = "#6ee07a", "#ffc37a", "#ff7b7b"
LATE_WATCH_PCT, LATE_BAD_PCT = 0.5, 2.0  # share of ticks more than 0.5 ms late
# Periods skipped by the stall policy: a stall of a few periods is a blip; one longer than the sensor's
# timeout is as long as a stale-data fault allows (the panel's missed-ticks row turns red there).
STALL_WATCH_MS = 10.0
VERDICT = {"good": "Loop OK", "watch": "Loop: check", "bad": "LOOP / DEVICE PROBLEM"}
AGE_REFRESH_EVERY = 6  # update the age readouts every this many ticks shown (10 Hz at 60 Hz)


def _whole(figure: str) -> str:
    """``figure`` kept on one line where the chip wraps its text: a narrow column breaks it between figures
    only ("late 3.27 %" is not split from its number)."""
    return figure.replace(" ", "\u00a0")


def health_summary(health: LoopHealth) -> str:
    """One line for the status bar."""
    return (f"loop {health.rate_hz:.0f} Hz · late > 0.5 ms: {health.late_over_0_5ms_pct:.2f} % · "
            f"p99 jitter {health.p99_abs_jitter_us:.0f} µs · missed {health.missed_ticks} · "
            f"longest stall {health.longest_stall_ms:.1f} ms · "
            + ("real-time priority" if health.rt_priority else "no real-time priority")
            + (f" · CPU {health.cpu}" if health.cpu is not None else "")
            + (f" · {health.warning}" if health.warning else ""))


class HealthPanel(QtWidgets.QWidget):
    """Child objectNames: ``loopRate``, ``lateTicks``, ``jitter``, ``missedTicks``, ``rtPriority``,
    ``rtWarning``, ``sensorAge``, ``masterAge``, ``slaveAge``. Each value label's ``level`` property is
    ``good``, ``watch`` or ``bad``."""

    def __init__(self, limits: SafetyLimits, rate_hz: float = 1000.0, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self._limits = limits
        self._rate_hz = rate_hz
        self._texts: dict[QtWidgets.QLabel, tuple[str, str]] = {}
        self._short: dict[str, str] = {}  # what overall() shows of each figure, once there is one
        self._controller_problem: str | None = None
        self._ticks_seen = 0
        grid = QtWidgets.QGridLayout(self)
        grid.setContentsMargins(6, 4, 6, 4)
        grid.setHorizontalSpacing(12)
        grid.setVerticalSpacing(3)
        rows = (("Loop rate", "loopRate"), ("Ticks > 0.5 ms late", "lateTicks"), ("p99 jitter", "jitter"),
                ("Missed ticks / longest stall", "missedTicks"), ("Real-time priority", "rtPriority"))
        self._labels: dict[str, QtWidgets.QLabel] = {}
        for r, (caption, name) in enumerate(rows):
            self._labels[name] = self._row(grid, r, caption, name)
        self._warning = QtWidgets.QLabel("", objectName="rtWarning", wordWrap=True)
        self._warning.setStyleSheet(f"color: {WATCH};")
        self._warning.hide()
        grid.addWidget(self._warning, len(rows), 0, 1, 2)
        header = QtWidgets.QLabel("Age of the newest reading")
        header.setStyleSheet("font-weight: bold; padding-top: 6px;")
        grid.addWidget(header, len(rows) + 1, 0, 1, 2)
        for r, (caption, name) in enumerate((("Tactile sensor", "sensorAge"), ("Master device", "masterAge"),
                                             ("Slave robot", "slaveAge")), start=len(rows) + 2):
            self._labels[name] = self._row(grid, r, caption, name)
        grid.setRowStretch(len(rows) + 5, 1)
        for label in self._labels.values():
            self._set(label, "—", "watch")

    @staticmethod
    def _row(grid: QtWidgets.QGridLayout, row: int, caption: str, name: str) -> QtWidgets.QLabel:
        grid.addWidget(QtWidgets.QLabel(caption), row, 0)
        value = QtWidgets.QLabel("—", objectName=name)
        value.setMinimumWidth(120)  # changing figures must not re-lay out the panel
        grid.addWidget(value, row, 1)
        return value

    def _set(self, label: QtWidgets.QLabel, text: str, level: str) -> None:
        if self._texts.get(label) == (text, level):
            return
        self._texts[label] = (text, level)
        label.setText(text)
        label.setProperty("level", level)
        label.setStyleSheet(f"color: {dict(good=GOOD, watch=WATCH, bad=BAD)[level]}; font-weight: bold;")

    def level(self, name: str) -> str:
        return self._labels[name].property("level")

    def overall(self) -> tuple[str, str]:
        """(worst level, two short lines) for a glance: the loop's rate and lateness, and each device's age.

        The one verdict on the loop's health: the status bar leads with the same words (:data:`VERDICT`).
        Every figure counts but real-time priority, whose absence is normal on a desktop machine; the
        reason it was refused does."""
        if self._controller_problem is not None:  # its figures are as old as its last report
            return "bad", f"{_whole(VERDICT['bad'])} · {self._controller_problem}"
        names = ("loopRate", "lateTicks", "jitter", "missedTicks", "sensorAge", "masterAge", "slaveAge")
        levels = [self.level(n) for n in names if n in self._short]
        if not levels:
            return "watch", "loop: no report yet"
        if self._warning.text() and not self._warning.isHidden():
            levels.append("watch")
        worst = "bad" if "bad" in levels else "watch" if "watch" in levels else "good"
        shown = ["loopRate", "lateTicks"] + (["missedTicks"] if self.level("missedTicks") != "good" else [])
        loop = " · ".join(_whole(self._short[n]) for n in shown if n in self._short)
        ages = " · ".join(_whole(f"{device} {self._short[n]}") for n, device in
                          (("sensorAge", "sensor"), ("slaveAge", "robot"), ("masterAge", "master")) if n in self._short)
        return worst, f"{_whole(VERDICT[worst])} · {loop}" + (f"\n{ages}" if ages else "")

    def show_controller_problem(self, problem: str | None) -> None:
        """The controller itself stopped or stopped answering (``problem`` in a few words), or None again."""
        self._controller_problem = problem

    def show_health(self, health: LoopHealth) -> None:
        L = self._labels
        rate_ok = abs(health.rate_hz - self._rate_hz) <= 0.01 * self._rate_hz
        self._set(L["loopRate"], f"{health.rate_hz:.0f} Hz", "good" if rate_ok else "bad")
        self._short["loopRate"] = f"{health.rate_hz:.0f} Hz"
        late = health.late_over_0_5ms_pct
        self._short["lateTicks"] = f"late {late:.2f} %"
        self._set(L["lateTicks"], f"{late:.2f} %",
                  "good" if late < LATE_WATCH_PCT else "watch" if late < LATE_BAD_PCT else "bad")
        jitter = health.p99_abs_jitter_us
        self._short["jitter"] = f"{jitter:.0f} µs"
        self._set(L["jitter"], f"{jitter:.0f} µs", "good" if jitter < 200 else "watch" if jitter < 500 else "bad")
        stall = health.longest_stall_ms
        self._short["missedTicks"] = f"missed {health.missed_ticks} (stall {stall:.0f} ms)"
        self._set(L["missedTicks"], f"{health.missed_ticks} / {stall:.1f} ms",
                  "good" if health.missed_ticks == 0 or stall <= STALL_WATCH_MS
                  else "watch" if stall <= 1e3 * self._limits.sensor_timeout_s else "bad")
        cpu = f", CPU {health.cpu}" if health.cpu is not None else ""
        self._set(L["rtPriority"], ("yes" if health.rt_priority else "no") + cpu,
                  "good" if health.rt_priority else "watch")
        self._warning.setVisible(bool(health.warning))
        if health.warning and self._warning.text() != health.warning:
            self._warning.setText(health.warning)

    def show_ages(self, tick: np.ndarray) -> None:
        """Device ages from the latest tick row; refreshed at a tenth of the display rate."""
        self._ticks_seen += 1
        if self._ticks_seen % AGE_REFRESH_EVERY != 1:
            return
        lim = self._limits
        for name, field, limit in (("sensorAge", "sensor_age_s", lim.sensor_timeout_s),
                                   ("masterAge", "master_age_s", lim.master_timeout_s),
                                   ("slaveAge", "slave_age_s", lim.slave_timeout_s)):
            age = float(tick[field])
            if math.isnan(age):
                self._set(self._labels[name], "none attached" if name == "masterAge" else "—", "good")
                self._short.pop(name, None)
            elif math.isinf(age):
                self._set(self._labels[name], "nothing received yet", "bad")
                self._short[name] = "silent"
            else:
                level = "good" if age <= 0.5 * limit else "watch" if age <= limit else "bad"
                self._set(self._labels[name], f"{age * 1e3:.0f} ms  (limit {limit * 1e3:.0f} ms)", level)
                self._short[name] = f"{age * 1e3:.0f} ms"
