"""The slave's end of the UDP link, in front of a robot (simulated or real; ``palpation-console slave`` is
:mod:`app.slave`).

Each :meth:`SlaveServer.step` (1 kHz in :meth:`SlaveServer.serve`) polls the robot, drains the socket
without blocking, applies the newest command, runs the link watchdog and sends the robot's state (and a
tactile frame when the slave-side sensor has a new one) to the master.

Safety rules, all on this side so they hold whatever the master does, from the slave's own settings:

* Only peers on the allow-list may command or ping; the socket binds to loopback unless told otherwise,
  and binding elsewhere requires an explicit allow-list.
* One master at a time: a command from another address or another session is refused while the current
  master has been heard within ``link_timeout_s``; after that it takes over. A session that has already
  been replaced is never accepted again (a delayed packet from before a restart).
* Only a command newer than the newest applied one is applied (late and duplicate packets are dropped).
* Link watchdog: no command for ``link_timeout_s`` latches LINK_TIMEOUT and holds the robot. The state
  packets say so, and the console withholds the readings, so its loop holds as well.
* Jump guard, always: a reference farther than ``resume_distance_m`` from the last one applied (or, while
  holding, from where the robot is) is refused (JUMP_REFUSED) and the robot holds, so neither a stale
  reference nor a lying master can yank it away. After a latched hold the robot follows again once the
  master sends HOLD (it has noticed) and then a reference near the robot.
* The slave's own soft limits: each reference is cut to its workspace and its speed limit (the robot's
  own by default, narrower if configured; LIMITED says it happened).
* The slave's own force limit (with a slave-side sensor): above ``force_limit_N`` it latches FORCE_LIMIT
  and holds, following only references that lift the probe, until the force is back below 80 % of the limit.
* The slave's own check that its array still reads (:mod:`hardware.liveness`, the console's own checks):
  no new frame, or only frames repeating the one before, for ``sensor_timeout_s``, or the robot
  ``unexplained_travel_m`` deeper than where the force last rose while pressing, latches SENSOR_LOST: the same
  hold, lifting only, until the array reads again and the probe is off the tissue.
* Until a master has spoken, the robot holds.
"""

from __future__ import annotations

import ipaddress
import math
import secrets
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from hardware.interfaces import ConnectionState, SlaveManipulator, TactileSensor, Vec3
from hardware.liveness import RepeatWatch, TravelWatch
from hardware.serial_tactile.config import integer, text
from hardware.settings import ConfigError, Settings, bounded, vec3
from hardware.udp import protocol as P
from hardware.udp.intake import Intake, bound_socket
from hardware.udp.protocol import is_loopback

DEFAULT_PORT = 47600
FORCE_RESUME_FRACTION = 0.8  # below this share of the force limit the latch lets go (no chattering at it)
CONTACT_N = 0.3  # more than this on the slave's array is pressing tissue (its noise is a few mN)
FORCE_RISE_N = 0.05  # what counts as the force rising, for the travel below the last rise
SENSOR_GRACE_S = 1.0  # after start-up, before the array's first frame is due
RETIRED_SESSIONS = 64  # replaced masters' sessions remembered, so their delayed packets stay refused
STEP_TOLERANCE_M = 1e-6  # rounding in the master's reference: far below any step that matters


def _network(key: str, value: Any) -> ipaddress.IPv4Network | ipaddress.IPv6Network:
    try:
        return ipaddress.ip_network(text(key, value), strict=False)
    except ValueError:
        raise ConfigError(key, f"must be an IP address or network like 192.168.1.20 or 10.0.0.0/24, "
                               f"got {value!r}") from None


@dataclass(frozen=True)
class SlaveServerSettings(Settings):
    bind_host: str = "127.0.0.1"
    port: int = DEFAULT_PORT  # 0: any free port (tests)
    allow: tuple[str, ...] = ()  # peers that may command; empty: loopback only (refused if not bound there)
    link_timeout_s: float = 0.02
    resume_distance_m: float = 0.002
    rate_hz: float = 1000.0
    max_packets_per_step: int = 64
    forward_tactile: bool = True
    # the slave's own limits; unset: the robot's (its constraints)
    workspace_min_m: Vec3 | None = None
    workspace_max_m: Vec3 | None = None
    max_speed_m_s: float | None = None
    force_limit_N: float = 15.0  # above the console's 12 N ceiling (it acts first), below the TSI's 23 N full scale
    sensor_timeout_s: float = 0.06  # as the console's: six frames of a 100 frames/s array
    unexplained_travel_m: float = 1e-3  # a backstop behind the console's 0.6 mm

    def __post_init__(self):
        self._set("bind_host", text("bind_host", self.bind_host))
        self._set("port", integer("port", self.port, 0, 65535))
        if isinstance(self.allow, str):
            raise ConfigError("allow", f"must be a list of addresses, got {self.allow!r}")
        allow = tuple(text(f"allow[{i}]", a) for i, a in enumerate(self.allow))
        for i, a in enumerate(allow):
            _network(f"allow[{i}]", a)
        if not allow:
            if not is_loopback(self.bind_host):
                raise ConfigError("allow", f"binding to {self.bind_host} exposes the robot to the network: "
                                           f"list the master's address(es) to allow (e.g. --allow 192.168.1.20)")
            allow = ("127.0.0.1",)
        self._set("allow", allow)
        self._set("link_timeout_s", bounded("link_timeout_s", self.link_timeout_s, 0.002, 1.0,
                                             "the robot must stop soon after the master goes quiet"))
        self._set("resume_distance_m", bounded("resume_distance_m", self.resume_distance_m, 0.0, 0.05))
        self._set("rate_hz", bounded("rate_hz", self.rate_hz, 10.0, 10e3))
        self._set("max_packets_per_step", integer("max_packets_per_step", self.max_packets_per_step, 1, 4096))
        if not isinstance(self.forward_tactile, bool):
            raise ConfigError("forward_tactile", f"must be true or false, got {self.forward_tactile!r}")
        for key in ("workspace_min_m", "workspace_max_m"):
            if getattr(self, key) is not None:
                self._set(key, vec3(key, getattr(self, key)))
        lo, hi = self.workspace_min_m, self.workspace_max_m
        if lo is not None and hi is not None and not all(a < b for a, b in zip(lo, hi)):
            raise ConfigError("workspace_max_m", f"must exceed workspace_min_m on every axis, got {lo} and {hi}")
        if self.max_speed_m_s is not None:
            self._set("max_speed_m_s", bounded("max_speed_m_s", self.max_speed_m_s, 1e-3, 0.5,
                                                "a palpation robot near tissue"))
        self._set("sensor_timeout_s", bounded("sensor_timeout_s", self.sensor_timeout_s, 0.01, 1.0,
                                              "a second without data is a lost device"))
        self._set("unexplained_travel_m", bounded("unexplained_travel_m", self.unexplained_travel_m, 0.2e-3, 5e-3,
                                                  "deeper is driving into the tissue blind"))
        self._set("force_limit_N", bounded("force_limit_N", self.force_limit_N, 0.1, 30.0,
                                            "the TSI's full scale is 23 N"))

    def allows(self, host: str) -> bool:
        try:
            addr = ipaddress.ip_address(host)
        except ValueError:
            return False
        return any(addr in ipaddress.ip_network(a, strict=False) for a in self.allow)


class SlaveServer:
    def __init__(self, robot: SlaveManipulator, settings: SlaveServerSettings | None = None,
                 sensor: TactileSensor | None = None):
        self.robot = robot
        self.sensor = sensor
        self.settings = settings if settings is not None else SlaveServerSettings()
        self._sock: socket.socket | None = None
        self._session = 0
        self._state_seq = 0
        self._tactile_seq = 0
        self._commands = P.SequenceTracker()
        self._master: tuple[str, int] | None = None
        self._last_cmd_rx: float | None = None
        self._echo = (0, 0.0, 0.0)  # seq, t_send (master clock), t_recv (ours) of the newest command
        self._mode = P.Mode.HOLD
        self._latched = P.Status.NONE  # LINK_TIMEOUT | JUMP_REFUSED | FORCE_LIMIT | SENSOR_LOST: its own hold
        self._held_at_start = False
        self._sent_sensor_seq: int | None = None
        self._retired: deque[int] = deque(maxlen=RETIRED_SESSIONS)
        self._applied: tuple[Vec3, float] | None = None  # the last reference sent to the robot, and when
        self._limited = False
        # where the robot was when the force limit or the lost array latched: no lower, no sideways, from there
        self._force_hold: Vec3 | None = None
        self._repeats = RepeatWatch(sensor.constraints.shape) if sensor is not None else None
        self._travel = TravelWatch(FORCE_RISE_N)
        self._sensor_seq: int | None = None
        self._fresh_s: float | None = None  # when the array last said something new (our clock)
        self._started_s: float | None = None
        c = robot.constraints
        st = self.settings
        self._lo = st.workspace_min_m if st.workspace_min_m is not None else c.workspace_min_m
        self._hi = st.workspace_max_m if st.workspace_max_m is not None else c.workspace_max_m
        self._vmax = st.max_speed_m_s if st.max_speed_m_s is not None else c.max_speed_m_s
        self.counters = dict.fromkeys(("received", "rejected_peers", "oversize", "malformed", "crc_errors",
                                       "invalid_values", "unexpected", "pings", "link_timeouts", "jumps_refused",
                                       "master_changes", "takeovers_refused", "stale_sessions", "limited",
                                       "force_limits", "sensor_lost", "sent", "send_errors", "socket_errors"), 0)
        self.last_error = ""
        self._intake = Intake(self.counters, self._set_error)

    def _set_error(self, message: str) -> None:
        self.last_error = message

    @property
    def address(self) -> tuple[str, int]:
        if self._sock is None:
            raise RuntimeError("the slave server is not open")
        return self._sock.getsockname()

    def fileno(self) -> int:
        """The socket's descriptor (to step as soon as a packet arrives)."""
        if self._sock is None:
            raise RuntimeError("the slave server is not open")
        return self._sock.fileno()

    @property
    def status(self) -> P.Status:
        st = self._latched
        if st or self._mode == P.Mode.HOLD:
            st |= P.Status.HOLDING
        if self._limited:
            st |= P.Status.LIMITED
        if self.robot.connection != ConnectionState.CONNECTED:
            st |= P.Status.ROBOT_FAULT
        return st

    def open(self) -> None:
        s = self.settings
        sock = bound_socket(s.bind_host, s.port, lambda why: (
            f"slave: cannot listen on {s.bind_host}:{s.port} ({why}); is another slave running?"))
        opened = []
        try:
            for device in (self.robot, self.sensor):
                if device is not None:
                    device.open()
                    opened.append(device)
        except BaseException:
            for device in reversed(opened):
                device.close()
            sock.close()
            raise
        self._sock = sock
        self._session = secrets.randbits(32)

    def close(self, now_s: float | None = None) -> None:
        if self._sock is None:
            return
        try:
            self.robot.hold(time.monotonic() if now_s is None else now_s)
        finally:
            self._sock.close()
            self._sock = None
            if self.sensor is not None:
                self.sensor.close()
            self.robot.close()

    # ---- one step ------------------------------------------------------------------------------------

    def step(self, now_s: float) -> None:
        sock = self._sock
        if sock is None:
            raise RuntimeError("the slave server is not open")
        self.robot.poll(now_s)
        if self.sensor is not None:
            self.sensor.poll(now_s)
        if not self._held_at_start:
            self.robot.hold(now_s)  # nobody has commanded anything yet
            self._held_at_start = True
        self._supervise_sensor(now_s)
        self._supervise_force(now_s)
        newest = self._drain(sock, now_s)
        if newest is not None:
            self._apply(newest, now_s)
        self._watchdog(now_s)
        if self._master is not None:
            self._send_state(self._master, now_s, P.Status.NONE)
            if self.sensor is not None and self.settings.forward_tactile:
                self._send_tactile(self._master, now_s)

    def _drain(self, sock: socket.socket, now_s: float) -> P.Command | None:
        c = self.counters
        newest: P.Command | None = None
        for header, body, addr in self._intake.packets(sock, self.settings.max_packets_per_step,
                                                      lambda addr: self.settings.allows(addr[0]),
                                                      lambda addr: f"{addr[0]}:{addr[1]}"):
            if header.type == P.PacketType.PING:
                c["pings"] += 1
                self._send_state(addr, now_s, P.Status.PING_REPLY, echo=(header.seq, header.t_send_s, now_s))
            elif header.type == P.PacketType.COMMAND:
                if not self._admit(addr, header.session, now_s):
                    continue
                if self._commands.accept(header.session, header.seq):
                    self._master = addr
                    self._last_cmd_rx = now_s
                    self._echo = (header.seq, header.t_send_s, now_s)
                    newest = body  # type: ignore[assignment]
            else:
                c["unexpected"] += 1
        return newest

    def _admit(self, addr: tuple[str, int], session: int, now_s: float) -> bool:
        """Whether a command from ``addr`` in ``session`` may command: the current master, or a new one once
        the current one has been silent past the link timeout; never a session that was replaced."""
        c = self.counters
        if session in self._retired:
            return self._count_stale(session)
        if self._master is None or (addr == self._master and session == self._commands.session):
            return True
        if self._last_cmd_rx is not None and now_s - self._last_cmd_rx <= self.settings.link_timeout_s:
            if not c["takeovers_refused"]:
                self.last_error = (f"refused commands from {addr[0]}:{addr[1]}: the master at {self._master[0]}:"
                                   f"{self._master[1]} is still talking")
            c["takeovers_refused"] += 1
            return False
        c["master_changes"] += 1
        if self._commands.session is not None:
            self._retired.append(self._commands.session)
        return True

    def _count_stale(self, session: int) -> bool:
        self.counters["stale_sessions"] += 1
        self.last_error = f"refused a command from session {session:#x}, which another master session replaced"
        return False

    def _hold(self, now_s: float) -> None:
        self._applied = None
        self.robot.hold(now_s)

    def _apply(self, cmd: P.Command, now_s: float) -> None:
        robot = self.robot
        if cmd.mode == P.Mode.HOLD:
            self._latched &= ~(P.Status.LINK_TIMEOUT | P.Status.JUMP_REFUSED)  # the master knows
            self._mode = P.Mode.HOLD
            self._hold(now_s)
            return
        here = robot.latest()
        # the jump guard: from the last reference applied while tracking, from the robot while holding
        anchor = self._applied[0] if self._applied is not None and not self._latched else (
            None if here is None else here.position_m)
        if anchor is None or math.dist(anchor, cmd.position_m) > self.settings.resume_distance_m:
            if not self._latched & P.Status.JUMP_REFUSED:
                self.counters["jumps_refused"] += 1
                dist = "unknown" if anchor is None else f"{math.dist(anchor, cmd.position_m) * 1e3:.1f} mm"
                self.last_error = (f"refused a reference {dist} away from the "
                                   f"{'last one' if self._applied is not None else 'robot'} "
                                   f"(limit {self.settings.resume_distance_m * 1e3:.1f} mm): holding")
            self._latched |= P.Status.JUMP_REFUSED
            self._hold(now_s)
            return
        self._latched &= ~(P.Status.LINK_TIMEOUT | P.Status.JUMP_REFUSED)  # near the robot: follow again
        position, velocity = self._limit(cmd.position_m, cmd.velocity_m_s, anchor, now_s)
        self._mode = P.Mode.TRACK
        self._applied = (position, now_s)
        robot.command(position, velocity, now_s)

    def _limit(self, position: Vec3, velocity: Vec3, anchor: Vec3, now_s: float) -> tuple[Vec3, Vec3]:
        """The reference cut to the slave's own limits: its workspace, no faster than its speed limit from
        the last reference applied, and while the force limit is latched no lower than where it latched."""
        p = [min(max(position[i], self._lo[i]), self._hi[i]) for i in range(3)]
        if self._force_hold is not None:
            p = [self._force_hold[0], self._force_hold[1], max(p[2], self._force_hold[2])]
        elapsed = now_s - self._applied[1] if self._applied is not None else 1.0 / self.settings.rate_hz
        reach = self._vmax * max(elapsed, 1.0 / self.settings.rate_hz)
        step = math.dist(p, anchor)
        if step > reach + STEP_TOLERANCE_M:
            p = [anchor[i] + (p[i] - anchor[i]) * reach / step for i in range(3)]
        v = list(velocity)
        speed = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
        if speed > self._vmax:
            v = [vi * self._vmax / speed for vi in v]
        if self._force_hold is not None:
            v = [0.0, 0.0, max(v[2], 0.0)]
        limited = tuple(p) != tuple(position) or tuple(v) != tuple(velocity)
        if limited:
            self.counters["limited"] += 1
        self._limited = limited
        return (p[0], p[1], p[2]), (v[0], v[1], v[2])

    def _supervise_force(self, now_s: float) -> None:
        """The slave's own force limit, on its own sensor's reading (none without a slave-side sensor)."""
        force = self._force_N()
        limit = self.settings.force_limit_N
        if not self._latched & P.Status.FORCE_LIMIT:
            if force > limit:
                self._lift_only(P.Status.FORCE_LIMIT, f"force {force:.1f} N above the slave's own {limit:g} N limit",
                                now_s)
        elif force < FORCE_RESUME_FRACTION * limit:
            self._let_go(P.Status.FORCE_LIMIT)

    def _supervise_sensor(self, now_s: float) -> None:
        """Whether the slave's own array still reads: fresh frames, and force rising as the robot presses deeper."""
        if self.sensor is None:
            return
        if self._started_s is None:
            self._started_s = now_s
        frame = self.sensor.latest()
        here = self.robot.latest()
        if frame is not None and frame.seq != self._sensor_seq:
            self._sensor_seq = frame.seq
            if self._repeats.push(frame.pressure_pa, frame.t_s):
                self._fresh_s = now_s
            force = self._force_N()
            if force > CONTACT_N and here is not None:
                self._travel.push(force, here.position_m[2])
        if here is not None and here.position_m[2] > self._travel.peak_z_m:
            self._travel.reset()  # lifted above where it last pressed: off the tissue
        heard = self._fresh_s if self._fresh_s is not None else self._started_s + SENSOR_GRACE_S
        silent = now_s - heard > self.settings.sensor_timeout_s
        travel = self._travel.travel_m(here.position_m[2]) if here is not None else math.nan
        if not self._latched & P.Status.SENSOR_LOST:
            if silent:
                repeats = self._repeats.repeats
                self._lift_only(P.Status.SENSOR_LOST, f"the slave's tactile array has said nothing new for "
                                f"{(now_s - heard) * 1e3:.0f} ms" + (f" ({repeats + 1} identical frames: frozen)"
                                                                     if repeats else ""), now_s)
            elif travel > self.settings.unexplained_travel_m:
                self._lift_only(P.Status.SENSOR_LOST, f"the robot went {travel * 1e3:.1f} mm deeper without the "
                                f"slave's tactile force rising above {self._travel.peak_N:.2f} N", now_s)
        elif not silent and not travel > 0.0:  # reading again, and lifted back above where it last pressed
            self._let_go(P.Status.SENSOR_LOST)

    def _lift_only(self, flag: P.Status, why: str, now_s: float) -> None:
        """Latch ``flag``: hold, and from here follow only references that lift the probe."""
        if self._force_hold is None:
            here = self.robot.latest()
            if here is None:
                return
            self._force_hold = here.position_m
        self._latched |= flag
        self.counters["force_limits" if flag == P.Status.FORCE_LIMIT else "sensor_lost"] += 1
        self.last_error = f"{why}: holding, and following only references that lift the probe"
        self._hold(now_s)

    def _let_go(self, flag: P.Status) -> None:
        self._latched &= ~flag
        if not self._latched & (P.Status.FORCE_LIMIT | P.Status.SENSOR_LOST):
            self._force_hold = None

    def _force_N(self) -> float:
        if self.sensor is None:
            return math.nan
        frame = self.sensor.latest()
        if frame is None:
            return math.nan
        return float(frame.pressure_pa.sum()) * self.sensor.constraints.element_area_m2

    def _watchdog(self, now_s: float) -> None:
        last = self._last_cmd_rx
        if last is None:
            return
        if now_s - last > self.settings.link_timeout_s:
            if not self._latched & P.Status.LINK_TIMEOUT:
                self._latched |= P.Status.LINK_TIMEOUT
                self.counters["link_timeouts"] += 1
                self.last_error = f"no command from the master for {(now_s - last) * 1e3:.0f} ms: holding"
            self._hold(now_s)

    def _send(self, data: bytes, addr: tuple[str, int]) -> None:
        try:
            self._sock.sendto(data, addr)  # type: ignore[union-attr]
        except OSError as err:
            self.counters["send_errors"] += 1
            self.last_error = f"cannot send to {addr[0]}:{addr[1]}: {err}"
            return
        self.counters["sent"] += 1

    def _send_state(self, addr: tuple[str, int], now_s: float, extra: P.Status,
                    echo: tuple[int, float, float] | None = None) -> None:
        reading = self.robot.latest()
        if reading is None:
            return
        force = self._force_N()
        e = self._echo if echo is None else echo
        state = P.State(self.status | extra, reading.seq, reading.t_s, reading.position_m, reading.velocity_m_s,
                        force, e[0], e[1], e[2])
        self._send(P.pack_state(self._session, self._state_seq, now_s, state), addr)
        self._state_seq += 1

    def _send_tactile(self, addr: tuple[str, int], now_s: float) -> None:
        frame = self.sensor.latest()  # type: ignore[union-attr]
        if frame is None or frame.seq == self._sent_sensor_seq:
            return
        self._sent_sensor_seq = frame.seq
        tac = P.Tactile(frame.seq, frame.t_s, frame.pressure_pa, frame.saturated)
        self._send(P.pack_tactile(self._session, self._tactile_seq, now_s, tac), addr)
        self._tactile_seq += 1

    # ---- running -------------------------------------------------------------------------------------

    @property
    def stats(self) -> dict[str, Any]:
        cmd = self._commands
        master = f"{self._master[0]}:{self._master[1]}" if self._master else ""
        return {"device": "udp-slave-server", "master": master, "status": int(self.status),
                "last_error": self.last_error, **self.counters, "commands": cmd.accepted, "lost": cmd.lost,
                "late": cmd.late, "duplicates": cmd.duplicates, "master_restarts": cmd.restarts}

    def serve(self, stop: threading.Event, duration_s: float | None = None, on_step=None) -> int:
        """Step at ``rate_hz`` on absolute deadlines until ``stop`` is set (or ``duration_s`` passes).

        A late step is not repeated: the next deadline after now is taken (the watchdog measures real
        time anyway). ``on_step(now_s)`` runs after each step (a slave-side emulator's pump). Returns
        the number of steps.
        """
        period = 1.0 / self.settings.rate_hz
        t0 = time.monotonic()
        end = math.inf if duration_s is None else t0 + duration_s
        k = 0
        steps = 0
        while not stop.is_set():
            now = time.monotonic()
            if now >= end:
                break
            self.step(now)
            if on_step is not None:
                on_step(now)
            steps += 1
            k = max(k + 1, int((time.monotonic() - t0) / period) + 1)
            delay = t0 + k * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        return steps
