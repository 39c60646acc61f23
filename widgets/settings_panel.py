"""Ramp settings and impedance gains, edited in the console and validated before anything is sent.

Every edit is checked at once with the same validation the configuration file goes through
(:class:`control.config.RampSettings`, :class:`control.config.ImpedanceGains`): an invalid combination is
refused with the reason, in words, next to the fields, and cannot be applied. A valid one is sent as a
request; the controller may still refuse it (settings change only between areas), and the panel shows
what it answered. The gains are shown at all times but can only be edited once unlocked, and lock again
once applied: they change how the robot responds to the tissue. What is applied, pending or refused is
the console's state (:class:`control.console_state.Setting`), shown here with :meth:`RampEditor.show_setting`.
"""

from __future__ import annotations

from collections.abc import Callable

from PySide6 import QtCore, QtWidgets

from control.config import ImpedanceGains, RampSettings
from control.console_state import Setting
from hardware.settings import ConfigError

# (field, label, unit, decimals, maximum)
RAMP_FIELDS = (
    ("force_min_N", "F_min", "N", 2, 50.0),
    ("force_max_N", "F_max", "N", 2, 50.0),
    ("force_step_N", "δF", "N", 2, 50.0),
    ("rmse_threshold_N", "ε (RMSE)", "N", 3, 10.0),
    ("settle_window_s", "settle window", "s", 2, 10.0),
    ("min_settle_s", "minimum settle", "s", 2, 30.0),
    ("level_timeout_s", "level timeout", "s", 1, 120.0),
)
_RAMP_LABELS = {name: label for name, label, *_ in RAMP_FIELDS}
AXES = "xyz"
# (field, label, unit, decimals, maximum)
GAIN_FIELDS = (
    ("mass_kg", "M_d", "kg", 2, 100.0),
    ("damping_N_s_m", "B_d", "N·s/m", 1, 1e4),
    ("stiffness_N_m", "K_d", "N/m", 0, 1e6),
)
_GAIN_LABELS = {name: label for name, label, *_ in GAIN_FIELDS}
ERROR_STYLE = "color: #ff7b7b; font-weight: bold;"
OK_STYLE = "color: #b0b0b0;"


def _spin(name: str, unit: str, decimals: int, maximum: float) -> QtWidgets.QDoubleSpinBox:
    spin = QtWidgets.QDoubleSpinBox(objectName=name)
    spin.setDecimals(decimals)
    spin.setRange(0.0, maximum)  # 0 is typeable so it can be refused with a reason, not silently clamped
    spin.setSingleStep(10 ** -decimals * (5 if decimals else 100))
    spin.setSuffix(f" {unit}")
    spin.setKeyboardTracking(False)
    spin.setMinimumWidth(110)
    return spin


def _describe(err: ConfigError, labels: dict[str, str]) -> str:
    key = err.key.split("[")[0]
    axis = err.key[len(key):]
    label = labels.get(key, key)
    if axis:
        label += f" {AXES[int(axis.strip('[]'))]}"
    problem = err.problem
    for name, text in labels.items():
        problem = problem.replace(name, text)
    return f"{label}: {problem}"


def _refuse(summary: QtWidgets.QLabel, apply: QtWidgets.QPushButton, problem: str) -> None:
    """Edited values the settings refuse: say why, and let nothing be applied."""
    summary.setText("Refused — " + problem)
    summary.setStyleSheet(ERROR_STYLE)
    apply.setEnabled(False)


def _show_status(label: QtWidgets.QLabel, setting: Setting) -> None:
    """What the controller answered about ``setting``; nothing until something was asked."""
    if setting.pending is not None:
        text, style = "Sent; waiting for the controller…", OK_STYLE
    elif setting.refusal is not None:
        text, style = f"Not applied — the controller refused: {setting.refusal}", ERROR_STYLE
    elif label.text():
        text, style = "Applied.", OK_STYLE
    else:
        return
    label.setText(text)
    label.setStyleSheet(style)


class RampEditor(QtWidgets.QWidget):
    """Signal ``apply_requested(RampSettings)``. Child objectNames: one spin box per field of
    :class:`RampSettings` (``force_min_N``, ...), ``rampApply``, ``rampRevert``, ``rampSummary`` (the levels,
    or why the values are refused), ``rampStatus`` (what the controller answered)."""

    apply_requested = QtCore.Signal(object)

    def __init__(self, ramp: RampSettings, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self._applied = ramp
        self._shown: tuple | None = None
        self._spins: dict[str, QtWidgets.QDoubleSpinBox] = {}
        form = QtWidgets.QFormLayout()
        form.setLabelAlignment(QtCore.Qt.AlignmentFlag.AlignRight)
        for name, label, unit, decimals, maximum in RAMP_FIELDS:
            spin = _spin(name, unit, decimals, maximum)
            spin.valueChanged.connect(self._validate)
            self._spins[name] = spin
            form.addRow(label, spin)
        self._summary = QtWidgets.QLabel("", objectName="rampSummary", wordWrap=True)
        self._status = QtWidgets.QLabel("", objectName="rampStatus", wordWrap=True)
        self._status.setStyleSheet(OK_STYLE)
        self._apply = QtWidgets.QPushButton("Apply ramp", objectName="rampApply")
        self._apply.clicked.connect(self._request)
        revert = QtWidgets.QPushButton("Revert", objectName="rampRevert")
        revert.setToolTip("Show the ramp the controller is using")
        revert.clicked.connect(lambda: self.show_ramp(self._applied))
        buttons = QtWidgets.QHBoxLayout()
        buttons.addWidget(self._apply)
        buttons.addWidget(revert)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        layout.addLayout(form)
        layout.addWidget(self._summary)
        layout.addLayout(buttons)
        layout.addWidget(self._status)
        layout.addStretch(1)
        self.show_ramp(ramp)

    def applied(self) -> RampSettings:
        return self._applied

    def show_setting(self, setting: Setting) -> None:
        """What the controller has in force, what it was asked for and has not answered, and a refusal."""
        shown = (setting.applied, setting.pending, setting.refusal)
        if shown == self._shown:
            return
        self._shown = shown
        self._applied = setting.applied
        _show_status(self._status, setting)
        self._validate()

    def show_ramp(self, ramp: RampSettings) -> None:
        """Put ``ramp`` into the fields (without applying it)."""
        for name, spin in self._spins.items():
            blocked = spin.blockSignals(True)
            spin.setValue(getattr(ramp, name))
            spin.blockSignals(blocked)
        self._validate()

    def edited(self) -> RampSettings:
        """The fields as settings; raises ConfigError naming the first problem."""
        return RampSettings(**{name: spin.value() for name, spin in self._spins.items()})

    def _validate(self) -> RampSettings | None:
        try:
            ramp = self.edited()
        except ConfigError as err:
            _refuse(self._summary, self._apply, _describe(err, _RAMP_LABELS))
            return None
        forces = [ramp.level_force_N(k) for k in range(ramp.n_levels)]
        shown = ", ".join(f"{f:g}" for f in forces) if len(forces) <= 10 else \
            f"{forces[0]:g}, {forces[1]:g}, … {forces[-1]:g}"
        self._summary.setText(f"{ramp.n_levels} levels: {shown} N")
        self._summary.setStyleSheet(OK_STYLE)
        self._apply.setEnabled(ramp != self._applied)
        return ramp

    def request(self, ramp: RampSettings) -> None:
        """Show ``ramp`` and ask the controller for it, as if the operator had typed it and pressed Apply."""
        self.show_ramp(ramp)
        self._request()

    def _request(self) -> None:
        ramp = self._validate()
        if ramp is not None:
            self.apply_requested.emit(ramp)


class GainsEditor(QtWidgets.QWidget):
    """Signal ``apply_requested(ImpedanceGains)``. Child objectNames: ``gainsUnlock``, ``gainsApply``,
    ``gainsSummary``, ``gainsStatus`` and one spin box per gain and axis, ``<field>_<axis>`` (``mass_kg_x``...)."""

    apply_requested = QtCore.Signal(object)

    def __init__(self, gains: ImpedanceGains, problem: Callable[[ImpedanceGains], str | None] = lambda gains: None,
                 parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self._applied = gains
        self._problem = problem  # the controller's own rule for gains it would refuse (ControlConfig.gains_problem)
        self._waiting = False  # a request is pending: keep showing what was sent
        self._shown: tuple | None = None
        self._spins: dict[tuple[str, int], QtWidgets.QDoubleSpinBox] = {}
        grid = QtWidgets.QGridLayout()
        for i, axis in enumerate(AXES):
            head = QtWidgets.QLabel(axis)
            head.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
            grid.addWidget(head, 0, i + 1)
        for r, (name, label, unit, decimals, maximum) in enumerate(GAIN_FIELDS, start=1):
            grid.addWidget(QtWidgets.QLabel(f"{label} ({unit})"), r, 0)
            for i, axis in enumerate(AXES):
                spin = _spin(f"{name}_{axis}", "", decimals, maximum)
                spin.setSuffix("")
                spin.setMinimumWidth(80)
                spin.valueChanged.connect(self._validate)
                self._spins[(name, i)] = spin
                grid.addWidget(spin, r, i + 1)
        self._unlock = QtWidgets.QCheckBox("Unlock to edit", objectName="gainsUnlock")
        self._unlock.setToolTip("The gains set how the robot responds to the tissue: change them deliberately")
        self._unlock.toggled.connect(self._set_editable)
        self._apply = QtWidgets.QPushButton("Apply gains", objectName="gainsApply")
        self._apply.clicked.connect(self._request)
        self._summary = QtWidgets.QLabel("", objectName="gainsSummary", wordWrap=True)
        self._status = QtWidgets.QLabel("", objectName="gainsStatus", wordWrap=True)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self._unlock)
        row.addStretch(1)
        row.addWidget(self._apply)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        layout.addLayout(grid)
        layout.addLayout(row)
        layout.addWidget(self._summary)
        layout.addWidget(self._status)
        layout.addStretch(1)
        self.show_gains(gains)
        self._set_editable(False)

    def show_gains(self, gains: ImpedanceGains) -> None:
        for (name, i), spin in self._spins.items():
            blocked = spin.blockSignals(True)
            spin.setValue(getattr(gains, name)[i])
            spin.blockSignals(blocked)
        self._validate()

    def edited(self) -> ImpedanceGains:
        return ImpedanceGains(**{name: tuple(self._spins[(name, i)].value() for i in range(3))
                                 for name, *_ in GAIN_FIELDS})

    def _set_editable(self, on: bool) -> None:
        for spin in self._spins.values():
            spin.setEnabled(on)
        if not on and self._unlock.isChecked():
            blocked = self._unlock.blockSignals(True)
            self._unlock.setChecked(False)
            self._unlock.blockSignals(blocked)
        if not on and not self._waiting:
            self.show_gains(self._applied)  # locking drops edits that were not applied
        self._validate()

    def _validate(self) -> ImpedanceGains | None:
        try:
            gains = self.edited()
            problem = self._problem(gains)
            if problem is not None:
                raise ConfigError("gains", problem)
        except ConfigError as err:
            _refuse(self._summary, self._apply, _describe(err, _GAIN_LABELS))
            return None
        self._summary.setText("" if self._unlock.isChecked() else "Locked: unlock to edit.")
        self._summary.setStyleSheet(OK_STYLE)
        self._apply.setEnabled(self._unlock.isChecked() and gains != self._applied)
        return gains

    def _request(self) -> None:
        gains = self._validate()
        if gains is None or not self._unlock.isChecked():
            return
        self._waiting = True
        self._set_editable(False)
        self.apply_requested.emit(gains)

    def show_setting(self, setting: Setting) -> None:
        """What the controller has in force, what it was asked for and has not answered, and a refusal."""
        shown = (setting.applied, setting.pending, setting.refusal)
        if shown == self._shown:
            return
        self._shown = shown
        self._applied = setting.applied
        self._waiting = setting.pending is not None
        _show_status(self._status, setting)
        if not self._waiting:
            self.show_gains(self._applied)
