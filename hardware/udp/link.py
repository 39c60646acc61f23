"""The console's end of the UDP link: the remote robot as a :class:`~hardware.interfaces.SlaveManipulator`.

Every tick the loop's reference goes out as a COMMAND (``command``) or a HOLD (``hold``); every
:meth:`UdpSlaveLink.poll` drains the socket without blocking (at most ``max_packets_per_poll``
datagrams) and keeps the newest STATE. Nothing but the configured slave address is listened to.

What can go wrong, and what the link does about it (each with a counter in :attr:`UdpSlaveLink.stats`):

* datagrams from another address: dropped (``rejected_peers``);
* oversize, malformed, bad CRC, non-finite values: dropped (``oversize``, ``malformed``, ``crc_errors``,
  ``invalid_values``);
* duplicates and late (reordered) states: dropped, only a newer state is news (``duplicates``, ``late``);
  gaps are counted (``lost``);
* no state for ``timeout_s``: the connection goes LOST (``link_losses``) and the last reading ages, so
  the loop's watchdog latches a hold;
* the slave holding on its own (its watchdog saw our commands stop, or it refused a jump, or its robot
  is down): its readings are *not* published while that lasts, so the loop holds too and the operator
  learns why from ``last_error``. Readings resume once the slave follows again.

Clocks: a STATE carries the slave's clock; :class:`LinkClock` estimates the offset from the echo of our
commands (the NTP calculation, keeping the sample with the shortest round trip over a sliding window),
so readings are stamped on our clock even when master and slave are two PCs.
"""

from __future__ import annotations

import math
import secrets
import socket
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from hardware.connection import Connection
from hardware.interfaces import (
    ConnectionState,
    DeviceError,
    SlaveConstraints,
    SlaveManipulator,
    SlaveState,
    TactileConstraints,
    TactileFrame,
    TactileSensor,
    Vec3,
    finite_vec3,
    tare_problem,
)
from hardware.serial_tactile.config import integer, text
from hardware.settings import ConfigError, Settings, bounded
from hardware.udp import protocol as P
from hardware.udp.intake import Intake, bound_socket
from hardware.udp.protocol import is_loopback
from tissue.face import MAX_COVER_SPREAD_M

RTT_HISTORY = 65536  # round trips kept for the health display and benchmarks


@dataclass(frozen=True)
class UdpLinkSettings(Settings):
    host: str = "127.0.0.1"  # the slave server (`palpation-console slave`)
    port: int = 47600
    bind_host: str = "127.0.0.1"  # our end; loopback unless the slave is another computer
    bind_port: int = 0  # 0: any free port
    timeout_s: float = 0.02  # no state for this long: LOST
    clock_window_s: float = 2.0
    max_packets_per_poll: int = 64
    tactile_timeout_s: float = 0.25  # forwarded tactile frames: none for this long, the view is LOST
    workspace_min_m: tuple[float, float, float] = SlaveConstraints().workspace_min_m
    workspace_max_m: tuple[float, float, float] = SlaveConstraints().workspace_max_m
    max_speed_m_s: float = SlaveConstraints().max_speed_m_s
    rate_hz: float = 1000.0

    def __post_init__(self):
        self._set("host", text("host", self.host))
        self._set("port", integer("port", self.port, 1, 65535))
        self._set("bind_host", text("bind_host", self.bind_host))
        self._set("bind_port", integer("bind_port", self.bind_port, 0, 65535))
        self._set("timeout_s", bounded("timeout_s", self.timeout_s, 0.002, 5.0))
        self._set("clock_window_s", bounded("clock_window_s", self.clock_window_s, 0.1, 60.0))
        self._set("max_packets_per_poll", integer("max_packets_per_poll", self.max_packets_per_poll, 1, 4096))
        self._set("tactile_timeout_s", bounded("tactile_timeout_s", self.tactile_timeout_s, 0.01, 10.0))
        self._set("max_speed_m_s", bounded("max_speed_m_s", self.max_speed_m_s, 1e-3, 10.0))
        self._set("rate_hz", bounded("rate_hz", self.rate_hz, 1.0, 10e3))
        for name in ("workspace_min_m", "workspace_max_m"):
            value = getattr(self, name)
            if isinstance(value, (str, bytes)) or len(value) != 3:
                raise ConfigError(name, f"must be three numbers [x, y, z], got {value!r}")
            self._set(name, tuple(bounded(f"{name}[{i}]", v, -10.0, 10.0) for i, v in enumerate(value)))
        for i, axis in enumerate("xyz"):
            if self.workspace_max_m[i] <= self.workspace_min_m[i]:
                raise ConfigError("workspace_max_m", f"{axis} upper bound must exceed the lower bound")

    def constraints(self) -> SlaveConstraints:
        return SlaveConstraints(self.workspace_min_m, self.workspace_max_m, self.max_speed_m_s, self.rate_hz)


class LinkClock:
    """The slave's clock minus ours, from command echoes (NTP), trusting the shortest recent round trip.

    For a command sent at ``t1`` (our clock), received at ``t2`` (slave clock), echoed in a state sent
    at ``t3`` (slave) and received at ``t4`` (ours): round trip ``(t4 - t1) - (t3 - t2)``, offset
    ``((t2 - t1) + (t3 - t4)) / 2``, exact when both directions take equally long. A sample delayed
    by queueing has a longer round trip and a skewed offset, so the estimate is the offset of the
    sample with the shortest round trip within the last ``window_s`` (which also follows drift).
    """

    def __init__(self, window_s: float = 2.0):
        self.window_s = window_s
        self._best: deque[tuple[float, float, float]] = deque()  # (t4, rtt, offset), rtt increasing
        self.rtt_s = np.full(RTT_HISTORY, np.nan)
        self.samples = 0

    @property
    def offset_s(self) -> float | None:
        return self._best[0][2] if self._best else None

    def add(self, t1: float, t2: float, t3: float, t4: float) -> float:
        rtt = max((t4 - t1) - (t3 - t2), 0.0)
        offset = ((t2 - t1) + (t3 - t4)) / 2.0
        best = self._best
        while best and best[-1][1] >= rtt:
            best.pop()
        best.append((t4, rtt, offset))
        while best[0][0] < t4 - self.window_s:
            best.popleft()
        self.rtt_s[self.samples % RTT_HISTORY] = rtt
        self.samples += 1
        return rtt

    def round_trips_s(self) -> np.ndarray:
        """The recorded round trips, oldest first (at most the last 65536)."""
        n = min(self.samples, RTT_HISTORY)
        start = self.samples % RTT_HISTORY if self.samples > RTT_HISTORY else 0
        return np.roll(self.rtt_s, -start)[:n].copy()


def resolve(host: str, port: int, what: str) -> tuple[str, int]:
    try:
        info = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)
    except (socket.gaierror, UnicodeError) as err:
        raise DeviceError(f"{what}: cannot resolve {host!r}: {err}") from None
    return info[0][4][0], port


class UdpSlaveLink(Connection, SlaveManipulator):
    name = "udp-slave"

    def __init__(self, settings: UdpLinkSettings | None = None):
        super().__init__()
        self.settings = settings if settings is not None else UdpLinkSettings()
        self.constraints = self.settings.constraints()
        self.clock = LinkClock(self.settings.clock_window_s)
        self._sock: socket.socket | None = None
        self._peer: tuple[str, int] | None = None
        self._session = 0
        self._cmd_seq = 0
        self._states = P.SequenceTracker()
        self._tactile_seq = P.SequenceTracker()
        self._latest: SlaveState | None = None
        self._published = -1
        self._last_state_rx: float | None = None
        self._last_echo: int | None = None
        self._sent_any = False
        self._holding_on_its_own = False
        self.slave_status = P.Status.NONE
        self.force_N = math.nan  # the slave's own force measurement, NaN when it has none
        self.tactile: UdpTactileSensor | None = None
        self.counters = dict.fromkeys(("sent", "send_errors", "received", "rejected_peers", "oversize", "malformed",
                                       "crc_errors", "invalid_values", "unexpected", "tactile_ignored", "unmapped",
                                       "link_losses", "slave_holds", "socket_errors"), 0)
        self._intake = Intake(self.counters, self._set_error)

    def _set_error(self, message: str) -> None:
        self.last_error = message

    # ---- Device --------------------------------------------------------------------------------------

    def fileno(self) -> int | None:
        """The socket's descriptor (to wait for packets with select), None while closed."""
        return self._sock.fileno() if self._sock is not None else None

    def _connect(self) -> ConnectionState:
        s = self.settings
        self._peer = resolve(s.host, s.port, "UDP link to the slave")
        if is_loopback(s.bind_host) and not is_loopback(self._peer[0]):
            raise DeviceError(f"UDP link: the slave at {self._peer[0]} is another computer, but the link binds to "
                              f"{s.bind_host}; set hardware.slave.bind_host to this computer's address on that "
                              f"network (or 0.0.0.0)")
        self._sock = bound_socket(s.bind_host, s.bind_port, lambda why: (
            f"UDP link: cannot bind {s.bind_host}:{s.bind_port} ({why}); is another console running, or is "
            f"bind_host not an address of this computer?"))
        self._session = secrets.randbits(32)
        self._sent_any = False
        return ConnectionState.CONNECTING

    def _disconnect(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def poll(self, now_s: float) -> None:
        sock = self._sock
        if sock is None:
            return
        if not self._sent_any:
            self.hold(now_s)  # tells the slave where we are; it answers with states from then on
        peer = self._peer
        c = self.counters
        for header, body, _ in self._intake.packets(sock, self.settings.max_packets_per_poll,
                                                   lambda addr: addr == peer, lambda addr: "the slave"):
            if header.type == P.PacketType.STATE:
                self._on_state(header, body, now_s)  # type: ignore[arg-type]
            elif header.type == P.PacketType.TACTILE:
                if self.tactile is None:
                    c["tactile_ignored"] += 1  # the slave forwards frames this rig takes from elsewhere
                elif self._tactile_seq.accept(header.session, header.seq):
                    self.tactile._on_frame(body, now_s)  # type: ignore[arg-type]
            else:
                c["unexpected"] += 1
        if self._silent(now_s, self._last_state_rx, self.settings.timeout_s, self._silence):
            c["link_losses"] += 1

    # ---- SlaveManipulator ----------------------------------------------------------------------------

    def latest(self) -> SlaveState | None:
        return self._latest

    def command(self, position_m: Vec3, velocity_m_s: Vec3, now_s: float) -> None:
        position = finite_vec3("UDP link: the reference position", position_m)
        velocity = finite_vec3("UDP link: the reference velocity", velocity_m_s)
        self._send(P.Command(P.Mode.TRACK, position, velocity), now_s)

    def hold(self, now_s: float) -> None:
        here = self._latest.position_m if self._latest is not None else (0.0, 0.0, 0.0)
        self._send(P.Command(P.Mode.HOLD, here, (0.0, 0.0, 0.0)), now_s)

    # ---- health --------------------------------------------------------------------------------------

    @property
    def stats(self) -> dict[str, Any]:
        st = self._states
        rtts = self.clock.round_trips_s()[-1000:]
        return {"device": self.name, "slave": f"{self.settings.host}:{self.settings.port}",
                "connection": self._state.name, "last_error": self.last_error, **self.counters,
                "states": st.accepted, "lost": st.lost, "late": st.late, "duplicates": st.duplicates,
                "slave_restarts": st.restarts, "slave_status": P.status_text(self.slave_status),
                "clock_offset_s": self.clock.offset_s,
                "round_trip_p50_us": float(np.median(rtts) * 1e6) if len(rtts) else math.nan,
                "force_N": self.force_N}

    def describe(self) -> dict[str, Any]:
        return {"backend": "udp", "settings": self.settings.to_mapping()}

    def tactile_sensor(self, constraints: TactileConstraints | None = None) -> UdpTactileSensor:
        """The slave's tactile array as forwarded over this link (one view per link)."""
        if self.tactile is None:
            self.tactile = UdpTactileSensor(self, constraints or TactileConstraints())
        return self.tactile

    # ---- internals -----------------------------------------------------------------------------------

    def _send(self, cmd: P.Command, now_s: float) -> None:
        sock = self._sock
        if sock is None:
            return
        data = P.pack_command(self._session, self._cmd_seq, now_s, cmd)
        self._cmd_seq += 1
        try:
            sock.sendto(data, self._peer)
        except OSError as err:  # a full send buffer or an unreachable network: the watchdogs take over
            self.counters["send_errors"] += 1
            self.last_error = f"cannot send to the slave: {err}"
            return
        self._sent_any = True
        self.counters["sent"] += 1

    def _silence(self, silent_s: float) -> str:
        return f"no state from the slave at {self._peer[0]}:{self._peer[1]} for {silent_s * 1e3:.0f} ms"

    def _on_state(self, header: P.Header, st: P.State, now_s: float) -> None:
        if not self._states.accept(header.session, header.seq):
            return
        if st.echo_seq != self._last_echo and not st.status & P.Status.PING_REPLY:
            self._last_echo = st.echo_seq
            self.clock.add(st.echo_t_send_s, st.echo_t_recv_s, header.t_send_s, now_s)
        offset = self.clock.offset_s
        if offset is None:
            self.counters["unmapped"] += 1
            return
        self._last_state_rx = now_s
        self.slave_status = st.status
        self.force_N = st.force_N
        if st.status.unrequested_hold:
            if not self._holding_on_its_own:
                self.counters["slave_holds"] += 1
                self._holding_on_its_own = True
            self._lost(f"the slave is holding on its own ({P.status_text(st.status)}); its readings are withheld")
            return
        self._holding_on_its_own = False
        self._published += 1
        self._latest = SlaveState(seq=self._published, t_s=min(st.t_sample_s - offset, now_s),
                                  position_m=st.position_m, velocity_m_s=st.velocity_m_s)
        self._heard()


@dataclass(frozen=True)
class ForwardedTactileSettings(Settings):
    """``[hardware.sensor] kind = "udp"``: the array whose frames the slave forwards, calibrated and tared on its
    side. What the console must still be told of it is what no frame says."""

    # how far the array's elastomer cover spreads an element's load sideways, as its maker states it (0: not
    # stated); sessions record it, and the analysis's expected pattern is blurred by it
    cover_spread_m: float = 0.0

    def __post_init__(self):
        self._set("cover_spread_m", bounded("cover_spread_m", self.cover_spread_m, 0.0, MAX_COVER_SPREAD_M))

    def constraints(self) -> TactileConstraints:
        return TactileConstraints(cover_spread_m=self.cover_spread_m)


class UdpTactileSensor(TactileSensor):
    """A tactile array on the slave's side, its frames forwarded over a :class:`UdpSlaveLink`.

    Opening, polling and closing act on the link (whichever of the two devices comes first). The
    slave sends frames calibrated and tared; :meth:`tare` re-zeros them here.
    """

    name = "udp-tsi"

    def __init__(self, link: UdpSlaveLink, constraints: TactileConstraints):
        if constraints.shape != (P.ROWS, P.COLS):
            raise ValueError(f"the UDP link forwards {P.ROWS} x {P.COLS} arrays, not {constraints.shape}")
        self.link = link
        self.constraints = constraints
        self._latest: TactileFrame | None = None
        self._untared: np.ndarray | None = None
        self._zero = np.zeros(constraints.shape)
        self._last_rx: float | None = None
        self._lost = False
        self.frames = 0
        self.unmapped = 0

    @property
    def connection(self) -> ConnectionState:
        if self.link.connection == ConnectionState.DISCONNECTED:
            return ConnectionState.DISCONNECTED
        if self._last_rx is None:
            return ConnectionState.CONNECTING
        return ConnectionState.LOST if self._lost else ConnectionState.CONNECTED

    def open(self) -> None:
        self.link.open()

    def close(self) -> None:
        self.link.close()

    def poll(self, now_s: float) -> None:
        self.link.poll(now_s)
        if self._last_rx is not None:
            self._lost = now_s - self._last_rx > self.link.settings.tactile_timeout_s

    def latest(self) -> TactileFrame | None:
        return self._latest

    def tare(self) -> None:
        """Re-zero the forwarded frames at the latest one; DeviceError (nothing changed) if there is none or
        an unloaded array could not give it."""
        if self._untared is None or self._latest is None:
            raise DeviceError("forwarded tactile sensor: no frame has arrived yet to take as zero")
        problem = tare_problem(self._untared, self._latest.saturated, self.constraints.full_scale_pa)
        if problem is not None:
            raise DeviceError(f"forwarded tactile sensor: not tared: {problem}")
        self._zero = self._untared.copy()

    @property
    def stats(self) -> dict[str, Any]:
        t = self.link._tactile_seq
        return {"device": self.name, "connection": self.connection.name, "frames": self.frames, "lost": t.lost,
                "late": t.late, "duplicates": t.duplicates, "unmapped": self.unmapped}

    def describe(self) -> dict[str, Any]:
        return {"backend": "udp-forwarded", "slave": f"{self.link.settings.host}:{self.link.settings.port}"}

    def _on_frame(self, tac: P.Tactile, now_s: float) -> None:
        offset = self.link.clock.offset_s
        if offset is None:
            self.unmapped += 1
            return
        saturated = tac.saturated if tac.saturated is not None else np.zeros(self.constraints.shape, bool)
        # a saturated element reads full scale here (a floor: its true load is unknown and may be more)
        untared = np.where(saturated, self.constraints.full_scale_pa + self._zero, tac.pressure_pa)
        self._untared = untared
        self.frames += 1
        self._last_rx = now_s
        self._latest = TactileFrame(seq=self.frames, t_s=min(tac.t_sample_s - offset, now_s),
                                    pressure_pa=untared - self._zero, saturated=saturated)

