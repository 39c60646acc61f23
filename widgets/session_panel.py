"""The console's session panel: where this run is being recorded, whether that is going well, and the
operator's notes.

It only displays and asks: the recorder itself belongs to the composition root (:mod:`app.gui`), which
calls :meth:`SessionPanel.show_recording` and friends and listens to :attr:`SessionPanel.note_submitted`.
"""

from __future__ import annotations

from pathlib import Path

from PySide6 import QtCore, QtWidgets

_STYLE = """
QLabel#sessionState[state="recording"] { color: #6ee07a; font-weight: bold; }
QLabel#sessionState[state="stopped"] { color: #c8c8c8; }
QLabel#sessionState[state="problem"] { color: white; background: #a01c28; font-weight: bold; padding: 3px; }
"""
NOTE_MAX_CHARS = 200  # the session file keeps 240 bytes of text per event; UTF-8 needs room


class SessionPanel(QtWidgets.QWidget):
    """Signal ``note_submitted(str)``: the operator entered a note (stripped, never empty).

    Child objectNames: ``sessionState``, ``sessionPath``, ``noteEdit``, ``addNoteButton``.
    """

    note_submitted = QtCore.Signal(str)

    def __init__(self, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self.setStyleSheet(_STYLE)
        self._state = QtWidgets.QLabel("Not recording: the controller has not started", objectName="sessionState",
                                       wordWrap=True)
        self._path = QtWidgets.QLabel("", objectName="sessionPath", wordWrap=True)
        self._path.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        self._note = QtWidgets.QLineEdit(objectName="noteEdit")
        self._note.setPlaceholderText("Operator note for the session file…")
        self._note.setMaxLength(NOTE_MAX_CHARS)
        self._note.returnPressed.connect(self._submit)
        self._add = QtWidgets.QPushButton("Add note", objectName="addNoteButton")
        self._add.clicked.connect(self._submit)
        note_row = QtWidgets.QHBoxLayout()
        note_row.addWidget(self._note, 1)
        note_row.addWidget(self._add)
        layout = QtWidgets.QVBoxLayout(self)
        layout.addWidget(self._state)
        layout.addWidget(self._path)
        layout.addLayout(note_row)
        layout.addStretch(1)
        self._set_state("stopped")
        self._set_notes_enabled(False)

    # ---- called by the composition root -----------------------------------------------------------------

    def show_recording(self, path: str | Path) -> None:
        self._state.setText("● Recording this session")
        self._path.setText(str(path))
        self._set_state("recording")
        self._set_notes_enabled(True)

    def show_stopped(self, path: str | Path, summary: str) -> None:
        """Recording ended (the file is closed); a problem shown before stays in view."""
        if self._state.property("state") != "problem":
            self._state.setText(f"Session saved: {summary}")
            self._set_state("stopped")
        self._path.setText(str(path))
        self._set_notes_enabled(False)

    def show_problem(self, message: str) -> None:
        """Recording stopped or never started; the controller goes on regardless."""
        self._state.setText(message)
        self._set_state("problem")
        self._set_notes_enabled(False)

    def note_added(self, text: str) -> None:
        self._note.clear()
        self._note.setToolTip(f"Last note: {text}")

    def state(self) -> str:
        """"recording", "stopped" or "problem"."""
        return str(self._state.property("state"))

    def state_text(self) -> str:
        return self._state.text()

    def path_text(self) -> str:
        return self._path.text()

    # ---- internals ----------------------------------------------------------------------------------

    def _submit(self) -> None:
        text = self._note.text().strip()
        if text:
            self.note_submitted.emit(text)

    def _set_notes_enabled(self, on: bool) -> None:
        self._note.setEnabled(on)
        self._add.setEnabled(on)

    def _set_state(self, state: str) -> None:
        if self._state.property("state") != state:
            self._state.setProperty("state", state)
            self._state.style().unpolish(self._state)
            self._state.style().polish(self._state)
