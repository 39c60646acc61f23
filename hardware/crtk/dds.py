"""Every DDS participant this project makes, pinned to the loopback interface.

Cyclone DDS left to its defaults picks the machine's network interface, announces itself by multicast on it and
answers whoever replies. A participant made here is told instead (:func:`loopback_config`): the ``lo`` interface
only, multicast off (so nothing is sent to a multicast group and none is joined), 127.0.0.1 its only peer, unicast
discovery through the well-known port of each participant index on it. What it sends therefore leaves from a socket
bound to 127.0.0.1, which the kernel routes nowhere but the loopback. (Cyclone still listens for unicast on the
domain's well-known ports on every address; with no peer but 127.0.0.1 and no interface but ``lo`` it talks to
nobody it hears from elsewhere.)

Cyclone keeps one domain per id per process, created with its configuration by the first participant; a
participant made on a domain id the process has not configured would get Cyclone's defaults. So participants are
made only through :class:`Participant`, which configures the domain when the process's first participant on it
is made and lets it go with the last.

ROS 2 over Cyclone (``rmw_cyclonedds_cpp``) names a ROS topic ``/a/b`` ``rt/a/b`` on the wire, and its messages
are XCDR1 (plain CDR): :func:`ros_topic` and the QoS here say so once.
"""

from __future__ import annotations

from typing import Any

from cyclonedds._clayer import ddspy_write
from cyclonedds.core import DDSException
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from hardware.settings import ConfigError

# The RTPS port mapping (7400 + 250 * domain + offsets) puts a domain's ports past 65535 beyond this id.
MAX_DOMAIN_ID = 232
# Participant indices Cyclone tries on a host, and so the ports a unicast-discovering peer probes.
MAX_PARTICIPANT_INDEX = 9

PORT_BASE, DOMAIN_GAIN, PARTICIPANT_GAIN = 7400, 250, 2
DISCOVERY_UNICAST_OFFSET, DATA_UNICAST_OFFSET = 10, 11


def domain_id(key: str, value: Any) -> int:
    """A DDS domain id (ConfigError naming ``key`` otherwise)."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_DOMAIN_ID:
        raise ConfigError(key, f"must be a whole number from 0 to {MAX_DOMAIN_ID} (a DDS domain id), got {value!r}")
    return value


def unicast_ports(domain: int) -> set[int]:
    """The ports a participant on ``domain`` may listen on for unicast discovery and data, one pair per
    participant index."""
    base = PORT_BASE + DOMAIN_GAIN * domain
    return {base + offset + PARTICIPANT_GAIN * index for index in range(MAX_PARTICIPANT_INDEX + 1)
            for offset in (DISCOVERY_UNICAST_OFFSET, DATA_UNICAST_OFFSET)}


def loopback_config(domain: int | None) -> str:
    """Cyclone's configuration (the XML ``CYCLONEDDS_URI`` takes) for one domain on the loopback interface only;
    ``None``: for every domain (what a process's environment sets, for a participant made some other way)."""
    which = "any" if domain is None else domain_id("domain", domain)
    return (
        '<CycloneDDS xmlns="https://cdds.io/config">'
        f'<Domain Id="{which}">'
        '<General><Interfaces><NetworkInterface name="lo" multicast="false"/></Interfaces>'
        '<AllowMulticast>false</AllowMulticast></General>'
        '<Discovery><ParticipantIndex>auto</ParticipantIndex>'
        f'<MaxAutoParticipantIndex>{MAX_PARTICIPANT_INDEX}</MaxAutoParticipantIndex>'
        '<Peers AddLocalhost="false"><Peer address="127.0.0.1"/></Peers></Discovery>'
        '</Domain></CycloneDDS>')


def take(reader: DataReader, most: int) -> list:
    """The data samples ``reader`` holds (at most ``most``), oldest first, without waiting; the notices that a
    writer left, which a reader also hands out, are dropped."""
    return [sample for sample in reader.take(most) if sample.sample_info.valid_data]


def write_encoded(writer: DataWriter, data: bytes) -> None:
    """Write a sample already in XCDR1 (encapsulation header included) for ``writer``'s type, as
    :meth:`DataWriter.write` writes the bytes it serialises: padded with zeros to a multiple of 4. The binding
    serialises a sample field by field in Python (23 µs a WrenchStamped, measured); the console's own topics
    are encoded a block of rows at a time with numpy instead (:mod:`session.mcap_export`, 1.6 µs a message
    written), which a test holds to the binding's bytes. DDSException if the write fails."""
    ret = ddspy_write(writer._ref, data + bytes(-len(data) % 4))
    if ret < 0:
        raise DDSException(ret, f"Occurred while writing an encoded sample in {writer!r}")


def ros_topic(name: str) -> str:
    """The DDS topic of the ROS 2 topic ``name`` (``/PSM1/measured_cp`` or ``PSM1/measured_cp``)."""
    return "rt/" + name.lstrip("/")


XCDR1 = Policy.DataRepresentation(use_cdrv0_representation=True)
# A stream of readings or setpoints: only the newest matters. Reliable, so that a ROS subscriber with the default
# (reliable) QoS matches it; keep-last 1, so a writer never waits for a slow reader.
STREAM = Qos(Policy.Reliability.Reliable(max_blocking_time=0), Policy.History.KeepLast(1), XCDR1)
# A state that a late joiner must still see (the dVRK's operating_state).
LATCHED = Qos(Policy.Reliability.Reliable(max_blocking_time=0), Policy.Durability.TransientLocal,
              Policy.History.KeepLast(1), XCDR1)
# Commands: every one counts.
COMMANDS = Qos(Policy.Reliability.Reliable(max_blocking_time=0), Policy.History.KeepLast(16), XCDR1)

_domains: dict[int, list] = {}  # domain id -> [Domain, participants on it]: Cyclone's own state is per process


class Participant:
    """A DDS participant on ``domain``, configured by :func:`loopback_config`; its topics, readers and writers.

    :meth:`close` deletes them all (a reliable writer first waits a moment for its last samples to be acknowledged)
    and, with the process's last participant on the domain, the domain and its sockets."""

    def __init__(self, domain: int):
        self.domain = domain_id("domain", domain)
        entry = _domains.get(domain)
        if entry is None:
            entry = _domains[domain] = [Domain(domain, loopback_config(domain)), 0]
        entry[1] += 1
        try:
            self._participant: DomainParticipant | None = DomainParticipant(domain)
        except BaseException:
            self._release()
            raise
        self._topics: dict[str, Topic] = {}
        self._endpoints: list[DataReader | DataWriter] = []

    def _topic(self, name: str, data_type: type) -> Topic:
        if self._participant is None:
            raise RuntimeError("the DDS participant is closed")
        topic = self._topics.get(name)
        if topic is None:
            topic = self._topics[name] = Topic(self._participant, name, data_type)
        return topic

    def writer(self, name: str, data_type: type, qos: Qos = STREAM) -> DataWriter:
        writer = DataWriter(self._participant, self._topic(name, data_type), qos=qos)
        self._endpoints.append(writer)
        return writer

    def reader(self, name: str, data_type: type, qos: Qos = STREAM) -> DataReader:
        reader = DataReader(self._participant, self._topic(name, data_type), qos=qos)
        self._endpoints.append(reader)
        return reader

    def close(self) -> None:
        """Safe to call twice; the readers and writers it made are deleted with it, whoever still holds them."""
        participant, self._participant = self._participant, None
        if participant is None:
            return
        # The binding deletes an entity when its Python object is collected, and its __del__ is written to run
        # once; called here, the participant and everything in it go now, not whenever the last reference does.
        participant.__del__()
        self._endpoints.clear()
        self._topics.clear()
        self._release()

    def _release(self) -> None:
        entry = _domains[self.domain]
        entry[1] -= 1
        if entry[1] == 0:
            del _domains[self.domain]
            entry[0].__del__()
