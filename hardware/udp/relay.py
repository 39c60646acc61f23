"""A misbehaving network between the console and the slave, for fault-injection tests and demos.

The console talks to the relay as if it were the slave; the relay forwards each datagram to the slave
(and the slave's answers back to whoever spoke last) after rolling the dice: drop, duplicate, hold back
one packet and send it after the next (reordering), or flip one byte (corruption, which the CRC must
catch). :attr:`FaultyRelay.blackout` drops everything in the chosen directions (a pulled cable, or a
one-way failure). Random choices come from a seeded generator, so a test run is reproducible.
"""

from __future__ import annotations

import random
import socket
from dataclasses import dataclass

from hardware.udp.protocol import RECV_BUFFER

TO_SLAVE = "to_slave"
TO_MASTER = "to_master"


@dataclass
class Faults:
    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    corrupt: float = 0.0


class FaultyRelay:
    def __init__(self, slave: tuple[str, int], faults: Faults | None = None, seed: int = 0,
                 host: str = "127.0.0.1"):
        self.slave = slave
        self.faults = faults if faults is not None else Faults()
        self.blackout: set[str] = set()
        self._rng = random.Random(seed)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((host, 0))
        self._sock.setblocking(False)
        self._master: tuple[str, int] | None = None
        self._held: dict[str, bytes] = {}
        self.counts = dict.fromkeys(("forwarded", "dropped", "duplicated", "reordered", "corrupted"), 0)

    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    def fileno(self) -> int:
        return self._sock.fileno()

    def step(self) -> int:
        """Forward whatever is waiting (never blocks); returns the datagrams read."""
        n = 0
        while True:
            try:
                data, addr = self._sock.recvfrom(RECV_BUFFER)
            except BlockingIOError:
                return n
            n += 1
            if addr == self.slave:
                if self._master is not None:
                    self._forward(data, self._master, TO_MASTER)
            else:
                self._master = addr
                self._forward(data, self.slave, TO_SLAVE)

    def _forward(self, data: bytes, dest: tuple[str, int], direction: str) -> None:
        f, rng, c = self.faults, self._rng, self.counts
        if direction in self.blackout or rng.random() < f.drop:
            c["dropped"] += 1
            return
        if rng.random() < f.corrupt:
            i = rng.randrange(len(data))
            data = data[:i] + bytes([data[i] ^ 0x5A]) + data[i + 1:]
            c["corrupted"] += 1
        if direction not in self._held and rng.random() < f.reorder:
            self._held[direction] = data
            c["reordered"] += 1
            return
        self._send(data, dest)
        if rng.random() < f.duplicate:
            self._send(data, dest)
            c["duplicated"] += 1
        held = self._held.pop(direction, None)
        if held is not None:
            self._send(held, dest)

    def _send(self, data: bytes, dest: tuple[str, int]) -> None:
        try:
            self._sock.sendto(data, dest)
        except OSError:
            self.counts["dropped"] += 1
            return
        self.counts["forwarded"] += 1

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> FaultyRelay:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
