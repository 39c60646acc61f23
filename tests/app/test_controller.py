"""The controller process on the simulated rig: start, stream, command, stop, crash, orphaning."""

import multiprocessing as mp
import os
import signal
import time
from multiprocessing import shared_memory
from pathlib import Path

import numpy as np
import pytest

from app.controller import ControllerProcess, ControllerStartError, PacingOptions, pacing_floor, wait_until
from app.rigs import RigSpec
from app.ring import NAME_PREFIX
from control.config import ControlConfig
from control.messages import ClearFault, EStop, FaultKind, FaultRaised

# Plain scheduling: the tests check behaviour, and must not take a core from the rest of the suite.
PLAIN = PacingOptions(realtime=False, pin_cpu=False)


def segments_of(pid: int) -> set[str]:
    return {p.name for p in Path("/dev/shm").glob(f"{NAME_PREFIX}{pid}_*")}


@pytest.fixture(autouse=True)
def no_shared_memory_leak():
    before = segments_of(os.getpid())
    yield
    assert segments_of(os.getpid()) == before, "a test left shared memory behind"


@pytest.fixture
def controller():
    proc = ControllerProcess(ControlConfig(), RigSpec(), PLAIN)
    yield proc
    proc.stop()


def test_streams_ticks_frames_and_health_then_stops_cleanly(controller, qtbot):
    controller.start()
    assert controller.is_alive and controller.started_info.pid == controller.pid
    qtbot.waitUntil(lambda: controller.ticks.write_count > 300 and controller.frames.write_count > 2, timeout=10_000)

    def health_arrived():
        controller.drain_events()
        return controller.health is not None

    qtbot.waitUntil(health_arrived, timeout=10_000)
    rows, _, lost = controller.ticks.read_since(0)
    assert lost == 0
    assert np.all(np.diff(rows["tick"]) == 1)
    assert np.all(np.diff(rows["t_s"]) > 0)
    assert np.all(rows["compute_s"] > 0) and np.all(rows["io_s"] > 0) and np.all(rows["late_s"] >= 0)
    assert np.all(np.diff(rows["missed_ticks"]) >= 0)
    frames, _, _ = controller.frames.read_since(0)
    assert np.all(np.diff(frames["sensor_seq"]) > 0)
    health = controller.health
    assert health.rate_hz > 0 and not health.rt_priority and health.cpu is None

    code = controller.stop()
    assert code == 0 and not controller.is_alive
    assert controller.stopped_info.ticks >= len(rows)
    assert controller.ticks.closed and controller.frames.closed


def test_commands_reach_the_loop_and_its_events_come_back(controller, qtbot):
    controller.start()
    qtbot.waitUntil(lambda: controller.ticks.write_count > 50, timeout=10_000)
    controller.send(EStop("pressed in a test"))
    events = []

    def estop_seen():
        events.extend(controller.drain_events())
        return any(isinstance(e, FaultRaised) and e.kind == FaultKind.ESTOP for e in events)

    qtbot.waitUntil(estop_seen, timeout=10_000)
    qtbot.waitUntil(lambda: int(controller.ticks.latest()["fault"]) == FaultKind.ESTOP, timeout=5_000)
    with pytest.raises(TypeError, match="not a control command"):
        controller.send("estop")
    controller.send(ClearFault())


def test_a_killed_child_is_reported_and_everything_is_released(controller, qtbot):
    controller.start()
    os.kill(controller.pid, signal.SIGKILL)
    qtbot.waitUntil(lambda: not controller.is_alive, timeout=10_000)
    assert controller.exitcode == -signal.SIGKILL
    with pytest.raises(RuntimeError, match="not running"):
        controller.send(EStop())
    assert controller.stop() == -signal.SIGKILL
    assert controller.ticks.closed


def test_sigterm_makes_the_child_hold_and_exit_cleanly(controller, qtbot):
    controller.start()
    os.kill(controller.pid, signal.SIGTERM)
    qtbot.waitUntil(lambda: not controller.is_alive, timeout=10_000)
    assert controller.exitcode == 0


@pytest.mark.parametrize(
    "spec, message",
    [
        (RigSpec(phantom="no_such_phantom"), "no_such_phantom"),
        (RigSpec(backend="ethercat"), r"unknown backend 'ethercat' \(known: crtk, sim, udp\)"),
        (RigSpec(sim={"sensor": {"noise_std_pa": -1}}), "noise_std_pa"),
    ],
)
def test_start_up_failures_surface_with_the_message(spec, message):
    proc = ControllerProcess(ControlConfig(), spec, PLAIN)
    with pytest.raises(ControllerStartError, match=message):
        proc.start()
    # refused either while preparing the rig in this process or by the child, which then exits with 1
    assert not proc.is_alive and proc.exitcode in (None, 1)
    proc.stop()


def test_a_process_can_only_be_started_once(controller):
    controller.start()
    with pytest.raises(RuntimeError, match="already started"):
        controller.start()


def test_realtime_request_is_granted_or_explained(qtbot):
    mask_before = os.sched_getaffinity(0)
    proc = ControllerProcess(ControlConfig(), RigSpec(), PacingOptions())
    try:
        proc.start()
        info = proc.started_info
        assert info.rt_priority or info.warning
        if info.cpu is not None:
            # the console's own threads keep off the controller's CPU while it runs
            tids = [int(t) for t in os.listdir(f"/proc/{os.getpid()}/task")]
            assert all(info.cpu not in os.sched_getaffinity(t) for t in tids)
    finally:
        proc.stop()
    assert os.sched_getaffinity(0) == mask_before


def _console_that_dies(conn) -> None:
    """Plays the console: starts a controller, reports it, then waits to be killed."""
    proc = ControllerProcess(ControlConfig(), RigSpec(), PLAIN)
    proc.start()
    conn.send((proc.pid, proc.ticks.name, proc.frames.name))
    conn.recv()


def _exited(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return True
    return state in ("Z", "X")


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to watch a process that is not our child")
def test_the_controller_holds_and_exits_when_the_console_dies(qtbot):
    ctx = mp.get_context("spawn")
    here, there = ctx.Pipe()
    console = ctx.Process(target=_console_that_dies, args=(there,))
    console.start()
    names = ()
    try:
        assert here.poll(30), "the console process did not start its controller"
        child_pid, *names = here.recv()
        assert not _exited(child_pid)
        console.kill()
        console.join()
        qtbot.waitUntil(lambda: _exited(child_pid), timeout=10_000)
    finally:
        if console.is_alive():
            console.kill()
            console.join()
        # The dead console could not release its rings; this process shares its resource tracker.
        for name in names:
            shm = shared_memory.SharedMemory(name=name)
            shm.close()
            shm.unlink()


def test_waiting_for_a_deadline_never_returns_before_it():
    for spin_s in (0.0, 150e-6, 10e-3):
        deadline = time.monotonic() + 1.5e-3
        assert wait_until(deadline, spin_s, 100e-6) >= deadline


def test_the_pacing_floor_paces_empty_ticks_in_a_process_of_its_own():
    options = PacingOptions(realtime=False, pin_cpu=False)
    with mp.get_context("spawn").Pool(1) as pool:
        floor = pool.apply(pacing_floor, (options, 1e-3, 0.05))
    assert len(floor.late_s) == 50 and (floor.late_s >= 0).all()
    assert (np.diff(floor.started_s) > 0).all()
    assert (floor.rt_priority, floor.cpu) == (False, None) and floor.pid != os.getpid()
