"""The palpation on the ROS 2 bus as it happens, so that ``ros2 bag record`` captures it without the console.

A :class:`BusPublisher` is one more :class:`app.bridge.RowSink`: the bridge's worker thread, in the GUI process,
hands it the rows the controller wrote since the display's last frame, as it hands them to the session
recorder. So the 1 kHz loop, in its own process, does nothing more for it; here it costs a few µs a row.

What goes on the bus is what a session's bag holds (:mod:`session.mcap_export`, docs/session-format.md, *The
session as a ROS 2 bag*), on the same topics, in the same messages, encoded by the same code:
``/palpation/tsi_pose``, ``/palpation/force`` and ``/palpation/force_desired`` every control period,
``/palpation/state`` whenever the loop's state changes (transient-local, so a late subscriber has the current
phase at once), ``/palpation/tactile`` every frame, and ``/palpation/levels`` and ``/palpation/events`` as the
loop's events come: the rows the session file records of them (:func:`session.format.rows_for_event`), so that
a ``ros2 bag record`` of the bus holds what a session's export does. The operator's notes (and the findings told)
and what the recorder itself notes (rows lost, the controller lost, the file closed) are the session file's
alone. The topics are on the CRTK arm's DDS domain (the ROS side's ``ROS_DOMAIN_ID``), through the same
loopback-pinned participants as the arm (:mod:`hardware.crtk.dds`).

Stamps are UTC: a row's loop time (the controller's monotonic clock, the same on every process of the
machine) plus the offset of UTC from that clock, read afresh at every call.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from app.realtime import read_clocks
from hardware.crtk import dds
from hardware.crtk.messages import ros_message_type
from session import mcap_export as bag
from session.format import EVENT_DTYPE, LEVEL_DTYPE, rows_for_event

log = logging.getLogger(__name__)

# Every control period's rows arrive a display frame at a time (16 at 60 Hz): a reader that keeps up takes
# them all, and a writer never waits for one that does not.
_HISTORY = 256
PER_TICK = ("/palpation/tsi_pose", "/palpation/force", "/palpation/force_desired")
STATE, TACTILE = "/palpation/state", "/palpation/tactile"
LEVELS, EVENTS = "/palpation/levels", "/palpation/events"
TOPICS = dict(bag.TOPICS)


def qos(topic: str) -> dds.Qos:
    """The QoS the console offers ``topic`` with (a subscriber's must be compatible to match)."""
    durability = (dds.Policy.Durability.TransientLocal,) if topic == STATE else ()
    return dds.Qos(dds.Policy.Reliability.Reliable(max_blocking_time=0), *durability,
                   dds.Policy.History.KeepLast(_HISTORY), dds.XCDR1)


class BusPublisher:
    """Publishes the rows of the controller on DDS domain ``domain``; a failing bus is logged once, told to
    :attr:`on_problem` (called in the bridge's thread) and then left alone until the next run (the palpation
    and its recording go on)."""

    def __init__(self, domain: int):
        self.domain = dds.domain_id("hardware.slave.domain", domain)
        self.on_problem: Callable[[str], None] | None = None
        self._bus: dds.Participant | None = None
        self._writers: dict[str, dds.DataWriter] = {}
        self._state: np.ndarray | None = None
        self.published = dict.fromkeys(TOPICS, 0)
        self.problem = ""

    def driver_started(self) -> None:
        self._close()
        self._state = None
        try:
            self._bus = bus = dds.Participant(self.domain)
            self._writers = {topic: bus.writer(dds.ros_topic(topic), ros_message_type(type_name, bag.DEFINITIONS),
                                               qos(topic)) for topic, type_name in TOPICS.items()}
        except dds.DDSException as err:
            self._fail(f"cannot join DDS domain {self.domain}: {err}")

    def add_rows(self, ticks: np.ndarray, frames: np.ndarray, events: list) -> None:
        if self._bus is None:
            return
        now_s, now_ns = read_clocks()
        offset_ns = now_ns - round(now_s * 1e9)

        def utc_ns(t_s: np.ndarray) -> np.ndarray:
            return np.round(t_s * 1e9).astype(np.int64) + offset_ns

        utc = utc_ns(ticks["t_s"])
        changed, self._state = bag.state_changes(ticks, self._state)
        frame_utc = utc_ns(frames["t_s"])
        event_rows, level_rows = _session_rows(events)
        try:
            self._write("/palpation/tsi_pose", bag.encode_poses(utc, ticks["x_slave_m"]))
            self._write("/palpation/force", bag.encode_wrenches(utc, ticks["force_measured_N"]))
            self._write("/palpation/force_desired", bag.encode_wrenches(utc, ticks["force_desired_N"]))
            self._write(STATE, [bag.encode_state(int(utc[k]), ticks[k]) for k in changed])
            self._write(TACTILE, bag.encode_images(frame_utc, frames["pressure_pa"]))
            for topic, rows, encode in ((LEVELS, level_rows, bag.encode_level), (EVENTS, event_rows, bag.encode_event)):
                self._write(topic, [encode(int(u), row) for u, row in zip(utc_ns(rows["t_s"]), rows)])
        except (dds.DDSException, bag.McapExportError) as err:
            self._fail(str(err))

    def driver_stopped(self, failure: str | None) -> None:
        self._close()

    def _write(self, topic: str, messages: list[bytes]) -> None:
        writer = self._writers[topic]
        for data in messages:
            dds.write_encoded(writer, data)
        self.published[topic] += len(messages)

    def _fail(self, why: str) -> None:
        self.problem = (f"The palpation is not published on the ROS 2 bus ({why}) until the controller starts "
                        "again; control and the session's recording go on.")
        log.warning("%s", self.problem)
        self._close()
        if self.on_problem is not None:
            self.on_problem(self.problem)

    def _close(self) -> None:
        bus, self._bus = self._bus, None
        self._writers = {}
        if bus is not None:
            bus.close()


def _session_rows(events: list) -> tuple[np.ndarray, np.ndarray]:
    """The /events and /levels rows the session file records of ``events`` (the loop's health reports, also
    handed to the sinks, give none)."""
    rows = [rows_for_event(event) for event in events]
    return (np.array([event for event, _ in rows if event is not None], EVENT_DTYPE),
            np.array([level for _, level in rows if level is not None], LEVEL_DTYPE))
