"""`palpation-console slave`: the slave side of the UDP link in front of the simulated robot."""

import pytest

from app.slave import slave_main


def test_the_slave_command_runs_and_stops(capsys):
    # --duration-s only bounds how long the slave serves; the test reads its exit code and output
    exit_code = slave_main(["--port", "0", "--duration-s", "0.2", "--serial-emulator", "--no-realtime"])
    assert exit_code == 0
    out = capsys.readouterr().out
    assert "slave: listening on 127.0.0.1:" in out and "serial tactile emulator at" in out
    assert "normal priority (--no-realtime)" in out
    assert "stopped after" in out


def test_the_slave_command_refuses_to_expose_the_robot(capsys):
    exit_code = slave_main(["--bind", "0.0.0.0", "--port", "0", "--duration-s", "0.1", "--no-realtime"])
    assert exit_code == 2  # refused before serving
    assert "exposes the robot" in capsys.readouterr().err


@pytest.mark.parametrize("args, said", [
    (["--force-limit-n", "100"], "force_limit_N: must lie between 0.1 and 30"),
    (["--max-speed-m-s", "5"], "max_speed_m_s: must lie between"),
    (["--workspace-min-m", "0", "0", "0.1", "--workspace-max-m", "0.1", "0.1", "0.05"], "must exceed workspace_min_m"),
])
def test_the_slave_command_refuses_limits_of_its_own_that_make_no_sense(capsys, args, said):
    exit_code = slave_main(["--port", "0", "--duration-s", "0.1", "--no-realtime", *args])
    assert exit_code == 2
    err = capsys.readouterr().err
    assert said in err and len(err.strip().splitlines()) == 1
