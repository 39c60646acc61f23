"""Choosing the real-hardware rig: the [hardware] tables of the config, the command line's flags."""

import select
import threading
import time

import pytest

from app.cli import build_parser, config_overrides, main
from app.config import COMMAND_LINE, load_config
from app.rigs import build_rig
from app.runtime import make_loop, run_tick
from hardware.interfaces import ConnectionState
from hardware.serial_tactile import SerialTactileSensor
from hardware.serial_tactile.emulator import SerialSensorEmulator, SimSensorFeed
from hardware.settings import ConfigError
from hardware.sim.rig import build_sim_rig
from hardware.udp import SlaveServer, SlaveServerSettings, UdpSlaveLink, UdpTactileSensor


def _write(tmp_path, text):
    f = tmp_path / "user.toml"
    f.write_text(text)
    return f


def test_the_udp_backend_with_default_hardware_is_the_slave_and_its_forwarded_sensor():
    config = load_config(overrides={"rig": {"backend": "udp"}})
    assert config.rig.hardware == {}
    rig = build_rig(config.rig, progress=lambda fraction, what: None)
    assert isinstance(rig.slave, UdpSlaveLink) and isinstance(rig.sensor, UdpTactileSensor) and rig.master is None
    assert rig.description["backend"] == "udp"


def test_a_config_with_hardware_tables_drives_the_slave_and_a_serial_sensor(tmp_path):
    """The config file alone chooses the backends: the slave server on the simulated robot, its sensor's
    frames on a pseudo-terminal, both reached through app.rigs.build_rig as the controller process does."""
    sim = build_sim_rig("flat")
    server = SlaveServer(sim.slave, SlaveServerSettings(port=0, forward_tactile=False), sensor=sim.sensor)
    server.open()
    emulator = SerialSensorEmulator(directory=tmp_path)
    feed = SimSensorFeed(sim.sensor, emulator.device)
    f = _write(tmp_path, f'[rig]\nbackend = "udp"\n\n'
                         f'[hardware.slave]\nhost = "127.0.0.1"\nport = {server.address[1]}\n\n'
                         f'[hardware.sensor]\nkind = "serial"\nport = "{emulator.path}"\n')
    config = load_config(f)
    rig = build_rig(config.rig)
    assert isinstance(rig.sensor, SerialTactileSensor) and isinstance(rig.slave, UdpSlaveLink)
    assert rig.description["hardware"]["sensor"]["port"] == emulator.path
    loop = make_loop(config.control, rig)
    stop = threading.Event()
    serving = threading.Thread(target=server.serve, args=(stop,), kwargs={"on_step": feed.pump})
    rig.open()
    serving.start()
    try:
        deadline = time.monotonic() + 10.0
        # paced by the socket and the serial line: each tick waits for whichever speaks first
        while rig.sensor.latest() is None or rig.slave.connection != ConnectionState.CONNECTED:
            assert time.monotonic() < deadline, f"the rig never came up: {rig.sensor.stats} {rig.slave.stats}"
            select.select([rig.sensor.fileno(), rig.slave.fileno()], [], [], 1e-3)
            run_tick(loop, rig, time.monotonic())
        assert rig.sensor.connection == ConnectionState.CONNECTED
        assert rig.slave.stats["force_N"] == pytest.approx(0.0, abs=0.05)  # the slave's robot, in the air
    finally:
        stop.set()
        serving.join()
        rig.close()
        server.close()
        emulator.close()


@pytest.mark.parametrize("text, key, problem", [
    ("[hardware.sensor]\nkind = \"serial\"\nport = \"/dev/ttyACM0\"\nbaud = 9600\n", "hardware.sensor.baud",
     "carries at most"),
    ("[hardware.sensor]\nkind = \"bluetooth\"\n", "hardware.sensor.kind", "unknown kind"),
    ("[hardware.slave]\nprot = 47600\n", "hardware.slave.prot", "unknown key"),
    ("[hardware.master]\nkind = \"spacemouse\"\nspeed = 1\n", "hardware.master.speed", "unknown key"),
    ("[hardware.robot]\nx = 1\n", "hardware.robot", "unknown table"),
    ("[sim.sensor]\nnoise_std_pa = -1\n", "sim.sensor.noise_std_pa", ">= 0"),
    ("[sim]\nsubstep = 0.001\n", "sim.substep", "unknown key"),
    # issue 49: tracebacks from the world's integration before
    ("[sim.robot]\nbandwidth_hz = 1e300\n", "sim.robot.bandwidth_hz", "between 0.5 and 200"),
    ("[sim]\nsubstep_s = 1e-300\n", "sim.substep_s", "between 1e-05 and 0.001"),
    ("[sim.sensor]\nmodel = \"perfect\"\n", "sim.sensor.model", "one of ideal, realistic"),
    ("[rig]\nbackend = \"ethercat\"\n", "rig.backend", "unknown backend 'ethercat' (known: crtk, sim, udp)"),
])
def test_bad_hardware_and_sim_keys_are_refused_at_load_time_naming_file_and_key(tmp_path, text, key, problem):
    """Even with the simulated rig, so a typo in a table not used today is found before anything starts."""
    f = _write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_config(f)
    assert err.value.key == f"{f}: {key}" and problem in err.value.problem


def test_a_mistake_is_blamed_on_its_source(tmp_path):
    f = _write(tmp_path, "[hardware.slave]\ntimeout_s = 0\n")
    with pytest.raises(ConfigError) as err:
        load_config(f, {"hardware": {"slave": {"port": 47601}}})
    assert err.value.key == f"{f}: hardware.slave.timeout_s"
    with pytest.raises(ConfigError) as err:
        load_config(None, {"hardware": {"slave": {"port": 70000}}})
    assert err.value.key == f"{COMMAND_LINE}: hardware.slave.port"
    assert load_config(None, {"rig": {"seed": 2}}).sources[-1] == COMMAND_LINE  # recorded in session files
    assert COMMAND_LINE not in load_config().sources


@pytest.mark.parametrize("argv, overrides", [
    (["run"], {}),
    (["run", "--backend", "udp"], {"rig": {"backend": "udp"}}),
    (["run", "--backend", "sim", "--phantom", "lumps"], {"rig": {"backend": "sim", "phantom": "lumps"}}),
    (["run", "--slave", "robot-pc:47600"],
     {"rig": {"backend": "udp"}, "hardware": {"slave": {"host": "robot-pc", "port": 47600}}}),
    (["run", "--slave", "[::1]:47601", "--sensor", "serial:/dev/ttyUSB0"],
     {"rig": {"backend": "udp"}, "hardware": {"slave": {"host": "::1", "port": 47601},
                                              "sensor": {"kind": "serial", "port": "/dev/ttyUSB0"}}}),
    (["run", "--sensor", "udp"], {"rig": {"backend": "udp"}, "hardware": {"sensor": {"kind": "udp"}}}),
    (["run", "--sensor", "usb"], {"rig": {"backend": "udp"}, "hardware": {"sensor": {"kind": "usb"}}}),
    (["run", "--backend", "udp", "--sensor", "usb:1209:0042"],
     {"rig": {"backend": "udp"}, "hardware": {"sensor": {"kind": "usb", "vid_pid": "1209:0042"}}}),
])
def test_flags_map_to_config_overrides(argv, overrides):
    assert config_overrides(build_parser().parse_args(argv)) == overrides


def test_flags_override_only_the_keys_they_name(tmp_path):
    f = _write(tmp_path, '[hardware.sensor]\nkind = "serial"\nport = "/dev/ttyACM0"\nbaud = 921600\n'
                         '[hardware.slave]\nbind_host = "127.0.0.1"\n')
    args = build_parser().parse_args(["--config", str(f), "run", "--sensor", "serial:/dev/ttyUSB1",
                                      "--slave", "localhost:47700"])
    config = load_config(args.config, config_overrides(args))
    assert config.rig.backend == "udp"
    assert config.rig.hardware["sensor"] == {"kind": "serial", "port": "/dev/ttyUSB1", "baud": 921600}
    assert config.rig.hardware["slave"] == {"bind_host": "127.0.0.1", "host": "localhost", "port": 47700}


@pytest.mark.parametrize("flag, value, problem", [
    ("--slave", "robot-pc", "is not HOST:PORT"),
    ("--slave", ":47600", "is not HOST:PORT"),
    ("--slave", "robot-pc:http", "is not a number"),
    ("--sensor", "serial", "is not one of udp | serial:PORT | usb[:VID:PID]"),
    ("--sensor", "bluetooth:hci0", "is not one of"),
    ("--backend", "ethercat", "invalid choice"),
])
def test_malformed_flags_are_usage_errors(capsys, flag, value, problem):
    with pytest.raises(SystemExit) as exit_:
        main(["run", flag, value])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"error: argument {flag}" in err and problem in err and "Traceback" not in err


def test_inconsistent_or_out_of_range_flags_are_reported_before_anything_starts(tmp_path, capsys):
    assert main(["run", "--backend", "sim", "--sensor", "serial:/dev/ttyUSB0"]) == 2
    assert capsys.readouterr().err == "error: --sensor: only the real rig (--backend udp) has these devices\n"
    assert main(["run", "--slave", "127.0.0.1:70000"]) == 2
    assert capsys.readouterr().err.startswith(f"error: {COMMAND_LINE}: hardware.slave.port: must be within")
    f = _write(tmp_path, '[rig]\nbackend = "udp"\n')
    assert main(["--config", str(f), "simulate"]) == 2
    assert "simulate palpates the simulated rig, not 'udp'" in capsys.readouterr().err


def test_the_crtk_backend_without_cyclone_dds_says_how_to_get_it(monkeypatch, capsys):
    import sys

    for name in [m for m in sys.modules if m == "cyclonedds" or m.startswith(("cyclonedds.", "hardware.crtk"))]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "cyclonedds", None)  # what an install without the crtk extra finds
    assert main(["run", "--backend", "crtk", "--arm", "PSM1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "pip install 'palpation-console[crtk]'" in err and err.count("\n") == 1
