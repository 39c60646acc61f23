"""The first use of a phantom shows its precompute in the console, not only on a terminal (issue 13)."""

from __future__ import annotations

import threading

import pytest
from PySide6 import QtCore, QtWidgets

from app.gui import prepare_in_console
from tissue.phantom import PhantomError


def _dialog():
    found = [w for w in QtWidgets.QApplication.topLevelWidgets() if w.objectName() == "prepareProgress"]
    return found[0] if found else None


def test_the_console_shows_how_far_the_tissue_model_is_while_it_is_computed(qtbot):
    release = threading.Event()
    terminal = []
    seen = {}

    def prepare(progress):
        progress(0.5, "condensing the tissue onto its surface")
        assert release.wait(30), "the dialog never showed the progress"

    def look():
        dialog = _dialog()
        if dialog is not None and dialog.isVisible() and dialog.value() == 500:
            seen["label"] = dialog.labelText()
            release.set()
        else:
            QtCore.QTimer.singleShot(20, look)

    QtCore.QTimer.singleShot(0, look)
    prepare_in_console(prepare, "Preparing the tissue model of 'flat'", terminal=lambda *a: terminal.append(a))
    assert seen["label"] == "Preparing the tissue model of 'flat'\ncondensing the tissue onto its surface"
    assert terminal == [(0.5, "condensing the tissue onto its surface")]
    qtbot.waitUntil(lambda: _dialog() is None or not _dialog().isVisible())


def test_a_quick_preparation_shows_no_dialog_and_a_failure_is_raised_in_the_console(qtbot):
    prepare_in_console(lambda progress: progress(1.0, "tissue model of 'flat' ready"), "Preparing")
    assert _dialog() is None or not _dialog().isVisible()

    def broken(progress):
        raise PhantomError("bad.toml", "phantom.sides", "must be one of free, mould, got 'tray'")

    with pytest.raises(PhantomError, match="phantom.sides"):
        prepare_in_console(broken, "Preparing")
