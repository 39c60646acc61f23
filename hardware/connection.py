"""The connection state of a real device, and the moves between states that every adapter makes alike.

A device is DISCONNECTED until it is opened and once it is closed; opening an open device does nothing.
Opened, it is CONNECTING until its first good reading (or CONNECTED at once, for one that is silent at
rest), CONNECTED while good readings come, and LOST when its hardware goes (a failed port, an unplug, a
peer holding on its own) or nothing good has come for the adapter's timeout. ``last_error`` says why, or
what else went wrong, until the next good reading. While LOST the last reading stays where it was, ageing,
so the loop's watchdogs hold. How a device comes back (a port reopened, a reader thread finding it again)
is its transport's own.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable

from hardware.interfaces import ConnectionState, Device


class Connection(Device):
    """A real device's :attr:`connection` and ``last_error``; a base before the device's interface
    (``class Adapter(Connection, TactileSensor)``)."""

    def __init__(self) -> None:
        self._state = ConnectionState.DISCONNECTED
        self.last_error = ""

    @property
    def connection(self) -> ConnectionState:
        return self._state

    def open(self) -> None:
        if self._state == ConnectionState.DISCONNECTED:
            self._state = self._connect()

    def close(self) -> None:
        self._disconnect()
        self._state = ConnectionState.DISCONNECTED

    @abstractmethod
    def _connect(self) -> ConnectionState:
        """Take hold of the device (DeviceError with a sentence a user can act on if it cannot); the state
        it starts in."""

    @abstractmethod
    def _disconnect(self) -> None:
        """Let go of every OS resource the device holds; safe when it holds none."""

    def _heard(self) -> None:
        """A good reading came: connected, and whatever went wrong before is over."""
        if self._state != ConnectionState.CONNECTED:
            self._state = ConnectionState.CONNECTED
            self.last_error = ""

    def _lost(self, why: str) -> None:
        self._state = ConnectionState.LOST
        self.last_error = why

    def _silent(self, now_s: float, last_s: float | None, timeout_s: float, why: Callable[[float], str]) -> bool:
        """Connected, but nothing good since ``last_s`` for longer than ``timeout_s``: lost, ``why`` of the
        silence's length saying so. True when it was lost here, for the adapter's count."""
        if self._state != ConnectionState.CONNECTED or last_s is None or now_s - last_s <= timeout_s:
            return False
        self._lost(why(now_s - last_s))
        return True
