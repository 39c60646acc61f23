"""The 1 kHz loop on real transports: a serial tactile line and the UDP master/slave link, on this machine.

The slave side runs in a process of its own, as on the paper's second PC: the simulated robot behind a
:class:`~hardware.udp.server.SlaveServer` stepping at 1 kHz, and the simulated sensor's frames served on a
pseudo-terminal by the serial emulator. This process is the console's controller: the real tick
(:func:`app.runtime.run_tick`) and a :class:`~control.loop.ControlLoop` on a rig of a
:class:`~hardware.serial_tactile.SerialTactileSensor` and a :class:`~hardware.udp.link.UdpSlaveLink`, paced
on absolute deadlines (SCHED_FIFO and a CPU of its own when permitted, the slave on the other CPU).
After a second it switches S_z off and palpates the same spot again and again (a 1-3 N ramp, so a region
finishes on the soft flat phantom): contact, force ramp, retract, while the link and the serial line
carry a palpation's traffic. Should a fault latch, it is cleared and the palpation starts again, as an
operator would.

Writes ``hardware.json``:

* ``late_over_0_5ms_pct`` (and the other figures of :func:`bench.loop_bench.tick_statistics`): the
  loop's lateness while the serial line and the UDP link run;
* ``round_trip_p99_us``: UDP round trip on loopback through the real packet code, a PING answered by
  the slave server's step as soon as it arrives, on a frozen simulator clock (what the link itself
  costs, process to process);
* ``link_round_trip_p99_us``: during the run, a command out to the state echoing it back, as the loop
  sees it (the slave answers at its next 1 kHz step and the console reads at its next tick, so up to
  two periods on top of the network);
* the devices' fault counters (all zero on a healthy machine) and what the palpation achieved;
* ``crtk_round_trip_p50_us``, ``crtk_round_trip_p99_us``: a ``servo_cp`` out through the CRTK slave to the
  fake dVRK arm (its own process, on the loopback, its loop at the dVRK's 1.5 kHz, reaching each goal at its
  next tick) until the slave reads a ``measured_cp`` at that goal: DDS both ways plus up to one of the arm's
  periods. None, with ``crtk_skipped`` saying why, where cyclonedds is not installed (the ``crtk`` extra);
* ``crtk_loop_*`` (the figures of :func:`bench.loop_bench.tick_statistics` named in :data:`CRTK_FIGURES`,
  ``crtk_loop_late_over_udp``: its ``late_over_0_5ms_pct`` over the UDP run's): the same loop, driver and
  operator on the CRTK rig instead, after the UDP run: the fake arm in its own process at the dVRK's 1.5 kHz
  through its second-order dynamics, and the simulated array of hardware/sim pressing the flat phantom where the
  arm's pose puts it (``[hardware.sensor] kind = "sim"``, app/crtk_sim.py); what it palpated
  (``crtk_levels_recorded``, ``crtk_regions_done``, ``crtk_faults``). The loop takes the arm's readings as stale
  after 50 ms (``safety.slave_timeout_s``, the slave's own watchdog) rather than 10: the fake arm, without
  real-time priority on a shared machine, misses 10 ms now and then;
* ``crtk_console_*`` and ``crtk_console_published_*``: the loop's lateness on the CRTK rig as the console runs it
  (the controller process, its rows drained at display rate by this process, now unprivileged and unpinned as
  the console's GUI process is, the operator above acting on them), without and with the palpation published
  on the bus from this process (app/ros_bus.py, what the console's bridge does with ``[hardware.bus]
  publish``), and ``crtk_console_published_messages``: what it published.
"""

from __future__ import annotations

import gc
import json
import multiprocessing as mp
import os
import secrets
import select
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from app.realtime import claim_realtime
from app.rigs import RigSpec, build_rig
from app.runtime import make_loop, run_tick
from bench.loop_bench import DISPLAY_HZ, WARMUP_S, duration_s, tick_statistics
from control.config import ControlConfig
from control.messages import ClearFault, FaultRaised, Jog, LevelRecorded, RegionDone, SetSz
from control.telemetry import TICK_DTYPE
from hardware.interfaces import Phase
from hardware.rig import Rig
from hardware.serial_tactile import SerialTactileSensor, SerialTactileSettings
from hardware.udp import protocol as P
from hardware.udp.link import UdpLinkSettings, UdpSlaveLink

NAME = "hardware"
SPIN_S = 2e-4  # the last stretch before a deadline is spun, not slept (sleep overshoots by ~60 µs)
PINGS = 5000
SZ_OFF_AT_S = 1.0
CRTK_ROUND_TRIPS = 2000
CRTK_DOMAIN = 231  # the tests take theirs from 150 up
CRTK_ARM_HZ = 1500.0  # the dVRK's loop
# The fake arm's home, 100 mm below its base, is where the simulated rig's robot starts in the tissue frame.
CRTK_TISSUE_IN_BASE_M = [-0.036, -0.015, -0.16]
CRTK_FIGURES = ("ticks", "late_over_0_5ms_pct", "late_over_1ms_pct", "p99_abs_jitter_us", "longest_stall_ms",
                "missed_ticks", "tick_work_p99_us", "io_p99_us")


def _pin(cpu: int) -> bool:
    try:
        if cpu in os.sched_getaffinity(0) and len(os.sched_getaffinity(0)) > 1:
            os.sched_setaffinity(0, {cpu})
            return True
    except (AttributeError, OSError):
        pass
    return False


def _start_arm(*options: str, cpu: int | None = None) -> subprocess.Popen:
    """The fake arm, on CPU ``cpu`` where there is one to give it: started from this process while it runs
    pinned, it would inherit its CPU and SCHED_FIFO, and never run while this process spins on that CPU."""
    arm = subprocess.Popen([sys.executable, "-m", "hardware.crtk.fake_arm", "--domain", str(CRTK_DOMAIN), *options],
                           stdout=subprocess.DEVNULL)
    if cpu is None:
        return arm
    try:
        os.sched_setaffinity(arm.pid, {cpu})
    except (AttributeError, OSError):  # no such CPU, or not ours to give: the scheduler places it
        pass
    return arm


def _slave_side(conn, serving, answering) -> None:
    """The slave PC: serve at 1 kHz while ``serving`` is set, then answer pings on arrival while ``answering``."""
    from hardware.serial_tactile.emulator import SerialSensorEmulator, SimSensorFeed
    from hardware.sim.rig import build_sim_rig
    from hardware.udp.server import SlaveServer, SlaveServerSettings

    _pin(1)
    rt = claim_realtime().realtime  # as a slave PC's control process would run
    sim = build_sim_rig("flat")
    server = SlaveServer(sim.slave, SlaveServerSettings(port=0, forward_tactile=False), sensor=sim.sensor)
    server.open()
    emulator = SerialSensorEmulator()
    feed = SimSensorFeed(sim.sensor, emulator.device)
    try:
        gc.freeze()
        conn.send((server.address, emulator.path))
        stop = _Cleared(serving)
        steps = server.serve(stop, on_step=feed.pump)
        # pings are answered on a frozen clock: the simulator does no physics, so the round trip is the link's
        frozen = time.monotonic()
        fd = server.fileno()
        while answering.is_set():
            if select.select([fd], [], [], 0.05)[0]:
                server.step(frozen)
        conn.send({"slave_rt_priority": rt, "steps": steps, "frames_sent": emulator.device.sent,
                   "serial_dropped_bytes": emulator.port.dropped_bytes,
                   **{f"slave_{k}": v for k, v in server.stats.items() if isinstance(v, int)}})
    finally:
        server.close()
        emulator.close()


class _Operator:
    """Palpates the same spot again and again: S_z off whenever the loop is idle above the tissue; after
    a fault, clears it and lifts the TSI back to its starting height first (a region must start off the
    tissue). Acts at most every 0.1 s, on the loop's latest tick row."""

    def __init__(self):
        self.start_z: float | None = None
        self.lifting = False

    def act(self, tick) -> list:
        z = float(tick["x_slave_m"][2])
        if tick["fault"]:
            return [ClearFault()]
        if tick["phase"] not in (Phase.APPROACH, Phase.DONE):
            return []
        if self.start_z is None:
            self.start_z = z
        if z < self.start_z - 1e-3:
            if self.lifting:
                return []
            self.lifting = True
            return [Jog((0.0, 0.0, self.start_z - z))]
        self.lifting = False
        return [SetSz(position_control=False)]


class _Cleared:
    """The inverse of an event: 'stop' once ``event`` is cleared (what SlaveServer.serve waits for)."""

    def __init__(self, event):
        self._event = event

    def is_set(self) -> bool:
        return not self._event.is_set()


def _run_loop(rig: Rig, config: ControlConfig, seconds: float) -> tuple[np.ndarray, list]:
    loop = make_loop(config, rig)
    period = config.period_s
    ticks = np.zeros(int(seconds / period) + 16, dtype=TICK_DTYPE)
    events: list = []
    monotonic = time.monotonic
    gc.freeze()
    t0 = monotonic()
    k = n = missed = 0
    next_action = round(SZ_OFF_AT_S / period)
    retry_ticks = round(0.1 / period)
    operator = _Operator()
    while n < len(ticks):
        deadline = t0 + k * period
        if deadline - t0 >= seconds:
            break
        remaining = deadline - monotonic()
        if remaining > SPIN_S:
            time.sleep(remaining - SPIN_S)
        now = monotonic()
        while now < deadline:
            now = monotonic()
        late = now - deadline
        if late >= period:  # resynchronise after a stall instead of replaying it
            skipped = int(late / period)
            missed += skipped
            k += skipped
        commands = []
        if k >= next_action:
            commands = operator.act(loop.tick)
            next_action = k + retry_ticks
        result = run_tick(loop, rig, now, commands)
        ticks[n] = loop.tick
        row = ticks[n]
        row["late_s"] = late
        row["missed_ticks"] = missed
        events += result.events
        n += 1
        k += 1
    return ticks[:n], events


def _ping_round_trips(address: tuple[str, int], count: int) -> tuple[np.ndarray, int]:
    """Round trips of PINGs answered by the slave server's step as soon as they arrive."""
    rtts = np.full(count, np.nan)
    lost = 0
    session = secrets.randbits(32)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for seq in range(count):
            sent = time.perf_counter()
            sock.sendto(P.pack_ping(session, seq, time.monotonic()), address)
            while True:
                if not select.select([sock], [], [], 0.5)[0]:
                    lost += 1
                    break
                header, body = P.unpack(sock.recv(P.RECV_BUFFER))
                if header.type == P.PacketType.STATE and body.echo_seq == seq:  # type: ignore[union-attr]
                    rtts[seq] = time.perf_counter() - sent
                    break
    return rtts[np.isfinite(rtts)], lost


def _crtk_round_trips(count: int) -> dict:
    """The CRTK slave's round trips to the fake arm: ``count`` goals 10 µm apart, each awaited before the next."""
    try:
        from hardware.crtk.slave import CrtkSettings, CrtkSlave
    except ImportError as err:
        return {"crtk_round_trip_p50_us": None, "crtk_round_trip_p99_us": None,
                "crtk_skipped": f"{err} (pip install 'palpation-console[crtk]')"}
    arm = _start_arm("--rate-hz", f"{CRTK_ARM_HZ:g}", "--ideal", cpu=1)
    slave = CrtkSlave(CrtkSettings(domain=CRTK_DOMAIN, open_timeout_s=30.0))
    rtts = np.full(count, np.nan)
    try:
        slave.open()
        x, y, z = slave.latest().position_m
        for i in range(count):
            goal = (x, y, z + 1e-5 * (i % 100 + 1))
            sent = time.perf_counter()
            slave.command(goal, (0.0, 0.0, 0.0), time.monotonic())
            deadline = sent + 0.5
            while time.perf_counter() < deadline:
                # Cyclone's receiving threads share this process's CPU and SCHED_FIFO priority: spinning
                # without yielding, it never let them hand over the arm's reply (every trip lost at 0.5 s).
                os.sched_yield()
                slave.poll(time.monotonic())
                if abs(slave.latest().position_m[2] - goal[2]) < 1e-9:
                    rtts[i] = time.perf_counter() - sent
                    break
    finally:
        slave.close()
        _stop(arm)
    done = rtts[np.isfinite(rtts)]
    return {"crtk_round_trip_p50_us": float(np.percentile(done, 50) * 1e6),
            "crtk_round_trip_p99_us": float(np.percentile(done, 99) * 1e6),
            "crtk_round_trips": int(len(done)), "crtk_round_trips_lost": int(count - len(done))}


def _crtk_spec() -> RigSpec:
    return RigSpec(backend="crtk", phantom="flat", hardware={
        "slave": {"domain": CRTK_DOMAIN, "tissue_in_base_m": CRTK_TISSUE_IN_BASE_M, "open_timeout_s": 30.0},
        "sensor": {"kind": "sim"}})


def _stop(arm: subprocess.Popen) -> None:
    arm.terminate()
    try:
        arm.wait(10)
    except subprocess.TimeoutExpired:
        arm.kill()
        arm.wait()


def _figures(prefix: str, ticks: np.ndarray, period_s: float) -> dict:
    steady = ticks[ticks["t_s"] - ticks["t_s"][0] >= WARMUP_S]
    figures = tick_statistics(steady, period_s)
    return {f"{prefix}{name}": figures[name] for name in CRTK_FIGURES}


def _crtk_loop(config: ControlConfig, seconds: float) -> dict:
    """The loop of the UDP run, in this process, on the CRTK rig."""
    rig = build_rig(_crtk_spec())
    arm = _start_arm("--rate-hz", f"{CRTK_ARM_HZ:g}", cpu=1)  # this process runs the loop on CPU 0
    try:
        rig.open()
        ticks, events = _run_loop(rig, config, seconds)
    finally:
        rig.close()
        _stop(arm)
    return {**_figures("crtk_loop_", ticks, config.period_s),
            "crtk_levels_recorded": sum(isinstance(e, LevelRecorded) for e in events),
            "crtk_regions_done": sum(isinstance(e, RegionDone) for e in events),
            "crtk_faults": [e.message for e in events if isinstance(e, FaultRaised)]}


def _crtk_console(config: ControlConfig, seconds: float, publish: bool) -> dict:
    """The CRTK rig's loop in the controller process, drained here at display rate (and published)."""
    from app.controller import ControllerProcess
    from app.ros_bus import BusPublisher

    prefix = "crtk_console_published_" if publish else "crtk_console_"
    arm = _start_arm("--rate-hz", f"{CRTK_ARM_HZ:g}")
    controller = ControllerProcess(config, _crtk_spec())
    publisher = BusPublisher(CRTK_DOMAIN) if publish else None
    chunks, cursor, frame_cursor = [], 0, 0
    operator, next_action = _Operator(), time.monotonic() + SZ_OFF_AT_S
    try:
        controller.start(timeout_s=60.0)
        if publisher is not None:
            publisher.driver_started()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            time.sleep(1.0 / DISPLAY_HZ)
            ticks, cursor, _ = controller.ticks.read_since(cursor)
            frames, frame_cursor, _ = controller.frames.read_since(frame_cursor)
            events = controller.drain_events()
            if publisher is not None:
                publisher.add_rows(ticks, frames, events)
            if len(ticks):
                chunks.append(ticks)
                if time.monotonic() >= next_action:
                    for command in operator.act(ticks[-1]):
                        controller.send(command)
                    next_action = time.monotonic() + 0.1
    finally:
        controller.stop()
        if publisher is not None:
            publisher.driver_stopped(None)
        _stop(arm)
    result = _figures(prefix, np.concatenate(chunks), config.period_s)
    if publisher is not None:
        result[f"{prefix}messages"] = sum(publisher.published.values())
        result[f"{prefix}problem"] = publisher.problem
    return result


def _crtk_config(base: ControlConfig) -> ControlConfig | None:
    """``base`` with the arm's readings stale after the slave's own watchdog; None without cyclonedds."""
    try:
        from hardware.crtk.slave import CrtkSettings
    except ImportError:
        return None  # _crtk_round_trips has said why
    return base.replace(safety=base.safety.replace(slave_timeout_s=CrtkSettings().timeout_s))


def run(out_dir: Path) -> dict:
    seconds = duration_s(20.0, 2 * WARMUP_S + SZ_OFF_AT_S)
    base = ControlConfig()
    config = base.replace(ramp=base.ramp.replace(force_max_N=3.0))
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    serving, answering = ctx.Event(), ctx.Event()
    serving.set()
    answering.set()
    slave = ctx.Process(target=_slave_side, args=(child, serving, answering), name="bench-slave", daemon=True)
    slave.start()
    saved_affinity = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    claim = None
    rig = None
    try:
        if not parent.poll(60.0):
            raise RuntimeError("the slave process did not come up within 60 s")
        address, pty_path = parent.recv()
        link = UdpSlaveLink(UdpLinkSettings(host=address[0], port=address[1]))
        sensor = SerialTactileSensor(SerialTactileSettings(port=pty_path))
        rig = Rig(sensor=sensor, slave=link)
        rig.open()
        pinned = _pin(0)
        claim = claim_realtime()
        rt = claim.realtime
        ticks, events = _run_loop(rig, config, seconds)
        serving.clear()  # before the console goes quiet, so the slave's watchdog has nothing to report
        link_rtts = link.clock.round_trips_s()
        serial_stats, link_stats = sensor.stats, link.stats
        rig.close()
        rig = None
        ping_rtts, ping_lost = _ping_round_trips(address, PINGS)
        crtk = _crtk_round_trips(CRTK_ROUND_TRIPS)
        crtk_config = _crtk_config(config)
        if crtk_config is not None:  # the UDP run's loop, driver, priority and CPU on the CRTK rig
            crtk.update(_crtk_loop(crtk_config, seconds))
        claim.release()
        claim = None
        if saved_affinity is not None:
            os.sched_setaffinity(0, saved_affinity)
        if crtk_config is not None:  # the console's own processes: its GUI side runs unprivileged, unpinned
            crtk.update(_crtk_console(crtk_config, seconds, publish=False))
            crtk.update(_crtk_console(crtk_config, seconds, publish=True))
        answering.clear()
        if not parent.poll(30.0):
            raise RuntimeError("the slave process did not report back")
        slave_stats = parent.recv()
    finally:
        if claim is not None:
            claim.release()
        if saved_affinity is not None:
            os.sched_setaffinity(0, saved_affinity)
        if rig is not None:
            rig.close()
        serving.clear()
        answering.clear()
        slave.join(10.0)
        if slave.is_alive():
            slave.kill()
            slave.join()

    steady = ticks[ticks["t_s"] - ticks["t_s"][0] >= WARMUP_S]
    faults = [e.message for e in events if isinstance(e, FaultRaised)]
    udp = tick_statistics(steady, config.period_s)
    if "crtk_loop_late_over_0_5ms_pct" in crtk:
        late = udp["late_over_0_5ms_pct"]
        crtk["crtk_loop_late_over_udp"] = crtk["crtk_loop_late_over_0_5ms_pct"] / late if late > 0 else None
    result = {
        **udp,
        "round_trip_p50_us": float(np.percentile(ping_rtts, 50) * 1e6),
        "round_trip_p99_us": float(np.percentile(ping_rtts, 99) * 1e6),
        "round_trip_pings": int(len(ping_rtts)),
        "round_trip_lost": int(ping_lost),
        "link_round_trip_p50_us": float(np.percentile(link_rtts, 50) * 1e6),
        "link_round_trip_p99_us": float(np.percentile(link_rtts, 99) * 1e6),
        "rt_priority": rt,
        "pinned_cpu": pinned,
        "seconds": seconds,
        "levels_recorded": sum(isinstance(e, LevelRecorded) for e in events),
        "regions_done": sum(isinstance(e, RegionDone) for e in events),
        "faults": faults,
        "load_avg_1min": os.getloadavg()[0],
        **{f"serial_{k}": v for k, v in serial_stats.items()
           if isinstance(v, (int, float)) and not isinstance(v, bool)},
        **{f"link_{k}": v for k, v in link_stats.items()
           if isinstance(v, (int, float)) and not isinstance(v, bool) and not k.startswith("round_trip")},
        **slave_stats,
        **crtk,
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    result = {k: None if isinstance(v, float) and not np.isfinite(v) else v for k, v in result.items()}
    (out_dir / f"{NAME}.json").write_text(json.dumps(result, indent=2, allow_nan=False) + "\n")
    return result
