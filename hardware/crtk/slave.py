"""The console's end of a CRTK arm (the dVRK's PSM) over DDS, as a :class:`~hardware.interfaces.SlaveManipulator`.

Topics, on a loopback-only participant (:mod:`hardware.crtk.dds`), named as the arm's ROS 2 bridge names them:
``rt/<ARM>/servo_cp`` (ours: the tool's goal pose), ``state_command`` (ours: "enable", "home") and ``hold`` (ours);
``measured_cp``, ``measured_cv``, ``measured_cf`` and ``operating_state`` (the arm's).

Frames: the console works in the tissue frame; the arm in its base frame. The tissue frame sits in the base frame
at ``tissue_in_base_m``, turned by ``tissue_in_base_rpy_deg`` (roll about x, pitch about y, yaw about z, applied in
that order); the probe face's centre is ``probe_in_tool_m`` from the tool's origin, in the tool frame. The tool's
orientation is the one the arm has when the console connects, kept throughout: the console moves the probe, it does
not turn it.

The arm's rules, followed: it takes ``servo_cp`` only while ENABLED and homed, so :meth:`open` asks it to enable and
home (``enable``, ``home``), waits at most ``open_timeout_s``, and otherwise refuses with the one line the arm's
state calls for. Once connected, the link is LOST, a ``hold`` is sent and no ``servo_cp`` goes out, whenever

* the arm stops being ENABLED and homed (a FAULT, a DISABLE from its own console), or
* no ``measured_cp`` has come for ``timeout_s`` (the arm, its bridge or the bus stalled),

until fresh readings of an ENABLED, homed arm come again; the loop's own watchdogs hold meanwhile. ``hold`` is also
sent on :meth:`close`. :meth:`poll` takes what the readers hold without waiting.

Clocks: the arm is on this computer (the participant is loopback-only), so its stamps are on this wall clock, and a
reading's age is the wall clock's now less its stamp.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from cyclonedds.core import DDSException

from hardware.connection import Connection
from hardware.crtk import dds
from hardware.crtk import messages as M
from hardware.interfaces import (
    ConnectionState,
    DeviceError,
    SlaveConstraints,
    SlaveManipulator,
    SlaveState,
    Vec3,
    finite_vec3,
)
from hardware.serial_tactile.config import boolean, integer, text
from hardware.settings import ConfigError, Settings, bounded

ENABLED = "ENABLED"


def _vec3(key: str, value: Any, limit: float) -> Vec3:
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 3:
        raise ConfigError(key, f"must be three numbers [x, y, z], got {value!r}")
    return tuple(bounded(f"{key}[{i}]", v, -limit, limit) for i, v in enumerate(value))  # type: ignore[return-value]


@dataclass(frozen=True)
class CrtkSettings(Settings):
    arm: str = "PSM1"  # the arm's ROS namespace
    domain: int = 0  # the DDS domain: the ROS side's ROS_DOMAIN_ID
    enable: bool = True  # open() asks a DISABLED arm to enable
    home: bool = True  # open() asks an unhomed arm to home
    open_timeout_s: float = 10.0  # how long open() waits for the arm to be ENABLED and homed
    timeout_s: float = 0.05  # no measured_cp for this long: LOST (the dVRK publishes at 100 Hz by default)
    tissue_in_base_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tissue_in_base_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    probe_in_tool_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_samples_per_poll: int = 64
    workspace_min_m: tuple[float, float, float] = SlaveConstraints().workspace_min_m
    workspace_max_m: tuple[float, float, float] = SlaveConstraints().workspace_max_m
    max_speed_m_s: float = SlaveConstraints().max_speed_m_s
    rate_hz: float = 1000.0

    def __post_init__(self):
        self._set("arm", text("arm", self.arm))
        if not all(c.isalnum() or c == "_" for c in self.arm.replace("/", "")):
            raise ConfigError("arm", f"must be a ROS namespace (letters, digits, _ and /), got {self.arm!r}")
        self._set("domain", dds.domain_id("domain", self.domain))
        self._set("enable", boolean("enable", self.enable))
        self._set("home", boolean("home", self.home))
        self._set("open_timeout_s", bounded("open_timeout_s", self.open_timeout_s, 0.1, 600.0))
        self._set("timeout_s", bounded("timeout_s", self.timeout_s, 0.002, 5.0))
        self._set("tissue_in_base_m", _vec3("tissue_in_base_m", self.tissue_in_base_m, 10.0))
        self._set("tissue_in_base_rpy_deg", _vec3("tissue_in_base_rpy_deg", self.tissue_in_base_rpy_deg, 360.0))
        self._set("probe_in_tool_m", _vec3("probe_in_tool_m", self.probe_in_tool_m, 1.0))
        self._set("max_samples_per_poll", integer("max_samples_per_poll", self.max_samples_per_poll, 1, 4096))
        self._set("max_speed_m_s", bounded("max_speed_m_s", self.max_speed_m_s, 1e-3, 10.0))
        self._set("rate_hz", bounded("rate_hz", self.rate_hz, 1.0, 10e3))
        for name in ("workspace_min_m", "workspace_max_m"):
            self._set(name, _vec3(name, getattr(self, name), 10.0))
        for i, axis in enumerate("xyz"):
            if self.workspace_max_m[i] <= self.workspace_min_m[i]:
                raise ConfigError("workspace_max_m", f"{axis} upper bound must exceed the lower bound")

    def constraints(self) -> SlaveConstraints:
        return SlaveConstraints(self.workspace_min_m, self.workspace_max_m, self.max_speed_m_s, self.rate_hz)

    def topic(self, name: str) -> str:
        return dds.ros_topic(f"{self.arm}/{name}")


def rotation_rpy(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """Rz(yaw) Ry(pitch) Rx(roll): roll about x first, then pitch about y, then yaw about z (fixed axes)."""
    r, p, y = (math.radians(a) for a in (roll_deg, pitch_deg, yaw_deg))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def rotation_quaternion(q: M.Quaternion) -> np.ndarray:
    """The rotation of a quaternion (normalised here: a ROS message's need not be)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(n) or n == 0.0:
        raise DeviceError(f"the arm's orientation is not a rotation: quaternion {(x, y, z, w)}")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def describe_state(state: M.OperatingState | None) -> str:
    """What an arm reports, as a phrase after "arm PSM1 is"."""
    if state is None:
        return "silent"
    homed = "homed" if state.is_homed else "not homed"
    busy = ", busy" if state.is_busy else ""
    return f"{state.state} but {homed}{busy}" if state.state == ENABLED and not state.is_homed else \
        f"{state.state} and {homed}{busy}"


def ready(state: M.OperatingState | None) -> bool:
    """The arm takes servo_cp."""
    return state is not None and state.state == ENABLED and state.is_homed and not state.is_busy


class CrtkSlave(Connection, SlaveManipulator):
    name = "crtk-slave"

    def __init__(self, settings: CrtkSettings | None = None):
        super().__init__()
        self.settings = s = settings if settings is not None else CrtkSettings()
        self.constraints = s.constraints()
        self._base_from_tissue = rotation_rpy(*s.tissue_in_base_rpy_deg)
        self._tissue_origin = np.array(s.tissue_in_base_m)
        self._probe_in_tool = np.array(s.probe_in_tool_m)
        self._bus: dds.Participant | None = None
        self._readers: dict[str, Any] = {}
        self._writers: dict[str, Any] = {}
        self.arm_state: M.OperatingState | None = None
        self._tool_rotation = np.eye(3)
        self._tool_orientation = M.Quaternion()
        self._latest: SlaveState | None = None
        self._velocity = np.zeros(3)
        self._last_rx: float | None = None
        self._holding = False
        self.force_N = math.nan  # the arm's force on the probe along the tissue's z (pressing: positive)
        self.counters = dict.fromkeys(("servo_cp", "holds", "withheld", "measured_cp", "arm_faults", "link_losses",
                                       "send_errors"), 0)

    # ---- Device --------------------------------------------------------------------------------------

    def _connect(self) -> ConnectionState:
        s = self.settings
        try:
            self._bus = bus = dds.Participant(s.domain)
            self._readers = {
                "measured_cp": bus.reader(s.topic("measured_cp"), M.PoseStamped),
                "measured_cv": bus.reader(s.topic("measured_cv"), M.TwistStamped),
                "measured_cf": bus.reader(s.topic("measured_cf"), M.WrenchStamped),
                "operating_state": bus.reader(s.topic("operating_state"), M.OperatingState, dds.LATCHED)}
            self._writers = {
                "servo_cp": bus.writer(s.topic("servo_cp"), M.PoseStamped),
                "state_command": bus.writer(s.topic("state_command"), M.StringStamped, dds.COMMANDS),
                "hold": bus.writer(s.topic("hold"), M.Empty, dds.COMMANDS)}
        except DDSException as err:
            self._disconnect()
            raise DeviceError(f"CRTK arm {s.arm}: cannot join DDS domain {s.domain}: {err}") from None
        try:
            self._await_ready()
        except BaseException:
            self._disconnect()
            raise
        return ConnectionState.CONNECTED

    def _await_ready(self) -> None:
        """Enable and home the arm as the settings allow; wait until it is ready and measuring, or refuse."""
        s = self.settings
        asked: set[str] = set()
        measured: M.PoseStamped | None = None
        deadline = time.monotonic() + s.open_timeout_s
        while True:
            self._take_state()
            measured = self._newest("measured_cp") or measured
            state = self.arm_state
            if ready(state) and measured is not None:
                break
            if state is not None:
                if state.state != ENABLED and s.enable and "enable" not in asked:
                    self._state_command("enable")
                    asked.add("enable")
                elif state.state == ENABLED and not state.is_homed and not state.is_busy and s.home \
                        and "home" not in asked:
                    self._state_command("home")
                    asked.add("home")
            if time.monotonic() > deadline:
                raise DeviceError(self._refusal(state, measured, asked))
            time.sleep(0.002)  # open() may wait: the controller has not started its loop yet
        self._tool_rotation = rotation_quaternion(measured.pose.orientation)
        self._tool_orientation = measured.pose.orientation
        self._on_measured(measured, time.monotonic())

    def _refusal(self, state: M.OperatingState | None, measured: M.PoseStamped | None, asked: set[str]) -> str:
        s = self.settings
        where = f"arm {s.arm} (DDS domain {s.domain})"
        if state is None:
            return (f"{where}: no operating_state within {s.open_timeout_s:g} s; is its ROS 2 side running on this "
                    f"computer with RMW_IMPLEMENTATION=rmw_cyclonedds_cpp and ROS_DOMAIN_ID={s.domain}?")
        if ready(state):
            return f"{where} is ready but published no measured_cp within {s.open_timeout_s:g} s"
        line = f"{where} is {describe_state(state)}; the console drives it only ENABLED and homed"
        if asked:
            line += f" (asked to {' and '.join(sorted(asked))} {s.open_timeout_s:g} s ago)"
        barred = [step for step, allowed in (("enable", s.enable), ("home", s.home)) if not allowed]
        if barred:
            line += (f"; {' and '.join(barred)} it from its own console, or let the console ask "
                     f"(hardware.slave.{barred[0]} = true)")
        return line

    def _disconnect(self) -> None:
        bus, self._bus = self._bus, None
        if bus is None:
            return
        if self._writers:
            self._send_hold()
        self._readers, self._writers = {}, {}
        bus.close()

    def close(self) -> None:
        super().close()
        self._holding = False

    def poll(self, now_s: float) -> None:
        if self._bus is None:
            return
        self._take_state()
        measured = self._newest("measured_cp")
        if not ready(self.arm_state):
            if self._state == ConnectionState.CONNECTED:
                self.counters["arm_faults"] += 1
                self._lost(f"arm {self.settings.arm} is {describe_state(self.arm_state)}")
                self._send_hold()
        elif measured is not None:
            self._on_measured(measured, now_s)
            self._heard()
        if self._silent(now_s, self._last_rx, self.settings.timeout_s, self._silence):
            self.counters["link_losses"] += 1
            self._send_hold()

    # ---- SlaveManipulator ----------------------------------------------------------------------------

    def latest(self) -> SlaveState | None:
        return self._latest

    def command(self, position_m: Vec3, velocity_m_s: Vec3, now_s: float) -> None:
        position = finite_vec3("CRTK arm: the reference position", position_m)
        finite_vec3("CRTK arm: the reference velocity", velocity_m_s)
        if self._state != ConnectionState.CONNECTED:
            self.counters["withheld"] += 1  # the arm holds: a fault is over only once it reads again
            return
        probe_base = self._base_from_tissue @ np.asarray(position) + self._tissue_origin
        tool = probe_base - self._tool_rotation @ self._probe_in_tool
        goal = M.PoseStamped(header=M.Header(stamp=M.stamp(time.time())),
                             pose=M.Pose(position=M.Point(float(tool[0]), float(tool[1]), float(tool[2])),
                                         orientation=self._tool_orientation))
        if self._write("servo_cp", goal):
            self.counters["servo_cp"] += 1
            self._holding = False

    def hold(self, now_s: float) -> None:
        if not self._holding:
            self._send_hold()

    # ---- health --------------------------------------------------------------------------------------

    @property
    def stats(self) -> dict[str, Any]:
        return {"device": self.name, "arm": self.settings.arm, "domain": self.settings.domain,
                "connection": self._state.name, "last_error": self.last_error,
                "arm_state": describe_state(self.arm_state), **self.counters, "force_N": self.force_N}

    def describe(self) -> dict[str, Any]:
        return {"backend": "crtk", "settings": self.settings.to_mapping()}

    # ---- internals -----------------------------------------------------------------------------------

    def _take_state(self) -> None:
        state = self._newest("operating_state")
        if state is not None:
            self.arm_state = state

    def _newest(self, reader: str):
        samples = dds.take(self._readers[reader], self.settings.max_samples_per_poll)
        return samples[-1] if samples else None

    def _on_measured(self, cp: M.PoseStamped, now_s: float) -> None:
        self.counters["measured_cp"] += 1
        self._last_rx = now_s
        p = cp.pose.position
        self._tool_rotation = rotation_quaternion(cp.pose.orientation)
        offset = self._tool_rotation @ self._probe_in_tool
        probe = self._base_from_tissue.T @ (np.array((p.x, p.y, p.z)) + offset - self._tissue_origin)
        cv = self._newest("measured_cv")
        if cv is not None:
            v, w = cv.twist.linear, cv.twist.angular
            self._velocity = self._base_from_tissue.T @ (np.array((v.x, v.y, v.z))
                                                         + np.cross((w.x, w.y, w.z), offset))
        cf = self._newest("measured_cf")
        if cf is not None:
            f = cf.wrench.force
            self.force_N = float((self._base_from_tissue.T @ np.array((f.x, f.y, f.z)))[2])
        age = max(time.time() - M.seconds(cp.header.stamp), 0.0)
        seq = self._latest.seq + 1 if self._latest is not None else 0
        self._latest = SlaveState(seq=seq, t_s=now_s - age, position_m=tuple(float(c) for c in probe),
                                  velocity_m_s=tuple(float(c) for c in self._velocity))

    def _state_command(self, command: str) -> None:
        self._write("state_command", M.StringStamped(header=M.Header(stamp=M.stamp(time.time())), string=command))

    def _send_hold(self) -> None:
        if self._write("hold", M.Empty()):
            self.counters["holds"] += 1
            self._holding = True

    def _write(self, writer: str, sample) -> bool:
        try:
            self._writers[writer].write(sample)
        except (DDSException, KeyError) as err:  # KeyError: closed; the watchdogs and the arm's own take over
            self.counters["send_errors"] += 1
            self.last_error = f"cannot send {writer} to arm {self.settings.arm}: {err}"
            return False
        return True

    def _silence(self, silent_s: float) -> str:
        return f"no measured_cp from arm {self.settings.arm} for {silent_s * 1e3:.0f} ms"
