"""Datagram intake shared by both ends of the link: a non-blocking socket bound to an address, drained with
every fault counted, handing on only well-formed packets from accepted peers."""

from __future__ import annotations

import socket
from collections.abc import Callable, Iterator

from hardware.interfaces import DeviceError
from hardware.udp import protocol as P

Address = tuple


def bound_socket(host: str, port: int, refused: Callable[[str], str]) -> socket.socket:
    """A non-blocking UDP socket bound to (host, port), or DeviceError(``refused`` of the reason) when the
    address cannot be had."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind((host, port))
    except OSError as err:
        sock.close()
        raise DeviceError(refused(err.strerror or str(err))) from None
    sock.setblocking(False)
    return sock


class Intake:
    def __init__(self, counters: dict[str, int], on_error: Callable[[str], None]):
        self._buf = bytearray(P.RECV_BUFFER)
        self._view = memoryview(self._buf)
        self._counters = counters
        self._on_error = on_error

    def packets(self, sock: socket.socket, max_packets: int, accept: Callable[[Address], bool],
                source: Callable[[Address], str]) -> Iterator[tuple[P.Header, object, Address]]:
        """Up to ``max_packets`` packets waiting on ``sock``. Each must be used before asking for the next:
        they share one receive buffer."""
        c = self._counters
        for _ in range(max_packets):
            try:
                n, addr = sock.recvfrom_into(self._buf)
            except BlockingIOError:
                return
            except OSError as err:  # e.g. an ICMP error surfacing on the socket
                c["socket_errors"] += 1
                self._on_error(f"socket error: {err}")
                return
            c["received"] += 1
            if not accept(addr):
                c["rejected_peers"] += 1
                continue
            if n >= P.RECV_BUFFER:
                c["oversize"] += 1
                continue
            try:
                header, body = P.unpack(self._view[:n])
            except P.PacketError as err:
                c[err.kind] += 1
                self._on_error(f"bad packet from {source(addr)}: {err}")
                continue
            yield header, body, addr
