"""`palpation-console devices`: the listing and probes as the command prints them."""

import json

import pytest

from app.devices import main
from hardware.usb.emulator import EmulatedBackend, UsbTactileDevice


def test_the_command_prints_recognised_devices_and_counts_the_rest(bus, capsys):
    assert main([], usb_backend=bus) == 0
    out = capsys.readouterr().out
    assert "1209:0001" in out and "256f:c62e" in out and "046d:c31c" not in out and "(1 other USB device" in out
    assert main(["--all", "--json"], usb_backend=bus) == 0
    listed = json.loads(capsys.readouterr().out)
    assert {d["address"] for d in listed["usb"]} == {"1209:0001", "256f:c62e", "046d:c31c", "256f:c635"}


def test_a_port_that_is_not_there_fails_the_command(tmp_path, capsys):
    assert main(["--probe-serial", str(tmp_path / "gone")], usb_backend=EmulatedBackend()) == 1
    assert "there is no serial port" in capsys.readouterr().out


def test_a_configuration_adds_the_devices_it_names_to_the_probes(tmp_path, capsys):
    """issue 13: `devices --config FILE` probes the sensor port and slave the console would use."""
    config = tmp_path / "lab.toml"
    gone = tmp_path / "ttyTSI"
    config.write_text(f'[hardware.sensor]\nkind = "serial"\nport = "{gone}"\nbaud = 921600\n'
                      '[hardware.slave]\nhost = "127.0.0.1"\nport = 9\n')
    assert main(["--config", str(config), "--json"], usb_backend=EmulatedBackend()) == 1
    probes = {p["address"]: p for p in json.loads(capsys.readouterr().out)["probes"]}
    assert set(probes) == {str(gone), "127.0.0.1:9"}
    assert "there is no serial port" in probes[str(gone)]["note"] and probes["127.0.0.1:9"]["role"] == ""
    own_id = EmulatedBackend(UsbTactileDevice(vendor_id=0x16C0, product_id=0x05DC))  # the lab's own USB id
    assert main([], usb_backend=own_id) == 0
    assert "16c0:05dc" not in capsys.readouterr().out  # not recognised without the configuration
    config.write_text('[hardware.sensor]\nkind = "usb"\nvid_pid = "16c0:05dc"\n')
    assert main(["--config", str(config)], usb_backend=own_id) == 0
    assert "16c0:05dc" in capsys.readouterr().out
    config.write_text('[control.ramp]\nforce_max_N = 5.0\n')  # a configuration for the simulated rig
    assert main(["--config", str(config)], usb_backend=EmulatedBackend()) == 0
    assert "names no serial port, USB id or slave" in capsys.readouterr().out
    config.write_text('[hardware.sensor]\nkind = "serial"\nport = "/dev/ttyACM0"\nbaud = 9600\n')
    assert main(["--config", str(config)], usb_backend=EmulatedBackend()) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {config}: hardware.sensor.baud") and len(err.strip().splitlines()) == 1


def test_a_baud_rate_no_port_takes_is_refused_in_one_line(capsys):
    """Issue 49: `devices --baud -1` raised pyserial's ValueError as a traceback."""
    with pytest.raises(SystemExit) as stop:
        main(["--probe-serial", "/dev/null", "--baud", "-1"], usb_backend=EmulatedBackend())
    assert stop.value.code == 2
    assert "argument --baud: must be within [1200, 12000000], got -1" in capsys.readouterr().err
