"""The UDP master/slave link on loopback: both ends, their watchdogs and every network fault.

Both ends are driven tick by tick on a virtual clock; the datagrams travel for real, and the tests wait
for them on the sockets (select), never by sleeping.
"""

import math
import select
import socket

import numpy as np
import pytest

from app.runtime import make_loop, run_tick
from control.config import ControlConfig
from control.loop import ControlLoop
from control.messages import ClearFault, FaultCleared, FaultKind, FaultRaised
from hardware.interfaces import (
    ConnectionState,
    DeviceError,
    SlaveConstraints,
    SlaveManipulator,
    SlaveState,
    TactileConstraints,
)
from hardware.rig import Rig
from hardware.settings import ConfigError
from hardware.sim.rig import build_sim_rig
from hardware.udp import SlaveServer, SlaveServerSettings, UdpLinkSettings, UdpSlaveLink
from hardware.udp import protocol as P
from hardware.udp.relay import TO_MASTER, TO_SLAVE, Faults, FaultyRelay

T0 = 100.0
MS = 1e-3
HOME = (0.036, 0.015, 0.06)


class Robot(SlaveManipulator):
    """Goes where it is told at once and remembers every order."""

    name = "test-robot"
    constraints = SlaveConstraints()

    def __init__(self):
        self.position = HOME
        self.orders: list[tuple[str, tuple]] = []
        self._state = ConnectionState.DISCONNECTED
        self._latest = None
        self._seq = 0

    @property
    def connection(self):
        return self._state

    def open(self):
        self._state = ConnectionState.CONNECTED

    def close(self):
        self._state = ConnectionState.DISCONNECTED

    def poll(self, now_s):
        self._seq += 1
        self._latest = SlaveState(self._seq, now_s, self.position, (0.0, 0.0, 0.0))

    def latest(self):
        return self._latest

    def command(self, position_m, velocity_m_s, now_s):
        self.orders.append(("track", tuple(position_m)))
        self.position = tuple(position_m)

    def hold(self, now_s):
        self.orders.append(("hold", self.position))


def arrived(fd, timeout_s=1.0) -> bool:
    return bool(select.select([fd], [], [], timeout_s)[0])


class Wire:
    """The console's link and the slave server, optionally through a faulty relay, one tick at a time."""

    def __init__(self, server: SlaveServer, relay: FaultyRelay | None = None, slave_clock_offset_s: float = 0.0,
                 **link_settings):
        self.server, self.relay = server, relay
        target = relay.address if relay is not None else server.address
        self.link = UdpSlaveLink(UdpLinkSettings(host=target[0], port=target[1], **link_settings))
        self.offset = slave_clock_offset_s

    def carry(self, dest_fd: int, n: int) -> None:
        """Wait until the ``n`` datagrams just sent are at ``dest_fd`` (or the relay dropped them)."""
        if n == 0:
            return
        if self.relay is None:
            arrived(dest_fd)
            return
        before, got = self.relay.counts["forwarded"], 0
        while got < n and arrived(self.relay.fileno()):
            got += self.relay.step()
        if self.relay.counts["forwarded"] > before:
            arrived(dest_fd)

    def to_slave(self, send) -> None:
        sent = self.link.counters["sent"]
        send()
        self.carry(self.server.fileno(), self.link.counters["sent"] - sent)

    def slave_step(self, now: float) -> None:
        sent = self.server.counters["sent"]
        self.server.step(now + self.offset)
        self.carry(self.link.fileno(), self.server.counters["sent"] - sent)

    def tick(self, now: float, reference=None) -> None:
        """The master sends (a HOLD without a reference), the slave steps, the master polls."""
        if reference is None:
            self.to_slave(lambda: self.link.hold(now))
        else:
            self.to_slave(lambda: self.link.command(reference, (0.0, 0.0, 0.0), now))
        self.slave_step(now)
        self.link.poll(now)


@pytest.fixture
def robot():
    return Robot()


@pytest.fixture
def server(robot):
    s = SlaveServer(robot, SlaveServerSettings(port=0))
    s.open()
    yield s
    s.close(T0)


@pytest.fixture
def wire(server):
    w = Wire(server)
    w.link.open()
    yield w
    w.link.close()


def test_states_flow_on_our_clock_even_when_the_slave_clock_is_elsewhere(server, robot):
    wire = Wire(server, slave_clock_offset_s=1000.0)
    wire.link.open()
    try:
        for k in range(20):
            wire.tick(T0 + k * MS, reference=(0.036, 0.015, 0.06 - 1e-4 * k))
        st = wire.link.latest()
        assert wire.link.connection == ConnectionState.CONNECTED
        # read at the step that received the last reference, before applying it
        assert st.position_m == pytest.approx((0.036, 0.015, 0.06 - 18e-4))
        assert wire.link.clock.offset_s == pytest.approx(1000.0, abs=1e-9)
        assert st.t_s == pytest.approx(T0 + 19 * MS)  # measured at the slave's step, mapped onto ours
        assert robot.orders[-1] == ("track", (0.036, 0.015, 0.06 - 19e-4))
        assert wire.link.stats["lost"] == 0 and wire.server.stats["commands"] == 20
    finally:
        wire.link.close()


def test_until_a_master_speaks_the_robot_holds_and_nobody_is_sent_anything(server, robot):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as spy:
        spy.bind(("127.0.0.1", 0))
        for k in range(5):
            server.step(T0 + k * MS)
        assert robot.orders == [("hold", HOME)]
        assert not arrived(spy.fileno(), 0.0)


def test_no_state_for_the_timeout_makes_the_link_lost_and_the_loop_hold(wire):
    loop = ControlLoop(ControlConfig(), TactileConstraints(), has_master=False)
    events = []
    for k in range(40):
        wire.tick(T0 + k * MS, reference=HOME)
    assert wire.link.connection == ConnectionState.CONNECTED
    last = wire.link.latest()
    for k in range(40, 80):  # the slave falls silent; the loop keeps ticking on the stale reading
        now = T0 + k * MS
        wire.link.poll(now)
        events += loop.step(now, None, wire.link.latest(), None).events
    assert wire.link.latest() is last
    assert wire.link.connection == ConnectionState.LOST and wire.link.stats["link_losses"] == 1
    assert "no state from the slave" in wire.link.stats["last_error"]
    assert any(isinstance(e, FaultRaised) and e.kind == FaultKind.SLAVE_STALE for e in events)


def test_the_slave_watchdog_holds_and_the_link_withholds_readings_until_the_master_notices(wire, robot):
    for k in range(10):
        wire.tick(T0 + k * MS, reference=HOME)
    server = wire.server
    published = []
    for k in range(10, 40):  # commands stop reaching the slave; its states still flow
        server.step(T0 + k * MS)
        arrived(wire.link.fileno())
        wire.link.poll(T0 + k * MS)
        published.append(wire.link.latest().seq)
    assert server.stats["link_timeouts"] == 1 and "no command from the master" in server.stats["last_error"]
    assert robot.orders[-1][0] == "hold"
    assert wire.link.connection == ConnectionState.LOST
    # states about a robot that ignores us are not readings: they stopped 20 ms after the last command
    published = published[-1]
    assert wire.link.latest().t_s == pytest.approx(T0 + 0.029)
    assert "holding on its own" in wire.link.stats["last_error"] and wire.link.stats["slave_holds"] == 1

    # commands resume with a reference that moved 5 mm on meanwhile: refused, still holding
    wire.tick(T0 + 0.040, reference=(HOME[0] + 0.005, HOME[1], HOME[2]))
    assert server.stats["jumps_refused"] == 1 and robot.position == HOME
    assert wire.link.latest().seq == published
    # the master holds (as the console's loop does once its watchdog fires): the slave follows again
    wire.tick(T0 + 0.041)
    assert wire.link.connection == ConnectionState.CONNECTED and wire.link.latest().seq > published
    target = (HOME[0] + 0.001, HOME[1], HOME[2])
    wire.tick(T0 + 0.042, reference=target)
    # followed again, no faster than the slave's own 0.1 m/s: 0.1 mm in this 1 ms step
    assert robot.position[0] - HOME[0] == pytest.approx(1e-4, abs=2e-6) and server.status & P.Status.LIMITED
    for k in range(43, 60):
        wire.tick(T0 + k * MS, reference=target)
    assert robot.position == target and not server.status & P.Status.LIMITED


def test_a_nearby_reference_resumes_tracking_after_a_short_dropout(wire, robot):
    for k in range(10):
        wire.tick(T0 + k * MS, reference=HOME)
    for k in range(10, 40):
        wire.server.step(T0 + k * MS)
    near = (HOME[0] + 0.0005, HOME[1], HOME[2])  # 0.5 mm: within the 2 mm resume distance
    for k in range(40, 50):
        wire.tick(T0 + k * MS, reference=near)
    assert robot.position == near and wire.server.stats["jumps_refused"] == 0


def test_late_and_duplicate_commands_never_reach_the_robot(server, robot):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as master:
        def send(seq, z):
            master.sendto(P.pack_command(5, seq, T0, P.Command(P.Mode.TRACK, (HOME[0], HOME[1], z), (0, 0, 0))),
                          server.address)
            arrived(server.fileno())
            server.step(T0 + seq * MS)

        for seq, z in [(0, 0.06000), (1, 0.06001), (1, 0.06002), (4, 0.06004), (3, 0.06003), (5, 0.06005)]:
            send(seq, z)
    tracked = [p[2] for kind, p in robot.orders if kind == "track"]
    assert tracked == [0.06000, 0.06001, 0.06004, 0.06005]
    st = server.stats
    assert (st["duplicates"], st["late"], st["lost"]) == (1, 1, 1)


def test_bad_datagrams_and_strangers_are_dropped_and_counted_at_both_ends(server, robot):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as fake_slave:
        fake_slave.bind(("127.0.0.1", 0))
        link = UdpSlaveLink(UdpLinkSettings(port=fake_slave.getsockname()[1]))
        link.open()
        try:
            link.poll(T0)  # its opening HOLD tells the fake slave where the console is
            assert arrived(fake_slave.fileno())
            data, console = fake_slave.recvfrom(P.RECV_BUFFER)
            hello = P.unpack(data)[0]
            good = P.State(P.Status.NONE, 1, T0, HOME, (0, 0, 0), 0.0, hello.seq, hello.t_send_s, T0)
            bad_crc = bytearray(P.pack_state(9, 0, T0, good))
            bad_crc[40] ^= 1
            nan = P.State(P.Status.NONE, 1, T0, (math.nan, 0.0, 0.0), (0, 0, 0), 0.0, 0, 0.0, 0.0)
            for junk in (bytes(3000), b"hello", bytes(bad_crc), P.pack_state(9, 0, T0, nan),
                         P.pack_ping(9, 0, T0)):
                fake_slave.sendto(junk, console)
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stranger:
                stranger.sendto(P.pack_state(9, 0, T0, good), console)
            fake_slave.sendto(P.pack_state(9, 1, T0, good), console)
            while link.latest() is None:
                assert arrived(link.fileno())
                link.poll(T0 + MS)
            st = link.stats
            assert (st["oversize"], st["malformed"], st["crc_errors"], st["invalid_values"], st["unexpected"],
                    st["rejected_peers"]) == (1, 1, 1, 1, 1, 1)
            assert link.latest().position_m == HOME and link.connection == ConnectionState.CONNECTED
        finally:
            link.close()

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as prober:
        cmd = P.pack_command(3, 0, T0, P.Command(P.Mode.TRACK, (0.0, 0.0, 0.03), (0, 0, 0)))
        for junk in (bytes(2000), cmd[:-1], cmd[:-4] + b"\0\0\0\0"):
            prober.sendto(junk, server.address)
        prober.sendto(P.pack_ping(3, 0, T0), server.address)
        assert arrived(server.fileno())
        server.step(T0)
        assert arrived(prober.fileno())  # a ping is answered at once, with a state echoing it
        header, state = P.unpack(prober.recv(P.RECV_BUFFER))
        assert state.status & P.Status.PING_REPLY and state.echo_seq == 0
    st = server.stats
    assert (st["oversize"], st["malformed"], st["crc_errors"], st["pings"]) == (1, 1, 1, 1)
    assert not any(kind == "track" for kind, _ in robot.orders)


def test_only_allowed_peers_may_command(robot):
    server = SlaveServer(robot, SlaveServerSettings(bind_host="127.0.0.1", port=0, allow=("10.1.2.0/24",)))
    server.open()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as intruder:
            intruder.sendto(P.pack_command(1, 0, T0, P.Command(P.Mode.TRACK, (0, 0, 0.02), (0, 0, 0))),
                            server.address)
            intruder.sendto(P.pack_ping(1, 1, T0), server.address)
            assert arrived(server.fileno())
            server.step(T0)
            server.step(T0 + MS)
            assert server.stats["rejected_peers"] == 2 and not arrived(intruder.fileno(), 0.05)
        assert robot.position == HOME
    finally:
        server.close(T0)


def test_binding_beyond_loopback_needs_an_explicit_allow_list():
    with pytest.raises(ConfigError, match="exposes the robot") as err:
        SlaveServerSettings.from_mapping({"bind_host": "0.0.0.0"}, "slave.")
    assert err.value.key == "slave.allow"
    assert SlaveServerSettings(bind_host="0.0.0.0", allow=("192.168.7.20",)).allows("192.168.7.20")
    assert not SlaveServerSettings().allows("192.168.7.20")
    with pytest.raises(ConfigError, match="IP address or network"):
        SlaveServerSettings(allow=("robot-pc",))


def test_a_port_in_use_is_a_sentence(server, robot):
    with pytest.raises(DeviceError, match="cannot listen on .*another slave running"):
        SlaveServer(Robot(), SlaveServerSettings(port=server.address[1])).open()
    link = UdpSlaveLink(UdpLinkSettings(bind_port=server.address[1]))
    with pytest.raises(DeviceError, match="cannot bind"):
        link.open()


def test_through_a_lossy_reordering_duplicating_corrupting_network(server, robot):
    faults = Faults(drop=0.05, duplicate=0.05, reorder=0.05, corrupt=0.03)
    with FaultyRelay(server.address, faults, seed=11) as relay:
        wire = Wire(server, relay)
        wire.link.open()
        try:
            seen = []
            for k in range(600):
                wire.tick(T0 + k * MS, reference=(HOME[0], HOME[1], 0.06 - 1e-5 * k))
                st = wire.link.latest()
                if st is not None and (not seen or st.seq != seen[-1].seq):
                    seen.append(st)
        finally:
            wire.link.close()
        link, srv = wire.link.stats, server.stats
        for stats in (link, srv):
            assert stats["lost"] > 0 and stats["late"] > 0 and stats["duplicates"] > 0 and stats["crc_errors"] > 0
        assert relay.counts["corrupted"] > 0
    # nothing reordered or repeated reached the robot, nor came back as a reading
    tracked = [p[2] for kind, p in robot.orders if kind == "track"]
    assert all(b < a for a, b in zip(tracked, tracked[1:]))
    zs = [s.position_m[2] for s in seen]
    assert all(b <= a for a, b in zip(zs, zs[1:])) and len(seen) > 500


def test_end_to_end_a_blackout_makes_both_sides_hold_and_the_operator_recovers():
    """The console's loop on the UDP rig (sim robot and its forwarded sensor), through a pulled cable."""
    sim = build_sim_rig("flat")
    server = SlaveServer(sim.slave, SlaveServerSettings(port=0), sensor=sim.sensor)
    server.open()
    relay = FaultyRelay(server.address)
    wire = Wire(server, relay)
    rig = Rig(sensor=wire.link.tactile_sensor(), slave=wire.link)
    loop = make_loop(ControlConfig(), rig)
    rig.open()
    events = []

    def tick(k, commands=()):
        now = T0 + k * MS
        wire.to_slave(lambda: events.extend(run_tick(loop, rig, now, commands).events))
        wire.slave_step(now)

    try:
        for k in range(300):
            tick(k)
        assert rig.sensor.connection == ConnectionState.CONNECTED and rig.sensor.latest() is not None
        assert not any(isinstance(e, FaultRaised) for e in events)
        assert math.isfinite(wire.link.force_N)

        relay.blackout = {TO_SLAVE, TO_MASTER}
        for k in range(300, 360):
            tick(k)
        fault = next(e for e in events if isinstance(e, FaultRaised))
        assert fault.kind == FaultKind.SLAVE_STALE and fault.t_s - T0 == pytest.approx(0.310, abs=2e-3)
        assert server.stats["link_timeouts"] == 1 and server.status & P.Status.LINK_TIMEOUT
        assert wire.link.connection == ConnectionState.LOST
        stopped = sim.slave.latest().position_m

        relay.blackout = set()
        for k in range(360, 400):
            tick(k)
        # the loop holds (HOLD packets), the slave takes that as the master noticing, readings return
        assert wire.link.connection == ConnectionState.CONNECTED and not server.status & P.Status.LINK_TIMEOUT
        tick(400, [ClearFault()])
        assert any(isinstance(e, FaultCleared) for e in events)
        for k in range(401, 450):
            tick(k)
        assert server.status == P.Status.NONE  # tracking the loop's reference again
        assert np.allclose(sim.slave.latest().position_m, stopped, atol=5e-4)  # nothing jumped
    finally:
        rig.close()
        relay.close()
        server.close(T0)


def test_a_remote_slave_needs_a_non_loopback_binding():
    with pytest.raises(DeviceError, match="another computer.*bind_host"):
        UdpSlaveLink(UdpLinkSettings(host="192.0.2.10")).open()


class Master:
    """A raw master socket: what a console, a lying one or a stale one can send."""

    def __init__(self, server: SlaveServer, session: int):
        self.server, self.session, self.seq = server, session, 0
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))

    def send(self, now: float, position=None, velocity=(0.0, 0.0, 0.0)) -> None:
        mode = P.Mode.HOLD if position is None else P.Mode.TRACK
        cmd = P.Command(mode, position if position is not None else (0.0, 0.0, 0.0), velocity)
        self.sock.sendto(P.pack_command(self.session, self.seq, now, cmd), self.server.address)
        self.seq += 1
        arrived(self.server.fileno())

    def close(self):
        self.sock.close()


class PressingSensor:
    """A slave-side tactile array over a flat layer at z = 50 mm, 2 N per mm of indentation, a new frame at
    each poll with 20 Pa of noise; ``lie(reading)`` makes it report ``reading(true pressure)`` instead."""

    name = "pressing"
    constraints = TactileConstraints()

    def __init__(self, robot: Robot):
        self.robot = robot
        self.reading = lambda pressure: pressure
        self._frame = None
        self._noise = np.random.default_rng(0)

    def open(self):
        pass

    def close(self):
        pass

    def poll(self, now_s):
        from hardware.interfaces import TactileFrame
        force = 2000.0 * max(0.050 - self.robot.position[2], 0.0)
        true = np.full((4, 15), force / 60 / self.constraints.element_area_m2) + self._noise.normal(0, 20, (4, 15))
        seq = self._frame.seq + 1 if self._frame is not None else 0
        self._frame = TactileFrame(seq, now_s, self.reading(true))

    def latest(self):
        return self._frame


def test_a_lying_master_cannot_take_the_robot_past_the_slaves_own_limits(robot):
    """Issue 14, finding 4: while tracking, the slave followed any finite setpoint (at 0.25 m/s to z = 0,
    reporting 23.3 N). Now its own speed, workspace and force limits hold whatever the master sends."""
    server = SlaveServer(robot, SlaveServerSettings(port=0, force_limit_N=10.0), sensor=PressingSensor(robot))
    server.open()
    liar = Master(server, 0x11)
    try:
        z = [HOME[2]]
        for k in range(100):  # a reference diving at 0.25 m/s, each step within the jump guard
            now = T0 + k * MS
            liar.send(now, (HOME[0], HOME[1], HOME[2] - 0.25 * k * MS), (0.0, 0.0, -0.25))
            server.step(now)
            z.append(robot.position[2])
        assert -np.diff(z).max() <= 0.1 * MS + 1e-9  # the robot's own 0.1 m/s, not the master's 0.25
        assert server.stats["limited"] >= 10
        # the reference ran away from what the robot was allowed to follow: past 2 mm the slave held
        assert server.stats["jumps_refused"] == 1 and robot.orders[-1][0] == "hold"
        assert HOME[2] - robot.position[2] < 0.002
        master = Master(server, 0x12)
        for k in range(100, 1200):  # then, after the watchdog, a master that pushes on at 50 mm/s to z = 0
            now = T0 + k * MS
            master.send(now, (HOME[0], HOME[1], max(robot.position[2] - 0.05 * MS, 0.0)))
            server.step(now)
            z.append(robot.position[2])
        # the force limit latched at 10 N (5 mm into the layer); deeper references were cut
        assert server.status & P.Status.FORCE_LIMIT and server.stats["force_limits"] == 1
        assert min(z) > 0.050 - 0.0051
        assert "above the slave's own 10 N limit" in server.stats["last_error"]
        liar.close()
        liar = master
        # references that lift the probe are followed; the latch lets go below 8 N
        bottom = robot.position[2]
        for k in range(200, 230):
            now = T0 + k * MS
            liar.send(now, (HOME[0], HOME[1], bottom + (k - 199) * 0.05e-3))
            server.step(now)
        assert robot.position[2] > bottom + 1e-3 and not server.status & P.Status.FORCE_LIMIT
        # a reference outside the robot's workspace is cut to it
        top = robot.constraints.workspace_max_m[2]
        for k in range(230, 1000):
            now = T0 + k * MS
            liar.send(now, (HOME[0], HOME[1], min(robot.position[2] + 1e-3, 0.5)))
            server.step(now)
        assert robot.position[2] == pytest.approx(top) and server.stats["jumps_refused"] == 1
    finally:
        liar.close()
        server.close(T0)


def test_hold_keeps_the_jump_guard(server, robot):
    # one HOLD packet used to switch the jump check off: the next reference, 30 mm away, was followed
    master = Master(server, 0x22)
    try:
        master.send(T0, HOME)
        server.step(T0)
        master.send(T0 + MS)
        server.step(T0 + MS)
        master.send(T0 + 2 * MS, (HOME[0] + 0.03, HOME[1], HOME[2]))
        server.step(T0 + 2 * MS)
        assert robot.position == HOME and server.stats["jumps_refused"] == 1
        assert server.status & P.Status.JUMP_REFUSED
    finally:
        master.close()


def test_a_second_master_takes_over_only_after_the_first_falls_silent_and_never_comes_back(server, robot):
    # two interleaved senders used to swap the master 654 times; a packet of an earlier session was accepted
    first, second = Master(server, 0x33), Master(server, 0x44)
    try:
        for k in range(50):
            now = T0 + k * MS
            first.send(now, (HOME[0], HOME[1], HOME[2] - 1e-5 * k))
            second.send(now, (HOME[0] + 1e-3, HOME[1], HOME[2]))
            server.step(now)
        st = server.stats
        assert st["master_changes"] == 0 and st["takeovers_refused"] == 50
        assert robot.position[0] == HOME[0]  # only the first master moved it
        assert "is still talking" in st["last_error"]
        for k in range(50, 80):  # the first falls silent: the watchdog holds, then the second may take over
            second.send(T0 + k * MS)
            server.step(T0 + k * MS)
        assert server.stats["master_changes"] == 1 and server.stats["master"].endswith(
            str(second.sock.getsockname()[1]))
        first.send(T0 + 0.081, HOME)  # the first comes back with its old session: refused for good
        server.step(T0 + 0.081)
        for k in range(82, 200):
            server.step(T0 + k * MS)
        first.send(T0 + 0.2, HOME)
        server.step(T0 + 0.2)
        assert server.stats["stale_sessions"] == 2 and server.stats["master_changes"] == 1
    finally:
        first.close()
        second.close()


@pytest.mark.parametrize("lie, at, said", [
    # a dead array streaming zeros, from above the tissue
    (lambda pressure: np.zeros_like(pressure), 300, "identical frames: frozen"),
    # the same frame again and again, 4 mm in: found deeper before it is stale
    ("repeat", 700, "without the slave's tactile force rising"),
    # a dead array that reads its own noise, 4 mm in
    (lambda pressure: np.random.default_rng().normal(0.0, 20.0, pressure.shape), 700, "deeper without the slave's"),
])
def test_the_slave_holds_on_its_own_when_its_array_stops_reading_the_tissue(robot, lie, at, said):
    """Issue 49: over UDP the slave's own 15 N limit read the same lying array and was as blind as the console.
    It now runs the console's liveness checks on its own copy: pressed on blind, it holds, lifting only."""
    sensor = PressingSensor(robot)
    server = SlaveServer(robot, SlaveServerSettings(port=0), sensor=sensor)
    server.open()
    master = Master(server, 0x21)
    try:
        z = []
        for k in range(3000):  # down at 20 mm/s from 10 mm above the layer: 4 mm into it after 0.7 s
            now = T0 + k * MS
            if k == at:
                if lie == "repeat":
                    frozen = sensor.latest().pressure_pa.copy()
                    sensor.reading = lambda pressure, frozen=frozen: frozen
                else:
                    sensor.reading = lie
            master.send(now, (HOME[0], HOME[1], max(robot.position[2] - 0.02 * MS, 0.0)))
            server.step(now)
            z.append(robot.position[2])
        assert server.status & P.Status.SENSOR_LOST and server.stats["sensor_lost"] == 1
        assert said in server.stats["last_error"]
        assert 0.050 - min(z) < 0.004 + 1.5e-3  # no more than the travel check allows past where it lied
        # lifted off the tissue with its array reading again, the slave follows the master once more
        sensor.reading = lambda pressure: pressure
        bottom = robot.position[2]
        for k in range(3000, 4500):
            now = T0 + k * MS
            master.send(now, (HOME[0], HOME[1], robot.position[2] + 0.02 * MS))
            server.step(now)
        assert robot.position[2] > max(bottom + 1e-3, 0.050) and not server.status & P.Status.SENSOR_LOST
    finally:
        master.close()
        server.close(T0)
