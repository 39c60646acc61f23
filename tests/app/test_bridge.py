"""The GUI bridge: snapshots at display rate, commands, crash reports, and a clean shutdown."""

import logging
import os
import signal
from pathlib import Path

import numpy as np
import pytest
from PySide6.QtCore import QThread

from app.bridge import ControllerBridge
from app.config import AppConfig
from app.controller import ControllerProcess, PacingOptions
from app.recording import SessionRecording, session_info
from app.rigs import RigSpec
from app.ring import NAME_PREFIX
from control.config import ControlConfig
from control.messages import EStop, FaultKind, FaultRaised, Jog
from control.telemetry import FRAME_DTYPE, TICK_DTYPE, LiveSnapshot
from session.reader import open_session

PLAIN = PacingOptions(realtime=False, pin_cpu=False)


def own_segments() -> set[str]:
    return {p.name for p in Path("/dev/shm").glob(f"{NAME_PREFIX}{os.getpid()}_*")}


@pytest.fixture(autouse=True)
def no_shared_memory_leak():
    before = own_segments()
    yield
    assert own_segments() == before, "a test left shared memory behind"


@pytest.fixture
def bridges():
    made = []

    def make(bridge):
        made.append(bridge)
        return bridge

    yield make
    for bridge in made:
        bridge.shutdown()
        assert not bridge._thread.isRunning()


class Collector:
    """Snapshots as the GUI gets them; frames as a row sink (the session recorder) gets them."""

    def __init__(self, bridge):
        self.snapshots: list[LiveSnapshot] = []
        self.frames: list[np.ndarray] = []
        self.sink_calls: list[str] = []
        self.sink_threads: set[str] = set()
        self.sink_ticks = 0
        bridge.snapshot.connect(self.snapshots.append)
        bridge.add_sink(self)

    def driver_started(self):
        self.sink_calls.append("started")

    def add_rows(self, ticks, frames, events):
        self.sink_threads.add(QThread.currentThread().objectName())
        self.sink_ticks += len(ticks)
        if len(frames):
            self.frames.append(frames)

    def driver_stopped(self, failure):
        self.sink_calls.append("stopped" if failure is None else "failed")

    @property
    def events(self):
        return [e for s in self.snapshots for e in s.events]

    @property
    def n_ticks(self):
        return sum(len(s.ticks) for s in self.snapshots)


def test_fast_forward_bridge_streams_snapshots_takes_commands_and_shuts_down(qtbot, bridges):
    bridge = bridges(ControllerBridge.for_fast_forward(ControlConfig(), RigSpec(), speed=4.0))
    got = Collector(bridge)
    with qtbot.waitSignal(bridge.started, timeout=10_000):
        bridge.start()
    assert bridge.running
    qtbot.waitUntil(lambda: got.n_ticks > 500 and len(got.frames) > 0, timeout=10_000)
    snap = got.snapshots[-1]
    assert snap.tick.shape == () and snap.tick.dtype == TICK_DTYPE
    assert snap.ticks.dtype == TICK_DTYPE and int(snap.tick["tick"]) == int(snap.ticks[-1]["tick"])
    assert snap.frame is not None and snap.frame.dtype == FRAME_DTYPE
    # at display rate, not one signal per tick
    assert len(got.snapshots) < got.n_ticks / 10
    ticks = np.concatenate([s.ticks for s in got.snapshots])
    np.testing.assert_array_equal(ticks["tick"], np.arange(len(ticks)))
    frames = np.concatenate(got.frames)
    assert np.all(np.diff(frames["sensor_seq"]) > 0)

    bridge.send(EStop("test"))
    qtbot.waitUntil(lambda: any(isinstance(e, FaultRaised) and e.kind == FaultKind.ESTOP for e in got.events),
                    timeout=10_000)
    with pytest.raises(TypeError, match="not a control command"):
        bridge.send("stop")

    with qtbot.waitSignal(bridge.stopped, timeout=10_000):
        bridge.stop()
    assert not bridge.running
    # the recorder's side: every row, in the bridge's own thread, between a start and a stop
    assert got.sink_calls == ["started", "stopped"] and got.sink_ticks == got.n_ticks
    assert got.sink_threads == {"controller-bridge"}
    with pytest.raises(RuntimeError, match="before the bridge starts"):
        bridge.add_sink(Collector.__new__(Collector))
    bridge.shutdown()
    bridge.shutdown()


def test_process_bridge_reports_a_crash_with_the_exit_reason(qtbot, bridges, tmp_path):
    process = ControllerProcess(ControlConfig(), RigSpec(), PLAIN)
    bridge = bridges(ControllerBridge(lambda: process))
    got = Collector(bridge)
    recording = SessionRecording(bridge, session_info(AppConfig(control=ControlConfig(), rig=RigSpec())),
                                 folder=tmp_path)
    with qtbot.waitSignal(bridge.started, timeout=20_000):
        bridge.start()
    qtbot.waitUntil(lambda: got.n_ticks > 200 and any(s.health is not None for s in got.snapshots),
                    timeout=10_000)
    with qtbot.waitSignal(bridge.crashed, timeout=10_000) as crash:
        os.kill(process.pid, signal.SIGKILL)
    assert "stopped unexpectedly" in crash.args[0] and "SIGKILL" in crash.args[0]
    assert not bridge.running
    assert got.sink_calls == ["started", "failed"]  # a dead controller ends the recording too, saying so
    with open_session(recording.last_status.path) as session:  # and the session says how it ended
        lost = [e for e in session.event_dicts() if e["kind"] == "controller_lost"]
        assert session.closed_cleanly and len(lost) == 1 and "SIGKILL" in lost[0]["text"]


def test_a_controller_that_stops_answering_is_told_and_so_is_its_return(qtbot, bridges):
    """Issue 49: SIGSTOP of the controller during force control looked healthy for 12.5 s (only is_alive was
    watched)."""
    from app.bridge import CONTROLLER_SILENT_S

    process = ControllerProcess(ControlConfig(), RigSpec(), PLAIN)
    bridge = bridges(ControllerBridge(lambda: process))
    got = Collector(bridge)
    with qtbot.waitSignal(bridge.started, timeout=20_000):
        bridge.start()
    qtbot.waitUntil(lambda: got.n_ticks > 200, timeout=10_000)
    silences = []
    bridge.silent.connect(silences.append)
    with qtbot.waitSignal(bridge.silent, timeout=5_000):
        os.kill(process.pid, signal.SIGSTOP)
    try:
        assert silences[0] >= CONTROLLER_SILENT_S and bridge.running
        qtbot.waitUntil(lambda: len(silences) >= 3, timeout=5_000)  # told again at display rate while it lasts
        assert silences == sorted(silences)
    finally:
        with qtbot.waitSignal(bridge.answering, timeout=10_000) as back:
            os.kill(process.pid, signal.SIGCONT)
    assert back.args[0] >= silences[-1]


def test_process_bridge_start_failure_is_reported(qtbot, bridges):
    bridge = bridges(ControllerBridge.for_process(ControlConfig(), RigSpec(phantom="no_such_phantom"), PLAIN))
    with qtbot.waitSignal(bridge.start_failed, timeout=20_000) as failure:
        bridge.start()
    assert "no_such_phantom" in failure.args[0]
    assert not bridge.running


def test_process_bridge_stop_then_restart(qtbot, bridges):
    bridge = bridges(ControllerBridge.for_process(ControlConfig(), RigSpec(), PLAIN))
    for _ in range(2):
        with qtbot.waitSignal(bridge.started, timeout=20_000):
            bridge.start()
        with qtbot.waitSignal(bridge.snapshot, timeout=10_000):
            pass
        with qtbot.waitSignal(bridge.stopped, timeout=10_000):
            bridge.stop()


def test_shutdown_while_running_stops_the_process_and_is_final(qtbot, bridges):
    process = ControllerProcess(ControlConfig(), RigSpec(), PLAIN)
    bridge = bridges(ControllerBridge(lambda: process))
    with qtbot.waitSignal(bridge.started, timeout=20_000):
        bridge.start()
    bridge.shutdown()
    assert not process.is_alive and process.exitcode == 0
    assert not bridge.running
    with pytest.raises(RuntimeError, match="shut down"):
        bridge.start()


def test_a_factory_that_fails_is_a_start_failure(qtbot, bridges):
    def broken():
        raise OSError("serial port /dev/ttyUSB7 not found")

    bridge = bridges(ControllerBridge(broken))
    with qtbot.waitSignal(bridge.start_failed, timeout=10_000) as failure:
        bridge.start()
    assert failure.args == ["OSError: serial port /dev/ttyUSB7 not found"]


def test_shutdown_without_start_is_harmless(bridges):
    bridge = bridges(ControllerBridge.for_fast_forward(ControlConfig(), RigSpec()))
    bridge.shutdown()
    with pytest.raises(ValueError, match="display_hz"):
        ControllerBridge(lambda: None, display_hz=0)


def test_a_command_after_the_operator_stopped_the_controller_is_not_a_warning(qtbot, bridges, caplog):
    # issue 13: quitting printed "controller is not running; Jog was dropped"
    bridge = bridges(ControllerBridge.for_fast_forward(ControlConfig(), RigSpec(), speed=4.0))
    with caplog.at_level(logging.DEBUG, logger="app.bridge"):
        bridge._worker.send(Jog((0.0, 0.0, 1e-3)))  # never started: worth a warning
        assert [r.levelno for r in caplog.records] == [logging.WARNING]
        with qtbot.waitSignal(bridge.started, timeout=10_000):
            bridge.start()
        with qtbot.waitSignal(bridge.stopped, timeout=10_000):
            bridge.stop()
        caplog.clear()
        bridge._worker.send(Jog((0.0, 0.0, 1e-3)))  # a key repeat still in flight as the console quits
        assert [r.levelno for r in caplog.records] == [logging.DEBUG] and "not sent" in caplog.text
