"""What ``palpation-console devices`` lists: serial ports, USB devices with the role each could play,
and on request a probe of a serial port (does a TSI send frames there?) or of a UDP slave (is
``palpation-console slave`` answering there?)."""

from __future__ import annotations

import secrets
import select
import socket
import time
from dataclasses import dataclass

import serial
import usb.core
from serial.tools import list_ports

from hardware.serial_tactile.adapter import describe_open_error
from hardware.serial_tactile.config import format_vid_pid
from hardware.serial_tactile.driver import FrameParser
from hardware.udp import protocol as P
from hardware.udp.server import DEFAULT_PORT
from hardware.usb.spacemouse import KNOWN_SPACEMICE
from hardware.usb.tactile import DEFAULT_TACTILE_ID


@dataclass(frozen=True)
class Found:
    kind: str  # "serial" | "usb" | "udp"
    address: str  # what to put in the config: a port, a VID:PID, host:port
    description: str
    role: str = ""  # what the console would use it as, when recognised
    note: str = ""  # what stands in the way, or what a probe measured


def serial_ports() -> list[Found]:
    found = []
    for p in sorted(list_ports.comports(), key=lambda p: p.device):
        ids = f" (USB {p.vid:04x}:{p.pid:04x})" if p.vid is not None and p.pid is not None else ""
        desc = p.description if p.description and p.description != "n/a" else "serial port"
        note = "a TSI on this port: check with --probe-serial " + p.device if p.vid is not None else ""
        found.append(Found("serial", p.device, desc + ids, note=note))
    return found


def usb_devices(backend=None, tactile_ids: tuple[str, ...] = (DEFAULT_TACTILE_ID,)) -> tuple[list[Found], str]:
    """Every USB device, recognised ones first; the second value explains why none could be listed."""
    kwargs = {"backend": backend} if backend is not None else {}
    try:
        devices = list(usb.core.find(find_all=True, **kwargs))
    except usb.core.NoBackendError:
        return [], "no USB library found: install libusb-1.0 to use USB devices"
    except usb.core.USBError as err:
        return [], f"cannot list USB devices: {err}"
    found = []
    for d in devices:
        ids = format_vid_pid((d.idVendor, d.idProduct))
        names, note = [], ""
        for attr in ("manufacturer", "product"):
            try:
                value = getattr(d, attr)
            except (usb.core.USBError, ValueError, NotImplementedError):
                note = "no permission to read its strings (see the udev rule in docs/hardware.md)"
                continue
            if value:
                names.append(value)
        role = ""
        if (d.idVendor, d.idProduct) in KNOWN_SPACEMICE:
            role = 'master device: [hardware.master] kind = "spacemouse"'
            names = names or [KNOWN_SPACEMICE[(d.idVendor, d.idProduct)]]
        elif ids in tactile_ids:
            role = f'tactile sensor: [hardware.sensor] kind = "usb", vid_pid = "{ids}"'
        desc = " ".join(names) or "(no name)"
        found.append(Found("usb", ids, f"{desc}, bus {d.bus} address {d.address}", role, note))
    found.sort(key=lambda f: (f.role == "", f.address))
    return found, ""


def probe_serial(port: str, baud: int = 460800, listen_s: float = 0.5) -> Found:
    """Listen on ``port`` for TSI frames; the note says what arrived."""
    try:
        line = serial.Serial(port, baud, timeout=0.05, exclusive=True)
    except (serial.SerialException, OSError) as err:
        return Found("serial", port, "serial port", note=describe_open_error(port, err))
    parser = FrameParser()
    frames = []
    received = 0
    try:
        deadline = time.monotonic() + listen_s
        while time.monotonic() < deadline and len(frames) < 50:
            data = line.read(4096)
            received += len(data)
            frames += parser.feed(data)
    except (serial.SerialException, OSError) as err:
        return Found("serial", port, "serial port", note=f"reading failed: {err}")
    finally:
        line.close()
    if not frames:
        what = f"{received} bytes that were not TSI frames" if received else "nothing"
        if parser.header_errors:
            what += f" (frames of another format: {parser.last_header_problem})"
        return Found("serial", port, "serial port", note=f"no TSI frames in {listen_s:g} s at {baud} baud: {what}")
    span_us = (frames[-1].device_time_us - frames[0].device_time_us) % P.U32
    rate = (len(frames) - 1) / (span_us * 1e-6) if len(frames) > 1 and span_us else float("nan")
    bad = parser.crc_errors + parser.truncated
    return Found("serial", port, "serial port",
                 role=f'tactile sensor: [hardware.sensor] kind = "serial", port = "{port}"',
                 note=f"TSI frames, {parser.rows} x {parser.cols}, {rate:.0f} frames/s by the device clock, "
                      f"{bad} damaged, {parser.garbage_bytes} garbage bytes")


def probe_udp(host: str, port: int = DEFAULT_PORT, timeout_s: float = 0.5, count: int = 5) -> Found:
    """PING a slave server (does not disturb it: pings neither command the robot nor feed its watchdog)."""
    address = f"{host}:{port}"
    try:
        target = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)[0][4]
    except (socket.gaierror, UnicodeError) as err:
        return Found("udp", address, "slave server", note=f"cannot resolve {host!r}: {err}")
    session = secrets.randbits(32)
    rtts, status = [], None
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for seq in range(count):
            sent = time.monotonic()
            try:
                sock.sendto(P.pack_ping(session, seq, sent), target)
            except OSError as err:
                return Found("udp", address, "slave server", note=f"cannot send: {err}")
            deadline = sent + timeout_s
            while (left := deadline - time.monotonic()) > 0:
                ready, _, _ = select.select([sock], [], [], left)
                if not ready:
                    break
                try:
                    data, addr = sock.recvfrom(P.RECV_BUFFER)
                except OSError:
                    break  # e.g. ICMP port unreachable: nothing listens there
                try:
                    header, body = P.unpack(data)
                except P.PacketError:
                    continue
                if header.type == P.PacketType.STATE and body.echo_seq == seq:  # type: ignore[union-attr]
                    rtts.append(time.monotonic() - sent)
                    status = body.status  # type: ignore[union-attr]
                    break
    if not rtts:
        return Found("udp", address, "slave server",
                     note=f"no answer in {timeout_s:g} s: is `palpation-console slave` running there, and does "
                          f"its --allow list include this computer?")
    return Found("udp", address, "slave server", role='slave: [hardware.slave] host/port',
                 note=f"answered {len(rtts)}/{count} pings, round trip {min(rtts) * 1e6:.0f}-{max(rtts) * 1e6:.0f} µs; "
                      f"slave {P.status_text(status & ~P.Status.PING_REPLY)}")
