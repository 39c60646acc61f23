"""The ROS 2 messages a CRTK arm speaks, laid out as ROS 2 puts them on DDS.

Each class is the message's IDL struct under the name ``rmw_cyclonedds_cpp`` gives it
(``<package>::msg::dds_::<Message>_``), so a ROS 2 node on the same domain matches our readers and writers; the
fields and their order are the ``.msg`` files', which is all XCDR1 encodes. Lengths in m, times as ROS stamps.

* geometry_msgs: PoseStamped (``servo_cp``, ``measured_cp``), TwistStamped (``measured_cv``), WrenchStamped
  (``measured_cf``);
* crtk_msgs: OperatingState (``operating_state``: state, is_homed, is_busy), StringStamped (``state_command``,
  as the dVRK's ROS 2 bridge takes it);
* std_msgs: Empty (``hold``, a command without a payload; ROS 2 gives an empty message one placeholder byte).

The console's own topics (``/palpation/...``) carry the messages a session's ROS 2 bag holds, whose ``.msg``
definitions are written once, in :data:`session.mcap_export.DEFINITIONS`: :func:`ros_message_type` makes the
DDS type of one from its definition, taking the types above where the definition uses them.
"""

# No ``from __future__ import annotations``: cyclonedds reads the field types from the annotations themselves.
import math
import re
from dataclasses import dataclass, field

from cyclonedds.idl import IdlStruct, make_idl_struct
from cyclonedds.idl import types as T
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


# The ROS 2 primitive types as IDL ("byte" and "char" as ROS 2 maps them).
_PRIMITIVES = {"bool": bool, "byte": T.uint8, "char": T.uint8, "int8": T.int8, "uint8": T.uint8, "int16": T.int16,
               "uint16": T.uint16, "int32": T.int32, "uint32": T.uint32, "int64": T.int64, "uint64": T.uint64,
               "float32": T.float32, "float64": T.float64, "string": str}
_FIELD = re.compile(r"^([A-Za-z0-9_/]+)(\[(\d*)\])?\s+([a-z][a-z0-9_]*)$")


def dds_typename(type_name: str) -> str:
    """ "sensor_msgs/Image" as rmw_cyclonedds_cpp names it on DDS: "sensor_msgs::msg::dds_::Image_"."""
    package, name = type_name.split("/")
    return f"{package}::msg::dds_::{name}_"


_made: dict[str, type] = {cls.__idl_typename__: cls for cls in list(globals().values())
                          if isinstance(cls, type) and issubclass(cls, IdlStruct) and cls is not IdlStruct}


def ros_message_type(type_name: str, definitions: dict[str, str]) -> type:
    """The DDS type of the ROS 2 message ``type_name`` ("package/Type"), made from its ``.msg`` text in
    ``definitions`` (and those of the types it uses); a type this module defines is that class. ValueError
    for a line this reader does not know (constants and default values are not used by our messages)."""
    typename = dds_typename(type_name)
    made = _made.get(typename)
    if made is not None:
        return made
    fields: dict[str, object] = {}
    for line in definitions[type_name].splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        match = _FIELD.match(line)
        if match is None:
            raise ValueError(f"{type_name}: cannot read the field {line!r}")
        kind, bracket, size, name = match.groups()
        element = _PRIMITIVES.get(kind) or ros_message_type(kind, definitions)
        fields[name] = element if bracket is None else T.sequence[element] if not size else T.array[element, int(size)]
    made = _made[typename] = make_idl_struct(type_name.split("/")[1], typename, fields)
    return made
