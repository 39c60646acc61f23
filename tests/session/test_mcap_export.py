"""A session as a ROS 2 bag in MCAP (issue 51): read back with the mcap reader, every level and frame checked,
every message type decoded by a ROS 2 decoder that is not ours, and the CDR bytes against Cyclone DDS's."""

from __future__ import annotations

import errno
import struct

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.decoder import DecoderFactory

from app.session_commands import export_main
from hardware.crtk.messages import Header, Point, Pose, PoseStamped, Time
from session import mcap_export
from session.format import EVENT_DTYPE, event_row
from session.mcap_export import (
    IMAGE_LAYOUT,
    POSE_LAYOUT,
    TOPICS,
    WRENCH_LAYOUT,
    encode_event,
    encode_poses,
    schema_text,
    write_mcap,
)
from session.reader import open_session


@pytest.fixture(scope="module")
def bag(recorded, tmp_path_factory):
    """(the recorded session's path, its MCAP export's path)."""
    out = tmp_path_factory.mktemp("mcap") / "session.mcap"
    assert export_main([str(recorded[0]), "--mcap", str(out)]) == 0
    return recorded[0], out


def _messages(path):
    """Every message, in file order: (topic, log time, publish time, sequence, data)."""
    with open(path, "rb") as f:
        return [(channel.topic, m.log_time, m.publish_time, m.sequence, m.data)
                for _, channel, m in make_reader(f).iter_messages(log_time_order=False)]


def _header_stamp_ns(data: bytes) -> int:
    sec, nanosec = struct.unpack_from("<iI", data, 4)
    return sec * 1_000_000_000 + nanosec


def test_the_bag_is_a_ros2_mcap_with_a_channel_per_topic(bag):
    with open(bag[1], "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
    channels = {c.topic: c for c in summary.channels.values()}
    assert list(channels) == [topic for topic, _ in TOPICS]
    for topic, type_name in TOPICS:
        channel, schema = channels[topic], summary.schemas[channels[topic].schema_id]
        assert channel.message_encoding == "cdr" and "offered_qos_profiles" in channel.metadata
        assert schema.encoding == "ros2msg" and schema.name == type_name.replace("/", "/msg/")
        assert schema.data.decode() == schema_text(type_name)
    header_text = schema_text("geometry_msgs/PoseStamped")
    assert f"\n{'=' * 80}\nMSG: std_msgs/Header\n" in header_text and "MSG: builtin_interfaces/Time" in header_text
    assert summary.statistics.message_count == sum(summary.statistics.channel_message_counts.values())


def test_every_tick_frame_level_and_event_is_there_stamped_in_utc_and_in_time_order(bag):
    messages = _messages(bag[1])
    log_times = np.array([m[1] for m in messages])
    assert (np.diff(log_times) >= 0).all()  # the file is in time order
    by_topic: dict[str, list] = {}
    for m in messages:
        by_topic.setdefault(m[0], []).append(m)
    for topic, rows in by_topic.items():
        stamps = np.array([_header_stamp_ns(m[4]) for m in rows])
        assert stamps.tolist() == [m[1] for m in rows] == [m[2] for m in rows], topic
        assert (np.diff(stamps) >= 0).all() and [m[3] for m in rows] == list(range(1, len(rows) + 1)), topic
    with open_session(bag[0]) as s:
        ticks, frames, levels, events = s.tick_rows(0, s.n_ticks), s.frames(), s.levels, s.events
        tick_utc, frame_utc = s.utc_ns(ticks["t_s"]), s.utc_ns(frames["t_s"])
        level_utc, event_utc = s.utc_ns(levels["t_s"]), s.utc_ns(events["t_s"])
    for topic in ("/palpation/tsi_pose", "/palpation/force", "/palpation/force_desired"):
        assert [m[1] for m in by_topic[topic]] == tick_utc.tolist()
    poses = np.frombuffer(b"".join(m[4] for m in by_topic["/palpation/tsi_pose"]), POSE_LAYOUT)
    assert np.array_equal(poses["position"], ticks["x_slave_m"]) and (poses["frame_id"] == b"tissue").all()
    for topic, column in (("/palpation/force", "force_measured_N"), ("/palpation/force_desired", "force_desired_N")):
        wrenches = np.frombuffer(b"".join(m[4] for m in by_topic[topic]), WRENCH_LAYOUT)
        assert np.array_equal(wrenches["force"][:, 2], ticks[column], equal_nan=True)
    # every frame, decoded from its bytes at the image's layout, is the session's frame
    images = np.frombuffer(b"".join(m[4] for m in by_topic["/palpation/tactile"]), IMAGE_LAYOUT)
    assert len(images) == len(frames) > 0 and [m[1] for m in by_topic["/palpation/tactile"]] == frame_utc.tolist()
    assert np.array_equal(images["data"], frames["pressure_pa"]) and (images["height"] == 4).all()
    assert [m[1] for m in by_topic["/palpation/levels"]] == level_utc.tolist() and len(levels) > 0
    assert [m[1] for m in by_topic["/palpation/events"]] == event_utc.tolist() and len(events) > 0


def test_every_message_type_decodes_as_ros2_reads_it(bag):
    """mcap_ros2 builds its decoder from the schema text alone, as Foxglove does."""
    every = ("/palpation/levels", "/palpation/state")
    others = [topic for topic, _ in TOPICS if topic not in every]
    decoded: dict[str, list] = {}
    with open(bag[1], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, message in reader.iter_decoded_messages(topics=list(every)):
            decoded.setdefault(channel.topic, []).append(message)
        for _, channel, _, message in reader.iter_decoded_messages(topics=others):  # the first of each
            decoded.setdefault(channel.topic, [message])
            if len(decoded) == len(TOPICS):
                break
    assert set(decoded) == {topic for topic, _ in TOPICS}
    with open_session(bag[0]) as s:
        first_tick, levels, events, frame = s.tick_rows(0, 1)[0], s.levels, s.events, s.frames(0, 1)[0]
        ticks = s.tick_rows(0, s.n_ticks, ["t_s", *mcap_export._STATE_COLUMNS])
        state_utc = s.utc_ns(ticks["t_s"])
    p = decoded["/palpation/tsi_pose"][0]
    assert p.header.frame_id == "tissue" and p.pose.orientation.w == 1.0
    assert [p.pose.position.x, p.pose.position.y, p.pose.position.z] == first_tick["x_slave_m"].tolist()
    w = decoded["/palpation/force"][0]
    assert w.header.frame_id == "tsi" and w.wrench.force.z == first_tick["force_measured_N"]
    image = decoded["/palpation/tactile"][0]
    assert (image.height, image.width, image.encoding, image.step) == (4, 15, "32FC1", 60)
    assert np.array_equal(np.frombuffer(bytes(image.data), "<f4").reshape(4, 15), frame["pressure_pa"])
    e = decoded["/palpation/events"][0]
    assert (e.kind, e.text, e.code) == (events["kind"][0].decode(), events["text"][0].decode(), events["code"][0])
    assert len(decoded["/palpation/levels"]) == len(levels)
    for message, level in zip(decoded["/palpation/levels"], levels):
        assert (message.region, message.level, message.force_desired) == (
            level["region"], level["level"], level["force_desired_N"])
        assert (message.rows, message.cols, message.window_frames) == (4, 15, level["window_frames"])
        assert message.tsi_position.z == level["tsi_position_m"][2]
        assert np.array_equal(message.pressure, level["pressure_pa"].ravel())
        assert np.array_equal(message.stiffness, level["stiffness_pa"].ravel(), equal_nan=True)
    # the state as the loop had it at each message's stamp, and a message only where it changed
    states = decoded["/palpation/state"]
    assert len(states) > 2 and states[0].phase_name == "APPROACH"
    for before, message in zip([None, *states], states):
        k = int(np.searchsorted(state_utc, message.header.stamp.sec * 10**9 + message.header.stamp.nanosec))
        row = ticks[k]
        now = (message.phase, message.sz, message.fault, message.region, message.level, message.n_levels,
               message.region_done)
        assert now == tuple(row[c].item() if c != "region_done" else bool(row[c]) for c in mcap_export._STATE_COLUMNS)
        if before is not None:
            assert now != (before.phase, before.sz, before.fault, before.region, before.level, before.n_levels,
                           before.region_done)


def test_the_cdr_is_ros2s_bytes():
    """A pose as Cyclone DDS encodes the ROS 2 message, and an event laid out by hand: each string's length
    counts its NUL, and what follows a string is aligned counting from the end of the encapsulation header."""
    position = (0.012, -0.015, 0.0213)
    utc = 1_800_000_000_250_000_000
    dds = PoseStamped(header=Header(stamp=Time(sec=1_800_000_000, nanosec=250_000_000), frame_id="tissue"),
                      pose=Pose(position=Point(*position)))
    assert encode_poses(np.array([utc]), np.array([position]))[0] == dds.serialize()
    row = np.array([event_row(1.0, "note", region=2, code=7, value=0.5, text="ok")], EVENT_DTYPE)[0]
    expected = (b"\x00\x01\x00\x00" + struct.pack("<iII", 1_800_000_000, 250_000_000, 1) + b"\0"  # stamp, ""
                + b"\0\0\0" + struct.pack("<I", 5) + b"note\0"  # kind
                + b"\0\0\0" + struct.pack("<iii", 2, -1, 7)  # region, level, code
                + struct.pack("<d", 0.5) + struct.pack("<I", 3) + b"ok\0")  # value at 40, a multiple of 8; text
    assert encode_event(utc, row) == expected


def test_the_bag_is_the_same_whatever_the_pieces_it_is_written_in(recorded, bag, tmp_path):
    """The pieces keep memory bounded; where they are cut must not move, drop or repeat a message."""
    with open_session(recorded[0]) as s:
        write_mcap(s, tmp_path / "small.mcap", window_ticks=997)
    assert _messages(tmp_path / "small.mcap") == _messages(bag[1])


def test_bad_input_and_outputs_get_one_line_and_leave_nothing_behind(recorded, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out.mcap"
    assert export_main([str(tmp_path / "missing.h5"), "--mcap", str(out)]) == 2
    assert capsys.readouterr().err == f"error: {tmp_path / 'missing.h5'}: no such file\n"
    (tmp_path / "notes.h5").write_text("not a session")
    assert export_main([str(tmp_path / "notes.h5"), "--mcap", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert export_main([str(recorded[0]), "--mcap", str(tmp_path / "nowhere" / "out.mcap")]) == 1
    assert capsys.readouterr().err == f"error: {tmp_path / 'nowhere'}: no such folder\n"
    assert export_main([str(recorded[0]), "--mcap", str(tmp_path / "out.bag")]) == 2
    assert "name it .mcap" in capsys.readouterr().err
    assert export_main([str(recorded[0]), "--mcap", str(out), "--tables", "ticks"]) == 2
    assert "--tables applies to --csv and --parquet" in capsys.readouterr().err
    (tmp_path / "taken.mcap").mkdir()  # a folder where the bag should go: found only at the rename
    assert export_main([str(recorded[0]), "--mcap", str(tmp_path / "taken.mcap")]) == 1
    err = capsys.readouterr().err.splitlines()
    assert err[-1].startswith(f"error: cannot write {tmp_path / 'taken.mcap'}: ") and len(err) == 1

    written = []

    def fill_the_disk(self, *args, **kwargs):
        written.append(1)
        if len(written) > 5000:
            raise OSError(errno.ENOSPC, "No space left on device")
        return add_message(self, *args, **kwargs)

    add_message = Writer.add_message
    monkeypatch.setattr(Writer, "add_message", fill_the_disk)
    assert export_main([str(recorded[0]), "--mcap", str(out)]) == 1
    assert capsys.readouterr().err == f"error: cannot write {out}: No space left on device\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.h5", "taken.mcap"]
    assert not any((tmp_path / "taken.mcap").iterdir())
