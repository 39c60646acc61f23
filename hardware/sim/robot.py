"""The simulated slave robot: the loop's reference X_r in, joint-encoder readings of the TSI pose out.

The robot's motion is the world's :class:`~hardware.sim.world.RobotBody` (inner position loop with its
bandwidth and speed/acceleration limits); this is the device the control loop sees: readings at the
robot's rate, each with its sequence number and the instant it describes, references and holds in.
Tissue contact does not stop the robot: it is position controlled and far stiffer than tissue. While the
link is down nothing reaches the robot, and its controller's watchdog has already braked it to a hold.
"""

from __future__ import annotations

from hardware.interfaces import SlaveConstraints, SlaveManipulator, SlaveState, Vec3, finite_vec3
from hardware.sim.world import SimDevice, SimWorld


class SimSlave(SimDevice, SlaveManipulator):
    name = "sim-slave"

    def __init__(self, world: SimWorld):
        super().__init__(world)
        s = world.settings.robot
        self.constraints = SlaveConstraints(
            workspace_min_m=s.workspace_min_m,
            workspace_max_m=s.workspace_max_m,
            max_speed_m_s=s.max_speed_m_s,
            rate_hz=s.rate_hz,
        )
        self._latest: SlaveState | None = None
        self._last_index = -1

    def latest(self) -> SlaveState | None:
        return self._latest

    def poll(self, now_s: float) -> None:
        sample = self._next_sample(now_s, self.constraints.rate_hz, self._last_index)
        if sample is None:
            return
        m, t = sample
        position, velocity = self.world.state_at(t)
        self._latest = SlaveState(seq=m, t_s=t, position_m=position, velocity_m_s=velocity)
        self._last_index = m

    def command(self, position_m: Vec3, velocity_m_s: Vec3, now_s: float) -> None:
        """Applies from ``now_s`` on; ignored while disconnected (it never reaches the robot)."""
        position = finite_vec3("sim slave: reference position", position_m)
        velocity = finite_vec3("sim slave: reference velocity", velocity_m_s)
        self.world.advance(now_s)
        if self.connected:
            self.world.robot.set_reference(position, velocity)

    def hold(self, now_s: float) -> None:
        """Brakes within the acceleration limit and stays where it stops, until the next ``command``."""
        self.world.advance(now_s)
        if self.connected:
            self.world.robot.hold()

    def simulate_unplug(self) -> None:
        """The robot controller's link watchdog brakes it to a hold when the host stops talking to it."""
        super().simulate_unplug()
        self.world.robot.hold()
