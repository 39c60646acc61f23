"""A session as a ROS 2 bag: one MCAP file, rosbag2's storage format, whose messages are ROS 2 messages in CDR
stamped in UTC, so that Foxglove, ``ros2 bag info`` and the ``mcap`` tools open it beside a lab's own bags.

What goes on which topic, and in which message, is in docs/session-format.md (*The session as a ROS 2
bag*). Every message's header stamp, and its log and publish times, are the UTC of the row it comes from
(:meth:`session.reader.Session.utc_ns`). The file follows the MCAP ``ros2`` profile as rosbag2 writes it: a
schema per message type in ``ros2msg`` encoding, the type's ``.msg`` definition followed by those of the
types it uses, each after a line of 80 ``=`` and a ``MSG: package/Type`` line; channels in ``cdr`` encoding
with an ``offered_qos_profiles`` entry.

CDR. ROS 2 puts messages on the wire in XCDR1: a 4-byte encapsulation header (CDR, little-endian), then the
fields in order, each primitive aligned to its own size counted from the end of that header (doubles to 8),
a string as a uint32 length that counts its terminating NUL, the bytes and the NUL, a sequence as a uint32
count and its elements. The few message types here are encoded by hand: the per-tick and per-frame ones,
whose encoding has the same length every time, as numpy records laid out at their CDR offsets (a whole
piece of the session at once); the rest field by field.

Memory stays bounded: the streams are read a piece at a time (:data:`WINDOW_TICKS` control periods and the
frames of that span), merged in time order with the levels and events of the span, and written out. The
file is written beside its final name and renamed into place, so a failure leaves no half-written bag.
"""

from __future__ import annotations

import math
import re
import struct
from pathlib import Path

import numpy as np

from control.telemetry import FRAME_DTYPE
from session.format import TICK_CODES
from session.info import software_version
from session.tables import written_whole

WINDOW_TICKS = 20_000  # control periods read, encoded and written at a time (20 s at 1 kHz)
_FRAME_BLOCK = 1024  # tactile frames read at a time
_ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR, little-endian, no options
_RULE = "=" * 80
_INT32_MAX = 2**31 - 1

# The ROS 2 interface definitions of the messages written, and of every type they use, by "package/Type".
# Standard types carry their fields only; ours say what each field holds, and are also the .msg files of the
# ROS 2 package a lab builds to handle them (ros/palpation_console_msgs/msg/, byte for byte: change both).
DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Wrench": "geometry_msgs/Vector3 force\ngeometry_msgs/Vector3 torque\n",
    "geometry_msgs/WrenchStamped": "std_msgs/Header header\ngeometry_msgs/Wrench wrench\n",
    "sensor_msgs/Image": ("std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n"
                          "uint32 step\nuint8[] data\n"),
    "palpation_console_msgs/LoopState": (
        "# The control loop's state, published at the first control period and whenever any of it changes\n"
        "std_msgs/Header header\n"
        "uint8 phase  # the Fig. 4 phase: 0 APPROACH, 1 SEEK_CONTACT, 2 SETTLING, 3 RETRACT, 4 DONE, 5 HOLD\n"
        "string phase_name\n"
        "uint8 sz  # 1 position control in z, 0 force control in z\n"
        "uint8 fault  # the latched fault kind, 0 none\n"
        "string fault_name\n"
        "int16 region  # the palpated area, counted from 0\n"
        "int16 level  # the force level within the area's ramp, counted from 0; -1 outside the ramp\n"
        "int16 n_levels  # levels in the ramp\n"
        "bool region_done\n"),
    "palpation_console_msgs/LevelRecord": (
        "# One recorded force level of an area (a /levels row of the session file); SI units; each array is\n"
        "# the tactile array's rows x cols elements, row-major (rows along the tissue's x, columns along y)\n"
        "std_msgs/Header header\n"
        "int32 region  # counted from 0\n"
        "int32 level  # counted from 0\n"
        "float64 force_desired  # N\n"
        "float64 force_measured  # N, mean over the settle window\n"
        "float64 rmse  # N, of the desired minus the measured force over the window\n"
        "float64 settle_time  # s, from the level's start to its recording\n"
        "geometry_msgs/Point tsi_position  # m, mean over the window, in the tissue frame\n"
        "float64 indentation  # m\n"
        "int32 window_frames  # frames averaged\n"
        "uint16 rows\n"
        "uint16 cols\n"
        "float64[] pressure  # Pa, mean over the window\n"
        "float64[] pressure_std  # Pa, over the window's frames\n"
        "float64[] element_force  # N\n"
        "float64[] onset_height  # m, the TSI's height at each element's contact onset (NaN: never)\n"
        "float64[] l0  # m, the initial tissue thickness under each element (Eq. 1)\n"
        "float64[] dl  # m, each element's indentation (Eq. 1)\n"
        "float64[] stiffness  # Pa, Eq. 1 (NaN: not in contact)\n"),
    "palpation_console_msgs/Event": (
        "# One event of the session (an /events row of the session file; docs/session-format.md lists the kinds)\n"
        "std_msgs/Header header\n"
        "string kind\n"
        "int32 region  # counted from 0; -1 when not about an area\n"
        "int32 level  # counted from 0; -1 when not about a level\n"
        "int32 code  # depends on kind\n"
        "float64 value  # depends on kind; NaN when unused\n"
        "string text\n"),
}

TISSUE_FRAME = "tissue"  # the tissue frame of the session file: x, y across the table, z up from it
TSI_FRAME = "tsi"  # the probe's face
# (topic, message type): docs/session-format.md says what each carries
TOPICS: tuple[tuple[str, str], ...] = (
    ("/palpation/tsi_pose", "geometry_msgs/PoseStamped"),
    ("/palpation/force", "geometry_msgs/WrenchStamped"),
    ("/palpation/force_desired", "geometry_msgs/WrenchStamped"),
    ("/palpation/state", "palpation_console_msgs/LoopState"),
    ("/palpation/tactile", "sensor_msgs/Image"),
    ("/palpation/levels", "palpation_console_msgs/LevelRecord"),
    ("/palpation/events", "palpation_console_msgs/Event"),
)
_STATE_COLUMNS = ("phase", "sz", "fault", "region", "level", "n_levels", "region_done")


class McapExportError(RuntimeError):
    """The bag could not be written; the message names the file and why."""


def ros_type_name(type_name: str) -> str:
    """ "geometry_msgs/PoseStamped" as ROS 2 names it in a bag: "geometry_msgs/msg/PoseStamped"."""
    package, name = type_name.split("/")
    return f"{package}/msg/{name}"


def _used_types(definition: str) -> list[str]:
    used = []
    for line in definition.splitlines():
        words = line.split("#", 1)[0].split()
        if words and "/" in words[0]:
            used.append(re.sub(r"\[\d*\]$", "", words[0]))
    return used


def schema_text(type_name: str) -> str:
    """The complete definition of ``type_name`` as rosbag2 stores it (``ros2msg``): its own, then every type
    it uses, depth first, once each."""
    seen: set[str] = set()

    def with_dependencies(name: str) -> str:
        text = DEFINITIONS[name]
        for used in _used_types(text):
            if used not in seen:
                seen.add(used)
                text += f"\n{_RULE}\nMSG: {used}\n" + with_dependencies(used)
        return text

    return with_dependencies(type_name)


# ---- CDR ------------------------------------------------------------------------------------------------


class _Cdr:
    """One message encoded field by field."""

    def __init__(self):
        self.out = bytearray(_ENCAPSULATION)

    def _align(self, size: int) -> None:
        self.out += bytes(-(len(self.out) - len(_ENCAPSULATION)) % size)

    def put(self, code: str, value) -> None:
        """A primitive: ``code`` is its struct format character (b, B, h, H, i, I, d, ?)."""
        size = struct.calcsize(code)
        self._align(size)
        self.out += struct.pack("<" + code, value)

    def string(self, text: str) -> None:
        raw = text.encode("utf-8") + b"\0"
        self.put("I", len(raw))
        self.out += raw

    def header(self, utc_ns: int, frame_id: str) -> None:
        sec, nanosec = _stamp(np.array([utc_ns], np.int64))
        self.put("i", int(sec[0]))
        self.put("I", int(nanosec[0]))
        self.string(frame_id)

    def doubles(self, values) -> None:
        """A float64[] sequence."""
        flat = np.ascontiguousarray(values, "<f8").ravel()
        self.put("I", flat.size)
        if flat.size:
            self._align(8)
            self.out += flat.tobytes()


def _stamp(utc_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sec, nanosec) of builtin_interfaces/Time for UTC in ns since the epoch."""
    sec, nanosec = np.divmod(utc_ns, 1_000_000_000)
    if len(sec) and (sec.min() < 0 or sec.max() > _INT32_MAX):
        raise McapExportError("the session's times lie outside what a ROS 2 stamp holds (1970 to 2038)")
    return sec.astype(np.int32), nanosec.astype(np.uint32)


def _fixed_layout(fields: list[tuple]) -> np.dtype:
    """A numpy record laid out as CDR lays out a message whose encoding always has the same length:
    ``fields`` are (name, numpy type) or (name, numpy type, alignment), in the message's order; a primitive
    is aligned to its size unless told otherwise. The record starts with the encapsulation header."""
    names, formats, offsets = ["encapsulation"], [("u1", 4)], [0]
    position = 0
    for name, fmt, *align in fields:
        dtype = np.dtype(fmt)
        alignment = align[0] if align else (dtype.base.itemsize if dtype.base.kind in "iuf" else 1)
        position += -position % alignment
        names.append(name)
        formats.append(dtype)
        offsets.append(len(_ENCAPSULATION) + position)
        position += dtype.itemsize
    return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                     "itemsize": len(_ENCAPSULATION) + position})


def _header_fields(frame_id: str) -> list[tuple]:
    return [("sec", "<i4"), ("nanosec", "<u4"), ("frame_id_length", "<u4"), ("frame_id", f"S{len(frame_id) + 1}")]


POSE_LAYOUT = _fixed_layout(_header_fields(TISSUE_FRAME) + [("position", ("<f8", 3)), ("orientation", ("<f8", 4))])
WRENCH_LAYOUT = _fixed_layout(_header_fields(TSI_FRAME) + [("force", ("<f8", 3)), ("torque", ("<f8", 3))])
_IMAGE_ENCODING = "32FC1"  # one float32 per pixel
_ROWS, _COLS = FRAME_DTYPE["pressure_pa"].shape
IMAGE_LAYOUT = _fixed_layout(_header_fields(TSI_FRAME) + [
    ("height", "<u4"), ("width", "<u4"), ("encoding_length", "<u4"), ("encoding", f"S{len(_IMAGE_ENCODING) + 1}"),
    ("is_bigendian", "u1"), ("step", "<u4"), ("data_length", "<u4"),
    ("data", ("<f4", (_ROWS, _COLS)), 1),  # a uint8[] in the message: bytes, aligned as bytes
])


def _records(layout: np.dtype, utc_ns: np.ndarray, frame_id: str) -> np.ndarray:
    rows = np.zeros(len(utc_ns), layout)
    rows["encapsulation"] = np.frombuffer(_ENCAPSULATION, np.uint8)
    rows["sec"], rows["nanosec"] = _stamp(utc_ns)
    rows["frame_id_length"] = len(frame_id) + 1
    rows["frame_id"] = frame_id.encode("ascii")
    return rows


def _split(rows: np.ndarray) -> list[bytes]:
    data, size = rows.tobytes(), rows.dtype.itemsize
    return [data[k:k + size] for k in range(0, len(data), size)]


def encode_poses(utc_ns: np.ndarray, position_m: np.ndarray) -> list[bytes]:
    """geometry_msgs/PoseStamped in the tissue frame, the orientation the identity (the probe stays level)."""
    rows = _records(POSE_LAYOUT, utc_ns, TISSUE_FRAME)
    rows["position"] = position_m
    rows["orientation"] = (0.0, 0.0, 0.0, 1.0)
    return _split(rows)


def encode_wrenches(utc_ns: np.ndarray, force_N: np.ndarray) -> list[bytes]:
    """geometry_msgs/WrenchStamped: the normal force as force.z (positive pressing into the tissue); the array
    measures no shear and no torque, and the loop commands none, so the rest is 0."""
    rows = _records(WRENCH_LAYOUT, utc_ns, TSI_FRAME)
    rows["force"][:, 2] = force_N
    return _split(rows)


def encode_images(utc_ns: np.ndarray, pressure_pa: np.ndarray) -> list[bytes]:
    """sensor_msgs/Image, 32FC1: one pixel per element, in Pa; the image's rows are the array's rows."""
    rows = _records(IMAGE_LAYOUT, utc_ns, TSI_FRAME)
    rows["height"], rows["width"] = _ROWS, _COLS
    rows["encoding_length"] = len(_IMAGE_ENCODING) + 1
    rows["encoding"] = _IMAGE_ENCODING.encode("ascii")
    rows["step"] = 4 * _COLS
    rows["data_length"] = 4 * _ROWS * _COLS
    rows["data"] = pressure_pa
    return _split(rows)


def _code_name(column: str, code: int) -> str:
    return TICK_CODES[column].get(str(code), str(code))


def encode_state(utc_ns: int, tick: np.void) -> bytes:
    """palpation_console_msgs/LoopState of one tick row."""
    cdr = _Cdr()
    cdr.header(utc_ns, "")
    phase, fault = int(tick["phase"]), int(tick["fault"])
    cdr.put("B", phase)
    cdr.string(_code_name("phase", phase))
    cdr.put("B", int(tick["sz"]))
    cdr.put("B", fault)
    cdr.string(_code_name("fault", fault))
    for column in ("region", "level", "n_levels"):
        cdr.put("h", int(tick[column]))
    cdr.put("?", bool(tick["region_done"]))
    return bytes(cdr.out)


def state_changes(ticks: np.ndarray, previous: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The indices of the tick rows whose LoopState differs from the row before (``previous``: the state
    after the rows before these, None at the first), and the state after these rows, for the next call."""
    if not len(ticks):
        return np.zeros(0, np.int64), previous
    state = np.stack([ticks[c].astype(np.int64) for c in _STATE_COLUMNS], axis=1)
    before = np.concatenate([[previous if previous is not None else state[0] - 1], state[:-1]])
    return np.flatnonzero((state != before).any(axis=1)), state[-1]


def encode_level(utc_ns: int, level: np.void) -> bytes:
    """palpation_console_msgs/LevelRecord of one /levels row."""
    cdr = _Cdr()
    cdr.header(utc_ns, TISSUE_FRAME)
    cdr.put("i", int(level["region"]))
    cdr.put("i", int(level["level"]))
    for column in ("force_desired_N", "force_measured_N", "rmse_N", "settle_time_s"):
        cdr.put("d", float(level[column]))
    for value in level["tsi_position_m"]:
        cdr.put("d", float(value))
    cdr.put("d", float(level["indentation_m"]))
    cdr.put("i", int(level["window_frames"]))
    rows, cols = level["pressure_pa"].shape
    cdr.put("H", rows)
    cdr.put("H", cols)
    for column in ("pressure_pa", "pressure_std_pa", "element_force_N", "onset_height_m", "L0_m", "dL_m",
                   "stiffness_pa"):
        cdr.doubles(level[column])
    return bytes(cdr.out)


def encode_event(utc_ns: int, event: np.void) -> bytes:
    """palpation_console_msgs/Event of one /events row."""
    cdr = _Cdr()
    cdr.header(utc_ns, "")
    cdr.string(bytes(event["kind"]).decode("ascii", errors="replace"))
    for column in ("region", "level", "code"):
        cdr.put("i", int(event[column]))
    cdr.put("d", float(event["value"]))
    cdr.string(bytes(event["text"]).decode("utf-8", errors="replace"))
    return bytes(cdr.out)


# ---- the session, a piece at a time --------------------------------------------------------------------------


class _Span:
    """The messages of one span of the session, from all topics."""

    def __init__(self, channel: dict[str, int]):
        self.channel = channel
        self.times: list[np.ndarray] = []
        self.channels: list[np.ndarray] = []
        self.messages: list[bytes] = []

    def add(self, topic: str, utc_ns: np.ndarray, encoded: list[bytes]) -> None:
        self.times.append(utc_ns)
        self.channels.append(np.full(len(utc_ns), self.channel[topic], np.int64))
        self.messages.extend(encoded)

    def in_time_order(self):
        """(log time, channel id, message) of each, in time order (a tie in the order added)."""
        times, channels = np.concatenate(self.times), np.concatenate(self.channels)
        for k in np.argsort(times, kind="stable"):
            yield int(times[k]), int(channels[k]), self.messages[k]


def _pieces(session, channel: dict[str, int], window_ticks: int):
    """The messages of the whole session, a span of ``window_ticks`` control periods at a time (each span's
    :meth:`_Span.in_time_order`); the frames, levels and events of a span are those from its first tick's
    time to the next span's (the first span from the beginning of time, the last to its end)."""
    levels, events = session.levels, session.events
    n = session.n_ticks
    frames = np.zeros(0, FRAME_DTYPE)
    next_frame = 0
    previous_state = None
    start, low = 0, -math.inf
    while True:
        stop = min(n, start + window_ticks)
        ticks = session.tick_rows(start, stop)
        high = float(session.tick_rows(stop, stop + 1, ["t_s"])["t_s"][0]) if stop < n else math.inf
        while next_frame < session.n_frames and (not len(frames) or frames["t_s"][-1] < high):
            block = session.frames(next_frame, next_frame + _FRAME_BLOCK)
            next_frame += len(block)
            frames = np.concatenate([frames, block])
        now = frames["t_s"] < high
        span_frames, frames = frames[now], frames[~now]

        span = _Span(channel)
        utc = session.utc_ns(ticks["t_s"])
        span.add("/palpation/tsi_pose", utc, encode_poses(utc, ticks["x_slave_m"]))
        span.add("/palpation/force", utc, encode_wrenches(utc, ticks["force_measured_N"]))
        span.add("/palpation/force_desired", utc, encode_wrenches(utc, ticks["force_desired_N"]))
        changed, previous_state = state_changes(ticks, previous_state)
        span.add("/palpation/state", utc[changed], [encode_state(int(utc[k]), ticks[k]) for k in changed])
        frame_utc = session.utc_ns(span_frames["t_s"])
        span.add("/palpation/tactile", frame_utc, encode_images(frame_utc, span_frames["pressure_pa"]))
        for topic, rows, encode in (("/palpation/levels", levels, encode_level),
                                    ("/palpation/events", events, encode_event)):
            rows = rows[(rows["t_s"] >= low) & (rows["t_s"] < high)]
            row_utc = session.utc_ns(rows["t_s"])
            span.add(topic, row_utc, [encode(int(u), row) for u, row in zip(row_utc, rows)])
        yield span.in_time_order()
        if stop >= n:
            return
        start, low = stop, high


def _time_base(session) -> str:
    if session.clock_note:
        return session.clock_note
    if session.simulated:
        return ("a simulated session's nominal time line: when recording began plus the simulated time since "
                "(it ran faster than real time)")
    return "the loop clock's readings beside UTC, stored with the session"


def write_mcap(session, path: str | Path, window_ticks: int = WINDOW_TICKS) -> dict[str, int]:
    """Write the open ``session`` as a ROS 2 bag in MCAP at ``path``; returns the messages written per topic.
    Raises McapExportError (one line) if it cannot; nothing is then left at ``path`` or beside it."""
    try:
        from mcap.writer import CompressionType, Writer
    except ImportError:
        raise McapExportError("MCAP needs the mcap package, which is not installed: pip install "
                              "'palpation-console[mcap]'") from None
    path = Path(path)
    if not path.parent.is_dir():
        raise McapExportError(f"{path.parent}: no such folder")
    with written_whole(path, McapExportError) as partial:
        with open(partial, "wb") as out:
            writer = Writer(out, compression=CompressionType.ZSTD)
            writer.start(profile="ros2", library=f"palpation-console {software_version()}")
            schemas: dict[str, int] = {}
            channel: dict[str, int] = {}
            for topic, type_name in TOPICS:
                if type_name not in schemas:
                    schemas[type_name] = writer.register_schema(ros_type_name(type_name), "ros2msg",
                                                                schema_text(type_name).encode("utf-8"))
                # rosbag2 reads an empty list of offered QoS profiles as "none recorded": a player then
                # offers its defaults
                channel[topic] = writer.register_channel(topic, "cdr", schemas[type_name],
                                                         {"offered_qos_profiles": ""})
            writer.add_metadata("palpation_console", {
                "session_file": session.path.name, "session_uuid": session.uuid,
                "created_utc": session.created_utc, "simulated": str(bool(session.simulated)).lower(),
                "time_base": _time_base(session)})
            topic_of = {c: t for t, c in channel.items()}
            sequence = dict.fromkeys(channel.values(), 0)
            for span in _pieces(session, channel, window_ticks):
                for t, c, data in span:
                    sequence[c] += 1
                    writer.add_message(c, log_time=t, data=data, publish_time=t, sequence=sequence[c])
            writer.finish()
    return {topic_of[c]: n for c, n in sequence.items()}
