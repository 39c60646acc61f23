"""``palpation-console slave``: the slave side of the UDP master/slave link, in front of a robot.

Today the robot behind it is the simulated rig (``--robot sim``); the link's own safety rules live in
:class:`hardware.udp.server.SlaveServer`, whatever robot it fronts.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path

from app.realtime import claim_realtime
from hardware.interfaces import DeviceError
from hardware.serial_tactile.emulator import SerialSensorEmulator, SimSensorFeed
from hardware.settings import ConfigError, read_toml
from hardware.sim.rig import build_sim_rig
from hardware.udp.server import DEFAULT_PORT, SlaveServer, SlaveServerSettings
from tissue.phantom import PhantomError


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="palpation-console slave",
        description="Run the slave side of the master/slave UDP link in front of a robot: it applies the "
                    "console's references at 1 kHz, streams the robot's state back, and holds the robot "
                    "when the console goes quiet.")
    p.add_argument("--bind", default="127.0.0.1", help="address to listen on (default: loopback only)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"UDP port (default {DEFAULT_PORT}; 0: any free)")
    p.add_argument("--allow", action="append", default=[], metavar="ADDRESS",
                   help="a master address or network allowed to command (repeat; required unless bound to loopback)")
    p.add_argument("--link-timeout-s", type=float, default=0.02, help="hold when no command came for this long")
    p.add_argument("--resume-distance-m", type=float, default=0.002,
                   help="after a hold, follow only references this close to the robot")
    p.add_argument("--force-limit-n", type=float, default=15.0,
                   help="the slave's own force limit on its sensor, N: above it the robot moves only up (default 15)")
    p.add_argument("--max-speed-m-s", type=float,
                   help="the slave's own speed limit on the references, m/s (default: the robot's)")
    p.add_argument("--workspace-min-m", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="the slave's own workspace, lower corner in m (default: the robot's)")
    p.add_argument("--workspace-max-m", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="the slave's own workspace, upper corner in m (default: the robot's)")
    p.add_argument("--robot", choices=["sim"], default="sim", help="the robot behind the slave (default: simulated)")
    p.add_argument("--phantom", default="flat", help="simulated robot: phantom name or TOML file")
    p.add_argument("--config", type=Path, help="simulated robot: a TOML file whose [sim] table overrides the defaults")
    p.add_argument("--seed", type=int, default=0, help="simulated robot: sensor noise seed")
    p.add_argument("--no-forward-tactile", action="store_true",
                   help="do not forward the slave-side tactile frames over the link")
    p.add_argument("--serial-emulator", action="store_true",
                   help="also serve the simulated sensor's frames on a pseudo-terminal (prints its path)")
    p.add_argument("--no-realtime", action="store_true",
                   help="do not ask for real-time scheduling (by default the slave asks, and says if refused)")
    p.add_argument("--duration-s", type=float, help="stop after this many seconds (default: until Ctrl-C)")
    return p


def _sim_settings(path: Path | None) -> dict:
    if path is None:
        return {}
    sim = read_toml(path).get("sim", {})
    if not isinstance(sim, dict):
        raise ConfigError(f"{path}: sim", "must be a table")
    return sim


def slave_main(argv: list[str] | None = None) -> int:
    """Entry point of ``palpation-console slave``; returns the exit status."""
    args = build_parser().parse_args(argv)
    emulator = None
    try:
        settings = SlaveServerSettings(bind_host=args.bind, port=args.port, allow=tuple(args.allow),
                                       link_timeout_s=args.link_timeout_s,
                                       resume_distance_m=args.resume_distance_m,
                                       forward_tactile=not args.no_forward_tactile,
                                       force_limit_N=args.force_limit_n, max_speed_m_s=args.max_speed_m_s,
                                       workspace_min_m=args.workspace_min_m, workspace_max_m=args.workspace_max_m)
        if args.duration_s is not None and not args.duration_s > 0:
            raise ConfigError("--duration-s", f"must be > 0, got {args.duration_s:g}")
        rig = build_sim_rig(args.phantom, settings=_sim_settings(args.config), seed=args.seed)
        server = SlaveServer(rig.slave, settings, sensor=rig.sensor)
        server.open()
    except (ConfigError, DeviceError, PhantomError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    feed = None
    stop = threading.Event()
    restore = {}
    claim = None
    try:
        if args.no_realtime:
            priority = "normal priority (--no-realtime)"
        else:
            claim = claim_realtime()
            priority = "real-time priority" if claim.realtime else (
                f"normal priority ({claim.warning}); the robot is held by the watchdog when steps come later "
                f"than the link timeout")
        if args.serial_emulator:
            emulator = SerialSensorEmulator()
            feed = SimSensorFeed(rig.sensor, emulator.device)
        host, port = server.address
        print(f"slave: listening on {host}:{port} (allowed: {', '.join(settings.allow)}); robot: simulated, "
              f"phantom {rig.description['phantom']!r}; tactile frames "
              f"{'forwarded over the link' if settings.forward_tactile else 'not forwarded'}; {priority}", flush=True)
        if emulator is not None:
            print(f"slave: serial tactile emulator at {emulator.path}", flush=True)
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                restore[sig] = signal.signal(sig, lambda *_: stop.set())
        steps = server.serve(stop, args.duration_s, on_step=feed.pump if feed is not None else None)
        st = server.stats
        print(f"slave: stopped after {steps} steps; {st['commands']} commands, {st['lost']} lost, "
              f"{st['link_timeouts']} link timeouts, {st['rejected_peers']} packets from refused peers", flush=True)
        return 0
    finally:
        for sig, handler in restore.items():
            signal.signal(sig, handler)
        if claim is not None:
            claim.release()
        server.close()
        if emulator is not None:
            emulator.close()
