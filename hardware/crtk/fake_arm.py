"""A fake dVRK arm on DDS: the CRTK backend's test double, in a process of its own.

``python -m hardware.crtk.fake_arm --arm PSM1 --domain N`` speaks, on the loopback only, what a dVRK arm's ROS 2
bridge speaks (topics ``rt/<ARM>/...``, :mod:`hardware.crtk.messages`), and behaves as the arm does where the
console can tell:

* its operating state starts DISABLED and not homed; ``state_command`` "enable" makes it ENABLED, "home" (while
  ENABLED) busy for ``homing_s`` and then homed, at ``home_m``; "disable" makes it DISABLED (and still), "unhome"
  not homed. The state is published transient-local, on every change, so a late subscriber has it at once;
* ``servo_cp`` is obeyed only while ENABLED, homed and not busy; otherwise it is ignored, and why is logged (once
  per state) on stderr;
* the tool follows the last ``servo_cp`` goal through second-order dynamics (``bandwidth_hz``, ``damping``,
  acceleration limited to ``max_accel_m_s2``, integrated a period at a time, however long since the last
  tick), or, ``ideal``, reaches it at the next tick; the orientation is taken as commanded. ``hold`` makes the
  goal where the tool is (the dVRK holds at its setpoint);
* every tick (``rate_hz``) it publishes ``measured_cp``, ``measured_cv`` and ``measured_cf``: the force of a
  spring floor, ``floor_stiffness_N_m`` below ``floor_z_m`` (base frame, z up), on the tool.

It stops cleanly on SIGTERM or SIGINT (its participant deleted, so its readers and writers leave the bus).
Stamps are the wall clock, as ROS's are.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from dataclasses import dataclass

from hardware.crtk import dds
from hardware.crtk import messages as M
from hardware.serial_tactile.config import boolean, text
from hardware.settings import ConfigError, Settings, bounded, vec3

DISABLED, ENABLED = "DISABLED", "ENABLED"


@dataclass(frozen=True)
class FakeArmSettings(Settings):
    arm: str = "PSM1"
    domain: int = 0
    rate_hz: float = 1000.0
    bandwidth_hz: float = 20.0
    damping: float = 1.0
    max_accel_m_s2: float = 20.0
    ideal: bool = False  # True: each servo_cp goal is where the tool is at the next tick
    homing_s: float = 0.05
    home_m: tuple[float, float, float] = (0.0, 0.0, -0.10)
    floor_z_m: float = -0.15
    floor_stiffness_N_m: float = 500.0

    def __post_init__(self):
        self._set("arm", text("arm", self.arm))
        self._set("domain", dds.domain_id("domain", self.domain))
        self._set("rate_hz", bounded("rate_hz", self.rate_hz, 100.0, 10e3, "the dVRK publishes at 100 Hz or more"))
        self._set("bandwidth_hz", bounded("bandwidth_hz", self.bandwidth_hz, 0.1, 1e3))
        self._set("damping", bounded("damping", self.damping, 0.05, 10.0))
        self._set("max_accel_m_s2", bounded("max_accel_m_s2", self.max_accel_m_s2, 1e-3, 1e4))
        self._set("ideal", boolean("ideal", self.ideal))
        self._set("homing_s", bounded("homing_s", self.homing_s, 0.0, 60.0))
        self._set("home_m", vec3("home_m", self.home_m))
        self._set("floor_z_m", bounded("floor_z_m", self.floor_z_m, -10.0, 10.0))
        self._set("floor_stiffness_N_m", bounded("floor_stiffness_N_m", self.floor_stiffness_N_m, 0.0, 1e6))


class FakeArm:
    """The arm's state and dynamics, advanced by :meth:`step`; :func:`run` paces it in real time."""

    def __init__(self, settings: FakeArmSettings, log=None):
        self.settings = s = settings
        self._log = log if log is not None else (lambda line: print(line, file=sys.stderr, flush=True))
        self.state = DISABLED
        self.homed = False
        self._homed_at: float | None = None  # homing: when it will be done
        self.position = list(s.home_m)
        self.velocity = [0.0, 0.0, 0.0]
        self.goal = list(s.home_m)
        self.orientation = M.Quaternion()
        self.refused = 0
        self._refusal = ""
        self.bus = dds.Participant(s.domain)
        topic = f"{s.arm}/"
        self._servo_cp = self.bus.reader(dds.ros_topic(topic + "servo_cp"), M.PoseStamped, dds.COMMANDS)
        self._state_command = self.bus.reader(dds.ros_topic(topic + "state_command"), M.StringStamped, dds.COMMANDS)
        self._hold = self.bus.reader(dds.ros_topic(topic + "hold"), M.Empty, dds.COMMANDS)
        self._measured_cp = self.bus.writer(dds.ros_topic(topic + "measured_cp"), M.PoseStamped)
        self._measured_cv = self.bus.writer(dds.ros_topic(topic + "measured_cv"), M.TwistStamped)
        self._measured_cf = self.bus.writer(dds.ros_topic(topic + "measured_cf"), M.WrenchStamped)
        self._operating_state = self.bus.writer(dds.ros_topic(topic + "operating_state"), M.OperatingState,
                                                dds.LATCHED)
        self._publish_state()

    @property
    def busy(self) -> bool:
        return self._homed_at is not None

    def close(self) -> None:
        self.bus.close()

    def step(self, dt: float) -> None:
        """Take the commands that came, move the tool ``dt`` on, publish what it measures."""
        now = time.time()
        for command in dds.take(self._state_command, 16):
            self._on_state_command(command.string, now)
        if self._homed_at is not None and now >= self._homed_at:
            self._homed_at = None
            self.homed = True
            self.position, self.velocity, self.goal = list(self.settings.home_m), [0.0, 0.0, 0.0], list(
                self.settings.home_m)
            self._publish_state()
        for _ in dds.take(self._hold, 16):
            self.goal = list(self.position)
        for goal in dds.take(self._servo_cp, 16):
            self._on_servo_cp(goal)
        if self.state == ENABLED and not self.busy:
            # A stall of this process is time the arm still moves through: one Euler step over all of it had
            # the tool jump 9 mm in 26 ms, which the console rightly refused as no robot's motion.
            steps = max(1, math.ceil(dt * self.settings.rate_hz - 1e-9))
            for _ in range(steps):
                self._advance(dt / steps)
        else:
            self.velocity = [0.0, 0.0, 0.0]
        self._publish_measured(now)

    def _on_state_command(self, command: str, now: float) -> None:
        if command == "enable":
            self.state = ENABLED
        elif command == "disable":
            self.state = DISABLED
            self._homed_at = None
        elif command == "home" and self.state == ENABLED:
            self._homed_at = now + self.settings.homing_s
        elif command == "unhome":
            self.homed = False
        else:
            self._log(f"fake arm {self.settings.arm}: ignored state_command {command!r} while {self.state}")
            return
        self._publish_state()

    def _on_servo_cp(self, goal: M.PoseStamped) -> None:
        why = ("it is DISABLED" if self.state != ENABLED else "it is homing" if self.busy
               else "it is not homed" if not self.homed else "")
        if why:
            self.refused += 1
            if why != self._refusal:
                self._log(f"fake arm {self.settings.arm}: servo_cp refused: {why}")
            self._refusal = why
            return
        self._refusal = ""
        p = goal.pose.position
        self.goal = [p.x, p.y, p.z]
        self.orientation = goal.pose.orientation
        if self.settings.ideal:
            self.position = list(self.goal)

    def _advance(self, dt: float) -> None:
        s = self.settings
        if s.ideal:
            return
        w = 2.0 * math.pi * s.bandwidth_hz
        x, v = self.position, self.velocity
        a = [w * w * (g - p) - 2.0 * s.damping * w * u for g, p, u in zip(self.goal, x, v)]
        norm = math.sqrt(sum(c * c for c in a))
        if norm > s.max_accel_m_s2:
            a = [c * s.max_accel_m_s2 / norm for c in a]
        for i in range(3):
            v[i] += a[i] * dt
            x[i] += v[i] * dt

    def _publish_state(self) -> None:
        self._operating_state.write(M.OperatingState(header=M.Header(stamp=M.stamp(time.time())), state=self.state,
                                                     is_homed=self.homed, is_busy=self.busy))

    def _publish_measured(self, now: float) -> None:
        header = M.Header(stamp=M.stamp(now))
        x, v = self.position, self.velocity
        self._measured_cp.write(M.PoseStamped(header=header, pose=M.Pose(position=M.Point(*x),
                                                                         orientation=self.orientation)))
        self._measured_cv.write(M.TwistStamped(header=header, twist=M.Twist(linear=M.Vector3(*v))))
        depth = self.settings.floor_z_m - x[2]
        force = self.settings.floor_stiffness_N_m * depth if depth > 0.0 else 0.0
        self._measured_cf.write(M.WrenchStamped(header=header, wrench=M.Wrench(force=M.Vector3(0.0, 0.0, force))))


def run(settings: FakeArmSettings) -> None:
    """Run the arm at ``settings.rate_hz`` until SIGTERM or SIGINT."""
    stop = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.append(True))
    arm = FakeArm(settings)
    period = 1.0 / settings.rate_hz
    try:
        print(f"fake arm {settings.arm} on DDS domain {settings.domain} (loopback)", flush=True)
        last = deadline = time.monotonic()
        while not stop:
            now = time.monotonic()
            arm.step(now - last)
            last = now
            deadline += period
            if deadline < now:  # a stall: carry on from now rather than replaying missed ticks back to back
                deadline = now
            time.sleep(max(deadline - time.monotonic(), 0.0))
    finally:
        arm.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hardware.crtk.fake_arm", description=__doc__.split("\n")[0])
    parser.add_argument("--arm", default="PSM1")
    parser.add_argument("--domain", type=int, default=0, help="DDS domain id (a ROS side's ROS_DOMAIN_ID)")
    parser.add_argument("--rate-hz", type=float, default=FakeArmSettings.rate_hz)
    parser.add_argument("--bandwidth-hz", type=float, default=FakeArmSettings.bandwidth_hz)
    parser.add_argument("--damping", type=float, default=FakeArmSettings.damping)
    parser.add_argument("--max-accel-m-s2", type=float, default=FakeArmSettings.max_accel_m_s2)
    parser.add_argument("--ideal", action="store_true", help="reach each servo_cp goal at the next tick")
    parser.add_argument("--homing-s", type=float, default=FakeArmSettings.homing_s)
    parser.add_argument("--floor-z-m", type=float, default=FakeArmSettings.floor_z_m)
    parser.add_argument("--floor-stiffness-N-m", dest="floor_stiffness_N_m", type=float,
                        default=FakeArmSettings.floor_stiffness_N_m)
    args = parser.parse_args(argv)
    try:
        settings = FakeArmSettings.from_mapping(vars(args))
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    run(settings)
    return 0


if __name__ == "__main__":
    sys.exit(main())
