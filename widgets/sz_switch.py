"""The S_z switch: position control (S_z = 1) or force control (S_z = 0) in the palpation direction.

It shows the state the controller reports, never the state it asked for: a click or the shortcut only
emits a request, and the owner shows it as pending (:meth:`SzSwitch.set_state`) until the controller
applies or refuses it (:class:`control.console_state.ConsoleState` decides which). The shortcut is ``S``,
not Space: Space also presses whichever button has focus, and a stray keystroke must not hand the robot to
force control.
"""

from __future__ import annotations

from PySide6 import QtCore, QtGui, QtWidgets

from widgets.glossary import GLOSSARY

_STYLE = """
QPushButton { font-size: 17pt; font-weight: bold; padding: 10px 16px; border: 2px solid #5a5a5a;
              border-radius: 6px; color: #9a9a9a; background: #2b2b2b; }
QPushButton:disabled { color: #6a6a6a; }
QPushButton[active="true"][mode="position"] { background: #1f6fd1; border-color: #8cc0ff; color: white; }
QPushButton[active="true"][mode="force"] { background: #e07b00; border-color: #ffc37a; color: black; }
QPushButton[pending="true"] { border: 2px dashed #f0f0f0; color: #f0f0f0; }
QLabel#szTitle { font-size: 17pt; font-weight: bold; }
QLabel#szHint { color: #b0b0b0; }
"""


class SzSwitch(QtWidgets.QFrame):
    """Two-segment switch "S_z: POSITION | FORCE".

    ``toggled(bool position_control)`` is the operator's request; call :meth:`set_state` with what the
    controller reports (``None`` while unknown, which disables the switch) and the request still pending,
    if any. Child objectNames:
    ``szTitle``, ``szPosition``, ``szForce``, ``szHint``.
    """

    toggled = QtCore.Signal(bool)

    def __init__(self, parent: QtWidgets.QWidget | None = None, shortcut: str = "S"):
        super().__init__(parent)
        self.setObjectName("szSwitch")
        self.setStyleSheet(_STYLE)
        self._state: bool | None = None
        self._pending: bool | None = None

        title = QtWidgets.QLabel("S_z", objectName="szTitle", toolTip=GLOSSARY["S_z"])
        self._position = QtWidgets.QPushButton("POSITION", objectName="szPosition")
        self._force = QtWidgets.QPushButton("FORCE", objectName="szForce")
        self._position.setProperty("mode", "position")
        self._force.setProperty("mode", "force")
        self._position.setToolTip(f"S_z = 1: position control in z; the operator moves the TSI ({shortcut})")
        self._force.setToolTip(f"S_z = 0: force control in z; starts the palpation ramp for this area ({shortcut})")
        for button, position_control in ((self._position, True), (self._force, False)):
            button.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)  # Space/Enter must never toggle it
            button.clicked.connect(lambda _=False, pc=position_control: self._request(pc))
        self._hint = QtWidgets.QLabel(f"press {shortcut} to switch", objectName="szHint")

        row = QtWidgets.QHBoxLayout()
        row.setSpacing(0)
        row.addWidget(self._position)
        row.addWidget(self._force)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(title)
        layout.addLayout(row)
        layout.addWidget(self._hint)

        self._shortcut = QtGui.QShortcut(QtGui.QKeySequence(shortcut), self)
        self._shortcut.setContext(QtCore.Qt.ShortcutContext.WindowShortcut)
        self._shortcut.activated.connect(self._toggle_requested)
        self._refresh()

    def state(self) -> bool | None:
        """The reported state: True = position control (S_z = 1), None = not known yet."""
        return self._state

    def pending(self) -> bool | None:
        """The requested state not yet confirmed, if any."""
        return self._pending

    def set_state(self, position_control: bool | None, pending: bool | None = None) -> None:
        """What the controller reports and the request it has not answered yet; cheap when unchanged (called
        at display rate)."""
        if position_control is not None:
            position_control = bool(position_control)
        if pending is not None:
            pending = bool(pending)
        if (position_control, pending) == (self._state, self._pending):
            return
        self._state, self._pending = position_control, pending
        self._refresh()

    def _toggle_requested(self) -> None:
        if self._state is not None:
            self._request(not self._state)

    def _request(self, position_control: bool) -> None:
        if self._state is None or position_control == self._state:
            return
        self.toggled.emit(position_control)

    def _refresh(self) -> None:
        known = self._state is not None
        for button, position_control in ((self._position, True), (self._force, False)):
            button.setEnabled(known)
            button.setProperty("active", known and self._state == position_control)
            button.setProperty("pending", self._pending == position_control)
            button.style().unpolish(button)
            button.style().polish(button)
        self._shortcut.setEnabled(known)
