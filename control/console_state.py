"""What the operator console may show and offer, derived from what the controller reports; no Qt.

The console's window draws; this decides. It is fed the controller's lifecycle (started, stopped, crashed),
every tick row it shows and every event, and the commands the operator sends, and it answers the questions
the window would otherwise answer with rules of its own:

* which fault the banner shows, in words (the loop's own explanation when its event was seen, the fault's
  name otherwise; a controller that stopped outranks any fault, because nothing can be cleared then, and one
  that has stopped answering outranks what its last tick row said);
* whether the TSI may be jogged from the console, and if not, why (the same reasons the loop would give
  for refusing the jog, said before the operator tries);
* whether tare may be offered;
* the S_z switch, the ramp and the gains as settings the operator *requested* and the controller either
  *applied* or *refused*: the reported value is always the applied one, and a request stays pending until
  the controller answers it (:class:`~control.messages.CommandApplied`, :class:`~control.messages.CommandRefused`,
  or, for S_z, the tick row showing the requested S_z).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from control.config import ControlConfig
from control.messages import (
    Command,
    CommandApplied,
    CommandRefused,
    FaultCleared,
    FaultKind,
    FaultRaised,
    SetGains,
    SetRamp,
    SetSz,
)
from hardware.interfaces import Phase

T = TypeVar("T")


def fault_name(kind: int) -> str:
    """A fault kind in words ("force ceiling"); unknown codes (a newer controller) by number."""
    try:
        return FaultKind(kind).name.replace("_", " ").lower()
    except ValueError:
        return f"fault {kind}"


@dataclass
class Setting(Generic[T]):
    """A setting the operator changes by asking the controller: the value in force, the one asked for and
    not yet answered, and why the last request was refused (None if it was not)."""

    applied: T
    pending: T | None = None
    refusal: str | None = None

    def request(self, value: T) -> None:
        self.pending, self.refusal = value, None

    def apply(self, value: T) -> None:
        self.applied = value
        if self.pending == value:
            self.pending = None

    def refuse(self, value: T, reason: str) -> None:
        if self.pending == value:
            self.pending, self.refusal = None, reason

    def drop(self) -> None:
        """The request can no longer be answered (the controller stopped)."""
        self.pending = None


class ConsoleState:
    """See the module docstring. ``tick`` is the newest TICK_DTYPE row seen (None before the first)."""

    def __init__(self, config: ControlConfig | None = None):
        config = config or ControlConfig()
        self.tick: np.ndarray | None = None
        self.running = False
        self.failure: str | None = None  # why the controller stopped on its own, while it stays stopped
        self.silence_s = 0.0  # how long the running controller has written nothing, while it is silent
        self.ramp: Setting = Setting(config.ramp)
        self.gains: Setting = Setting(config.gains)
        self.sz: Setting = Setting(None)  # True = position control (S_z = 1); None until the first tick
        self._fault_texts: dict[int, str] = {}

    # ---- what happens ----------------------------------------------------------------------------------

    def started(self) -> None:
        self.running, self.failure = True, None

    def stopped(self) -> None:
        self.running = False
        self._drop_requests()

    def crashed(self, message: str) -> None:
        self.running, self.failure, self.silence_s = False, message, 0.0
        self._drop_requests()

    def silent(self, seconds: float) -> None:
        """The controller, still running, has written nothing for ``seconds``."""
        self.silence_s = seconds

    def answering(self) -> None:
        self.silence_s = 0.0

    def controller_problem(self) -> str | None:
        """What is wrong with the controller itself, in a few words (None: nothing): the loop's health line
        says the same as the banner."""
        if self.failure is not None:
            return "controller stopped"
        if self.silence_s:
            return f"controller not answering for {self.silence_s * 1e3:.0f} ms"
        return None

    def on_tick(self, tick: np.ndarray) -> None:
        self.tick = tick
        self.sz.apply(int(tick["sz"]) == 1)

    def on_event(self, event) -> None:
        if isinstance(event, FaultRaised):
            self._fault_texts[int(event.kind)] = event.message
        elif isinstance(event, FaultCleared):
            self._fault_texts.pop(int(event.kind), None)
        elif isinstance(event, CommandApplied):
            setting, value = self._setting_of(event.command)
            if setting is not None:
                setting.apply(value)
        elif isinstance(event, CommandRefused):
            setting, value = self._setting_of(event.command)
            if setting is not None:
                setting.refuse(value, event.reason)

    def request(self, command: Command) -> Command:
        """Note a command the operator is sending (a setting goes pending); returns it, to send."""
        setting, value = self._setting_of(command)
        if setting is not None:
            setting.request(value)
        return command

    # ---- what follows --------------------------------------------------------------------------------

    def fault(self) -> tuple[int, str] | None:
        """(fault kind, banner text) of what holds the robot, or None."""
        if self.failure is not None:
            return (int(FaultKind.CONTROLLER),
                    f"CONTROLLER STOPPED — {self.failure}. The robot was left holding (or was never commanded); "
                    "restart the console to go on.")
        if self.silence_s:
            return (int(FaultKind.CONTROLLER),
                    f"CONTROLLER NOT ANSWERING — no report for {self.silence_s * 1e3:.0f} ms (stopped, hung or "
                    "starved of CPU): what the console shows is that old, and nothing it sends is carried out. A "
                    "real robot holds on its own link watchdog; press STOP, and restart the console if this "
                    "lasts.")
        kind = int(self.tick["fault"]) if self.tick is not None else 0
        if kind == 0:
            return None
        message = self._fault_texts.get(kind)
        name = fault_name(kind)
        if message and message.lower().startswith(name.lower()):
            return kind, f"FAULT: {message}"  # the loop's words already name it: "force ceiling — Force ceiling: …"
        return kind, f"FAULT: {name}" + (f" — {message}" if message else "")

    def operator_owns_z(self) -> bool:
        """Between areas, nothing faulted: the operator may move the TSI, tare and change settings."""
        tick = self.tick
        return (self.failure is None and not self.silence_s and tick is not None and int(tick["fault"]) == 0
                and Phase(int(tick["phase"])).idle)

    def jog_unavailable(self, autopilot_running: bool = False) -> str | None:
        """Why the console may not jog the TSI now, or None if it may."""
        tick = self.tick
        if self.failure is not None:
            return "the controller is not running"
        if self.silence_s:
            return "the controller is not answering"
        if tick is None:
            return "waiting for the controller"
        if not np.isnan(float(tick["master_age_s"])):
            return "a master device is attached: move the TSI with it"
        if int(tick["fault"]) != 0:
            return "a fault holds the robot"
        if autopilot_running:
            return "the autopilot is driving the TSI"
        if not Phase(int(tick["phase"])).idle:
            return "the TSI moves only between areas (S_z = position, not during a ramp)"
        return None

    def can_tare(self) -> bool:
        return self.operator_owns_z()

    # ---- internals ---------------------------------------------------------------------------------------

    def _setting_of(self, command) -> tuple[Setting | None, object]:
        if isinstance(command, SetRamp):
            return self.ramp, command.ramp
        if isinstance(command, SetGains):
            return self.gains, command.gains
        if isinstance(command, SetSz):
            return self.sz, command.position_control
        return None, None

    def _drop_requests(self) -> None:
        for setting in (self.ramp, self.gains, self.sz):
            setting.drop()
