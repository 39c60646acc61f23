"""``palpation-console devices``: what this computer sees of the console's devices, and probes of them."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

from hardware.discovery import DEFAULT_TACTILE_ID, Found, probe_serial, probe_udp, serial_ports, usb_devices
from hardware.serial_tactile.config import integer
from hardware.settings import ConfigError, read_toml
from hardware.udp.rig import HardwareSettings
from hardware.udp.server import DEFAULT_PORT


def _baud(text: str) -> int:
    """``--baud``, within what the serial array's settings take (a negative one raised from pyserial)."""
    try:
        return integer("--baud", int(text), 1200, 12_000_000)
    except (ValueError, ConfigError) as err:
        raise argparse.ArgumentTypeError(err.problem if isinstance(err, ConfigError) else
                                         f"{text!r} is not a whole number") from None


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, DEFAULT_PORT
    try:
        return host, int(port)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HOST[:PORT], got {text!r}") from None


def _configured_probes(config: dict) -> tuple[list[tuple[str, int]], list[tuple[str, int]], list[str]]:
    """What the configuration's [hardware] tables name, checked as ``run`` checks them: serial ports with
    their baud, slave addresses, USB ids. Only what the file names: its defaults are no one's device."""
    tables = config.get("hardware", {})
    settings = HardwareSettings.from_mapping(tables)
    slaves = [(settings.slave.host, settings.slave.port)] if "slave" in tables else []
    if settings.sensor_kind == "serial":
        return [(settings.sensor.port, settings.sensor.baud)], slaves, []
    if settings.sensor_kind == "usb":
        return [], slaves, [settings.sensor.vid_pid]
    return [], slaves, []


def main(argv: list[str] | None = None, usb_backend=None) -> int:
    """Entry point of ``palpation-console devices``; 1 if a requested probe found nothing usable."""
    parser = argparse.ArgumentParser(prog="palpation-console devices",
                                     description="List the serial ports and USB devices this computer sees, and "
                                                 "probe a port or a slave for the console's protocols.")
    parser.add_argument("--probe-serial", action="append", default=[], metavar="PORT",
                        help="listen on PORT for TSI frames (repeatable)")
    parser.add_argument("--baud", type=_baud, default=460800, help="baud rate for --probe-serial")
    parser.add_argument("--probe-udp", action="append", default=[], type=_host_port, metavar="HOST[:PORT]",
                        help=f"ping a slave server (default port {DEFAULT_PORT}; repeatable)")
    parser.add_argument("--tactile-vid-pid", action="append", default=[], metavar="VID:PID",
                        help=f"USB id of your tactile array (default {DEFAULT_TACTILE_ID})")
    parser.add_argument("--all", action="store_true", help="list every USB device, not only recognised ones")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    parser.add_argument("--config", type=Path, help="a console configuration (TOML): also probe the devices "
                        "its [hardware] tables name (the sensor's serial port or USB id, the slave's address)")
    args = parser.parse_args(argv)
    serial_probes = [(port, args.baud) for port in args.probe_serial]
    if args.config is not None:
        try:
            serial_more, udp_more, ids_more = _configured_probes(read_toml(args.config))
        except ConfigError as err:
            print(f"error: {err}" if str(args.config) in str(err) else f"error: {args.config}: {err}",
                  file=sys.stderr)
            return 2
        serial_probes += serial_more
        args.probe_udp += udp_more
        args.tactile_vid_pid += ids_more
        if not (serial_more or udp_more or ids_more) and not args.json:
            print(f"({args.config} names no serial port, USB id or slave: its [hardware] tables are not set)")

    ports = serial_ports()
    devices, usb_problem = usb_devices(usb_backend, tuple(args.tactile_vid_pid) or (DEFAULT_TACTILE_ID,))
    probes = [probe_serial(port, baud) for port, baud in serial_probes]
    probes += [probe_udp(h, p) for h, p in args.probe_udp]
    failed = any(not f.role for f in probes)
    if args.json:
        print(json.dumps({"serial": [asdict(f) for f in ports], "usb": [asdict(f) for f in devices],
                          "usb_problem": usb_problem, "probes": [asdict(f) for f in probes]}, indent=2))
        return 1 if failed else 0

    def show(f: Found) -> None:
        print(f"  {f.address:<28} {f.description}")
        if f.role:
            print(f"  {'':<28} -> {f.role}")
        if f.note:
            print(f"  {'':<28} {f.note}")

    print("Serial ports:" if ports else "Serial ports: none")
    for f in ports:
        show(f)
    shown = devices if args.all else [f for f in devices if f.role]
    hidden = len(devices) - len(shown)
    print("USB devices:" if shown else f"USB devices: {usb_problem or 'none recognised'}")
    for f in shown:
        show(f)
    if hidden:
        print(f"  ({hidden} other USB device{'s' if hidden != 1 else ''}; --all lists them)")
    if probes:
        print("Probes:")
        for f in probes:
            show(f)
    return 1 if failed else 0

