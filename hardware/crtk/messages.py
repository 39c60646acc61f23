"""The ROS 2 messages a CRTK arm speaks, laid out as ROS 2 puts them on DDS.

Each class is the message's IDL struct under the name ``rmw_cyclonedds_cpp`` gives it
(``<package>::msg::dds_::<Message>_``), so a ROS 2 node on the same domain matches our readers and writers; the
fields and their order are the ``.msg`` files', which is all XCDR1 encodes. Lengths in m, times as ROS stamps.

* geometry_msgs: PoseStamped (``servo_cp``, ``measured_cp``), TwistStamped (``measured_cv``), WrenchStamped
  (``measured_cf``);
* crtk_msgs: OperatingState (``operating_state``: state, is_homed, is_busy), StringStamped (``state_command``,
  as the dVRK's ROS 2 bridge takes it);
* std_msgs: Empty (``hold``, a command without a payload; ROS 2 gives an empty message one placeholder byte).
"""

# No ``from __future__ import annotations``: cyclonedds reads the field types from the annotations themselves.
import math
from dataclasses import dataclass, field

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float64, int32, uint8, uint32


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
class TwistStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TwistStamped_"):
    header: Header = field(default_factory=Header)
    twist: Twist = field(default_factory=Twist)


@dataclass
class Wrench(IdlStruct, typename="geometry_msgs::msg::dds_::Wrench_"):
    force: Vector3 = field(default_factory=Vector3)
    torque: Vector3 = field(default_factory=Vector3)


@dataclass
class WrenchStamped(IdlStruct, typename="geometry_msgs::msg::dds_::WrenchStamped_"):
    header: Header = field(default_factory=Header)
    wrench: Wrench = field(default_factory=Wrench)


@dataclass
class OperatingState(IdlStruct, typename="crtk_msgs::msg::dds_::OperatingState_"):
    header: Header = field(default_factory=Header)
    state: str = ""  # DISABLED, ENABLED, PAUSED or FAULT
    is_homed: bool = False
    is_busy: bool = False


@dataclass
class StringStamped(IdlStruct, typename="crtk_msgs::msg::dds_::StringStamped_"):
    header: Header = field(default_factory=Header)
    string: str = ""


@dataclass
class Empty(IdlStruct, typename="std_msgs::msg::dds_::Empty_"):
    structure_needs_at_least_one_member: uint8 = 0


def stamp(t_s: float) -> Time:
    """A ROS stamp of ``t_s`` seconds."""
    sec = math.floor(t_s)
    return Time(sec=int(sec), nanosec=min(int(round((t_s - sec) * 1e9)), 999_999_999))


def seconds(time: Time) -> float:
    return time.sec + time.nanosec * 1e-9


def pose(position_m, t_s: float, frame_id: str = "") -> PoseStamped:
    """A pose at ``position_m`` with the orientation unchanged from identity (the probe stays level)."""
    x, y, z = position_m
    return PoseStamped(header=Header(stamp=stamp(t_s), frame_id=frame_id),
                       pose=Pose(position=Point(float(x), float(y), float(z))))
