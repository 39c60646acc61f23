"""`palpation-console devices`: listing USB devices with their roles, probing a serial port and a slave."""

import threading

import numpy as np

from hardware import discovery
from hardware.serial_tactile.emulator import SerialSensorEmulator
from hardware.udp import SlaveServer, SlaveServerSettings
from tests.hardware.test_udp_link import Robot


def test_usb_devices_are_listed_with_the_role_they_could_play(bus):
    found, problem = discovery.usb_devices(bus)
    assert problem == ""
    roles = {f.address: f for f in found}
    assert "tactile sensor" in roles["1209:0001"].role and "TSI 4x15" in roles["1209:0001"].description
    assert 'kind = "spacemouse"' in roles["256f:c62e"].role
    assert roles["046d:c31c"].role == "" and "Keyboard" in roles["046d:c31c"].description
    # a device the user may not open is still listed, by its known name, with what to do about it
    assert "udev rule" in roles["256f:c635"].note and "SpaceMouse Compact" in roles["256f:c635"].description
    assert [f.role != "" for f in found] == [True, True, True, False]  # recognised ones first


def probe_while_sending(emu, send, **probe):
    """Run the probe on its thread while the emulated device keeps sending (opening a port flushes it)."""
    result = []
    prober = threading.Thread(target=lambda: result.append(discovery.probe_serial(emu.path, **probe)))
    prober.start()
    k = 0
    while prober.is_alive():
        send(k)
        k += 1
        prober.join(0.002)
    return result[0]


def test_probing_a_serial_port_recognises_tsi_frames(tmp_path):
    with SerialSensorEmulator(directory=tmp_path) as emu:
        # 100 frames/s by the device's clock, however fast the test sends them
        found = probe_while_sending(emu, lambda k: emu.send(np.full((4, 15), 2000.0), 10.0 + 0.01 * k), listen_s=0.3)
        assert "TSI frames, 4 x 15, 100 frames/s" in found.note and f'port = "{emu.path}"' in found.role
        found = probe_while_sending(emu, lambda k: emu.write(b"AT+OK\r\n"), listen_s=0.1)
        assert found.role == "" and "no TSI frames" in found.note and "bytes that were not TSI frames" in found.note
    assert "there is no serial port" in discovery.probe_serial(str(tmp_path / "gone")).note


def test_probing_a_slave_answers_without_disturbing_it():
    robot = Robot()
    server = SlaveServer(robot, SlaveServerSettings(port=0))
    server.open()
    stop = threading.Event()
    serving = threading.Thread(target=server.serve, args=(stop,))
    serving.start()
    try:
        host, port = server.address
        found = discovery.probe_udp(host, port, count=3)
        assert found.role and "answered 3/3 pings" in found.note and "holding" in found.note
    finally:
        stop.set()
        serving.join()
        server.close()
    assert server.stats["pings"] == 3 and server.stats["commands"] == 0
    assert all(kind == "hold" for kind, _ in robot.orders)
    nobody = discovery.probe_udp(host, port, timeout_s=0.05, count=1)
    assert nobody.role == "" and "no answer" in nobody.note
