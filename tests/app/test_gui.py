"""The composition root: which rig the console drives, and the whole console on the controller process."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest
from PySide6 import QtCore, QtGui

from app.config import load_config
from app.gui import console_rig, run_gui
from app.rigs import RigSpec, build_rig
from hardware.settings import ConfigError
from tissue.phantom import PhantomError

ROOT = Path(__file__).resolve().parents[2]


def test_the_interactive_console_drives_the_simulated_rig_without_its_scripted_operator():
    config = load_config()
    spec = console_rig(config)
    assert spec.master == "none" and spec.phantom == config.rig.phantom
    rig = build_rig(spec)
    assert rig.master is None and rig.description["master"] == "none"
    assert build_rig(RigSpec()).master is not None  # `simulate` keeps the scripted operator
    with pytest.raises(ConfigError, match="rig.master: unknown master 'robot' \\(known: scripted, none\\)"):
        RigSpec(master="robot")


def test_a_bad_phantom_is_reported_before_any_window_opens(tmp_path):
    config = load_config()
    config = dataclasses.replace(config, rig=dataclasses.replace(config.rig, phantom="no_such_phantom"))
    with pytest.raises(PhantomError, match="no_such_phantom"):
        run_gui(config, screenshot=str(tmp_path / "never.png"))


def test_nothing_builds_the_tissue_model_before_the_progress_dialog_can_show_it(monkeypatch, qapp):
    """issue 50: the session's description built the rig, and with it the tissue model, before the Qt
    application and its progress dialog existed: 36 s of black window and a silent terminal on a first run."""
    order = []

    class Stop(Exception):
        pass

    def described(*args, **kwargs):
        order.append("session described")
        raise Stop

    def prepared(prepare, title, terminal=None):
        from PySide6 import QtWidgets

        order.append("prepared with progress" if QtWidgets.QApplication.instance() else "prepared without Qt")

    monkeypatch.setattr("app.gui.session_info", described)
    monkeypatch.setattr("app.gui.prepare_in_console", prepared)
    with pytest.raises(Stop):
        run_gui(load_config())
    assert order == ["prepared with progress", "session described"]


def test_the_console_runs_on_the_controller_process_and_saves_a_screenshot(tmp_path):
    # Its own process, as `make run` starts it: the console quits its QApplication at the end, which a
    # test process must not do to the QApplication the other tests share.
    shot = tmp_path / "console.png"
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen", "XDG_CONFIG_HOME": str(tmp_path / "config")}
    done = subprocess.run([sys.executable, "-m", "app", "run", "--screenshot", str(shot), "--screenshot-after-s", "4"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=90)
    assert done.returncode == 0, done.stderr
    image = QtGui.QImage(str(shot))
    assert not image.isNull() and image.width() >= 1200 and image.height() >= 550  # within the offscreen screen
    # the emergency stop's red is on screen
    reds = sum(1 for x in range(0, image.width(), 8) for y in range(0, image.height(), 8)
               if image.pixelColor(x, y).name() == "#c01c28")
    assert reds > 50
    # the layout was saved for the next run, in the user's configuration directory
    saved = QtCore.QSettings(str(tmp_path / "config" / "palpation-console" / "console.ini"),
                             QtCore.QSettings.Format.IniFormat)
    assert saved.value("window/state") is not None
