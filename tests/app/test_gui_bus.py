"""The console publishing the palpation on the ROS 2 bus as ``run_gui`` wires it (:func:`app.gui.wire_bus`): on a
CRTK rig that publishes, the rows the console's bridge drains go on the bus, over the loopback; a bus that fails
is told in the window, once, while control goes on.

The window is the real console on the fast-forward bridge (the real control loop on the simulated rig), as in
test_gui_recording, so the rows published are a real palpation's; the console on the arm itself, through the
fake dVRK arm, is tests/hardware/test_crtk_autopilot.py's. Waits are conditions, never sleeps.
"""

from __future__ import annotations

import pytest
from PySide6 import QtCore

from app.bridge import ControllerBridge
from app.gui import wire_bus
from app.rigs import RigSpec, plan_for_rig
from app.ros_bus import STATE, qos
from control.config import ControlConfig
from hardware.crtk import dds
from hardware.crtk import messages as M
from hardware.interfaces import Phase
from session import mcap_export as bag
from tests.hardware import test_crtk
from widgets.live_window import LiveWindow
from widgets.review import RecentSessions

# a domain of this worker's own, and a participant of the test's on it (test_crtk's fixtures)
domain, listener = test_crtk.domain, test_crtk.listener

CONFIG = ControlConfig()
SIM = RigSpec(master="none")
WAIT_MS = 10_000
BUS_LINE = "not published on the ROS 2 bus"


def crtk(domain: int, **bus) -> RigSpec:
    return RigSpec(backend="crtk", hardware={"slave": {"domain": domain}, "sensor": {"kind": "sim"}, "bus": bus})


@pytest.fixture
def bridge():
    made = ControllerBridge.for_fast_forward(CONFIG, SIM, speed=4.0)
    yield made
    made.shutdown()


@pytest.fixture
def window(qtbot, tmp_path, bridge):
    ini = QtCore.QSettings.Format.IniFormat
    made = LiveWindow(bridge, config=CONFIG, plan=plan_for_rig(SIM, CONFIG), sessions_folder=tmp_path,
                      settings=QtCore.QSettings(str(tmp_path / "console.ini"), ini),
                      recent=RecentSessions(QtCore.QSettings(str(tmp_path / "recent.ini"), ini)))
    qtbot.addWidget(made)
    made.show()
    return made


def told(window) -> list[str]:
    return [line for line in window.messages().lines() if BUS_LINE in line]


def test_the_console_on_a_crtk_rig_that_publishes_puts_the_palpation_on_the_loopback(qtbot, window, bridge, domain,
                                                                                     listener):
    assert wire_bus(window, bridge, SIM) is None
    assert wire_bus(window, bridge, crtk(domain, publish=False)) is None
    # transient-local, as the console offers it: the loop's state reaches a subscriber whenever it joins
    state = listener.reader(dds.ros_topic(STATE), M.ros_message_type(dict(bag.TOPICS)[STATE], bag.DEFINITIONS),
                            qos(STATE))
    poses = listener.reader(dds.ros_topic("/palpation/tsi_pose"), M.PoseStamped, qos("/palpation/tsi_pose"))
    publisher = wire_bus(window, bridge, crtk(domain))
    with qtbot.waitSignal(bridge.started, timeout=WAIT_MS):
        bridge.start()
    got = {"state": [], "poses": []}

    def heard() -> bool:
        got["state"] += dds.take(state, 10)
        got["poses"] += dds.take(poses, 256)
        return bool(got["state"]) and len(got["poses"]) >= 100

    qtbot.waitUntil(heard, timeout=WAIT_MS)
    with qtbot.waitSignal(bridge.stopped, timeout=WAIT_MS):
        bridge.stop()
    assert got["state"][0].phase == Phase.APPROACH and got["state"][0].phase_name == "APPROACH"
    assert {pose.header.frame_id for pose in got["poses"]} == {bag.TISSUE_FRAME}
    assert publisher.published["/palpation/tsi_pose"] >= len(got["poses"])
    assert not publisher.problem and not told(window)


def test_a_bus_that_fails_is_told_in_the_window_once_and_control_goes_on(qtbot, window, bridge, domain,
                                                                         monkeypatch):
    def refused(domain: int):
        # as Cyclone refuses a participant it cannot make (no free participant index on the host, ...)
        raise dds.DDSException(dds.DDSException.DDS_RETCODE_ERROR,
                               "Occurred upon initialisation of a cyclonedds.domain.DomainParticipant")

    monkeypatch.setattr(dds, "Participant", refused)
    publisher = wire_bus(window, bridge, crtk(domain))
    bridge.start()
    qtbot.waitUntil(lambda: bool(told(window)), timeout=WAIT_MS)
    assert f"(cannot join DDS domain {domain}: [DDS_RETCODE_ERROR]" in told(window)[0]
    assert window.statusBar().currentMessage() == publisher.problem
    # the loop runs on, the console showing it, and the trouble is told once, not at every display frame
    qtbot.waitUntil(lambda: window.latest_tick() is not None and float(window.latest_tick()["t_s"]) > 0.5,
                    timeout=WAIT_MS)
    assert len(told(window)) == 1
    with qtbot.waitSignal(bridge.stopped, timeout=WAIT_MS):
        bridge.stop()
