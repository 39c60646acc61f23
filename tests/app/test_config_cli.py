"""Configuration loading and the command line's handling of bad input."""

import pytest

from app.cli import main
from app.config import load_config
from hardware.settings import ConfigError


def test_defaults_load_and_validate():
    config = load_config()
    assert config.control.ramp.n_levels == 7
    assert config.rig.backend == "sim" and config.rig.phantom == "flat"


def test_user_file_overrides_single_keys(tmp_path):
    f = tmp_path / "user.toml"
    f.write_text("[control.ramp]\nforce_max_N = 5.0\n")
    config = load_config(f)
    assert config.control.ramp.force_max_N == 5.0 and config.control.ramp.force_min_N == 1.0


@pytest.mark.parametrize(
    "text, key, problem",
    [
        ("[control.ramp]\nforce_max_N = 0.5\n", "control.ramp.force_max_N", "must be >= force_min_N"),
        ("[control.ramp]\nforce_stepN = 1\n", "control.ramp.force_stepN", "unknown key"),
        ("[control.safety]\nworkspace_min_m = [0, 0]\n", "control.safety.workspace_min_m", "three numbers"),
        ("[control.gains]\nmass_kg = [1, -1, 1]\n", "control.gains.mass_kg[1]", "must be > 0"),
        ("[robot]\nx = 1\n", "robot", "unknown section"),
        ("[rig]\nseed = 1.5\n", "rig.seed", "integer"),
        ("[control.ramp]\nforce_max_N = true\n", "control.ramp.force_max_N", "must be a number, got True"),
        ("[control\n", "user.toml", "not valid TOML"),
        # the scripted operator would begin every seek farther above the tissue than a seek may go (2.36 mm)
        ("[sim.operator]\nclearance_m = 0.003\n", "sim.operator.clearance_m", "the seek goes no deeper than 2.36 mm"),
        ("[sim.operator]\nclearance_m = 0.0015\n[control.safety]\nforce_ceiling_N = 5\n"
         "[control.ramp]\nforce_max_N = 4\n", "sim.operator.clearance_m", "goes no deeper than 0.96 mm"),
    ],
)
def test_bad_config_names_the_key_and_the_problem(tmp_path, text, key, problem):
    f = tmp_path / "user.toml"
    f.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(f)
    assert key in str(err.value) and problem in str(err.value)


def test_cli_reports_bad_input_without_a_traceback(tmp_path, capsys):
    f = tmp_path / "user.toml"
    f.write_text("[control.ramp]\nrmse_threshold_N = -1\n")
    assert main(["--config", str(f), "simulate"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "rmse_threshold_N: must be > 0" in err and "Traceback" not in err
    assert main(["simulate", "--phantom", "no-such-phantom"]) == 2
    assert "no such phantom" in capsys.readouterr().err


@pytest.mark.parametrize("make, said", [
    (lambda d: d, "is a folder, not a configuration file"),
    (lambda d: (d / "deep.toml", (d / "deep.toml").write_text("a = " + "[" * 100_000 + "]" * 100_000))[0],
     "nested too deeply"),
    (lambda d: (d / "big.toml", (d / "big.toml").write_bytes(b"#" * (2 << 20)))[0], "larger than 1024 kB"),
    (lambda d: (d / "latin.toml", (d / "latin.toml").write_bytes(b"# caf\xe9\n"))[0], "not UTF-8"),
])
def test_a_config_path_that_cannot_serve_is_one_line(tmp_path, capsys, make, said):
    # issue 14, finding 8: a folder or a 100k-deep file gave tracebacks
    assert main(["--config", str(make(tmp_path)), "simulate"]) == 2
    err = capsys.readouterr().err
    assert said in err and len(err.strip().splitlines()) == 1


def test_a_negative_seed_is_one_line(capsys):
    assert main(["simulate", "--seed", "-3"]) == 2
    assert "rig.seed: must be a whole number from 0" in capsys.readouterr().err


def test_simulate_palpates_every_region_of_the_default_phantom_to_region_done_and_records_it(capsys):
    from session.info import sessions_dir
    from session.reader import open_session

    assert main(["simulate"]) == 0
    out = capsys.readouterr().out
    assert "9 of 9 regions done, 0 problems" in out
    assert out.count("done (7 levels)") == 9
    (path,) = sessions_dir().glob("*.h5")  # issue 13: stitch and review work without the GUI
    assert f"Session recorded: {path} (63 force levels" in out
    with open_session(path) as s:
        assert len(s.levels) == 63 and s.closed_cleanly
        assert s.tissue_extent_m == (0.0, 0.072, 0.0, 0.030)  # what coverage is a share of


@pytest.fixture(scope="module")
def noisy_two_level_simulation(tmp_path_factory):
    """(what ``simulate --config FILE --no-record -v`` printed, the file, the data folder it ran with): the
    default phantom palpated once, two levels an area, with a sensor four times noisier than the default's, for
    the two tests below, which each palpated its nine areas before. Sandboxed and checked as the suite's own
    fixtures do a test (tests/conftest.py): a module's fixture runs before them."""
    import contextlib
    import io

    from tests.conftest import nothing_left_running, sandboxed

    base = tmp_path_factory.mktemp("noisy")
    config = base / "noisy.toml"
    config.write_text("[control.ramp]\nforce_max_N = 2.0\n[sim.sensor]\nnoise_std_pa = 200.0\n")
    printed = io.StringIO()
    with nothing_left_running(), sandboxed(base), contextlib.redirect_stdout(printed):
        code = main(["simulate", "--config", str(config), "--no-record", "-v"])
    assert code == 0, printed.getvalue()
    return printed.getvalue(), config, base / "data"


def test_simulate_takes_its_config_after_the_subcommand_and_can_skip_recording(noisy_two_level_simulation,
                                                                                  monkeypatch):
    from session.info import sessions_dir

    out, config, data = noisy_two_level_simulation
    assert out.count("done (2 levels)") == 9 and "Recording" not in out
    monkeypatch.setenv("PALPATION_DATA_DIR", str(data))
    assert not list(sessions_dir().glob("*.h5"))
    given = []  # given before the subcommand, the file is what simulate is handed (it palpated with it above)
    monkeypatch.setattr("app.simulate.simulate", lambda config, **options: given.append(config) or 0)
    assert main(["--config", str(config), "simulate", "--no-record"]) == 0
    assert [c.control.ramp.force_max_N for c in given] == [2.0]


def test_a_sensor_four_times_noisier_than_the_default_still_palpates_every_area(noisy_two_level_simulation):
    """The contact thresholds follow the noise the loop measures between areas: with the configured ones
    (300 / 900 Pa, 1.5 / 4.5 sigma at 200 Pa) the noise was taken for contact in air, and the indentation
    ceiling stopped the palpation in its first area."""
    out, _, _ = noisy_two_level_simulation
    assert "9 of 9 regions done, 0 problems" in out
    assert out.count("more than the configured 300 Pa onset allows for") == 9


def test_the_command_line_loads_no_heavy_module_until_a_command_runs():
    """``--help`` must answer at once: importing app.cli stops at the standard library (the time itself is
    measured by ``make bench``, cli.json)."""
    import subprocess
    import sys

    probe = ("import sys, app.cli; heavy = ('PySide6', 'pyqtgraph', 'scipy', 'h5py', 'numpy', "
             "'tissue.mechanics'); print(sorted(m for m in sys.modules if m.startswith(heavy)))")
    out = subprocess.run([sys.executable, "-c", probe], check=True, capture_output=True, text=True).stdout
    assert out.strip() == "[]"


BLAS_PROBE = """
import multiprocessing, os, sys, threadpoolctl
if sys.argv[1] == "numpy first":
    import numpy
import app.cli

def blas_threads():
    import numpy, scipy.linalg
    return sorted({i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"})

def command(argv):  # what a command, and a process it starts, run with
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        child = pool.apply(blas_threads)
    print(blas_threads(), child, os.environ["NUMPY_MADVISE_HUGEPAGE"])
    return 0

if __name__ == "__main__":
    app.cli.DELEGATED["probe"] = (command, "", None)
    sys.exit(app.cli.main(["probe"]))
"""


@pytest.mark.parametrize("loaded, given", [("numpy after", None), ("numpy first", None), ("numpy first", "2")])
def test_the_application_runs_blas_on_one_thread_unless_the_user_says_otherwise(tmp_path, loaded, given):
    """main() limits BLAS, in its process whether numpy was loaded before it or not, and in the processes it
    starts; it keeps numpy off huge pages for them all; a thread count of the user's own is left alone."""
    import os
    import subprocess
    import sys

    from app.process import BLAS_THREAD_VARIABLES

    env = {k: v for k, v in os.environ.items() if k not in (*BLAS_THREAD_VARIABLES, "NUMPY_MADVISE_HUGEPAGE")}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    (tmp_path / "probe.py").write_text(BLAS_PROBE)
    out = subprocess.run([sys.executable, str(tmp_path / "probe.py"), loaded], check=True, capture_output=True,
                         text=True, env=env, timeout=100).stdout
    # OpenBLAS takes no more threads than the process may use cores
    kept = 1 if given is None else min(int(given), len(os.sched_getaffinity(0)))
    assert out.split() == [f"[{kept}]", f"[{kept}]", "0"]


def test_the_parser_names_exactly_the_backends_the_rig_builder_knows():
    from app.cli import BACKEND_NAMES
    from app.rigs import BACKENDS

    assert sorted(BACKEND_NAMES) == sorted(BACKENDS)


def test_every_delegated_subcommand_reaches_its_own_parser(capsys):
    """`palpation-console stitch --help` (and the others) must find the function they are handed to."""
    from app.cli import DELEGATED

    for name in DELEGATED:
        try:
            code = main([name, "--help"])
        except SystemExit as stop:  # argparse's own way out, for the subcommands that let it through
            code = stop.code
        assert code == 0, name
        assert f"usage: palpation-console {name}" in capsys.readouterr().out


def test_every_subcommand_takes_config_before_or_after_it_or_says_why_not(tmp_path, capsys, monkeypatch):
    """issue 13: `--config FILE review` failed with "unrecognized arguments"; stitch and review analyse what a
    session recorded, so they say they read no configuration rather than ignore it."""
    config = tmp_path / "lab.toml"
    config.write_text('[hardware.slave]\nhost = "127.0.0.1"\nport = 9\n')
    for argv in (["--config", str(config), "stitch", "x.h5"], ["stitch", "x.h5", "--config", str(config)],
                 [f"--config={config}", "review"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "reads no configuration file" in err and len(err.strip().splitlines()) == 1, argv
    seen = []
    monkeypatch.setattr("app.devices.main", lambda argv: seen.append(argv) or 0)
    assert main(["--config", str(config), "devices", "--json"]) == 0
    assert main(["devices", "--config", str(config)]) == 0
    assert seen == [["--config", str(config), "--json"], ["--config", str(config)]]


def test_run_without_a_display_says_what_to_do_before_building_anything(monkeypatch, capsys):
    import sys

    for name in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.setattr("app.rigs.prepare_rig", lambda *_: pytest.fail("the tissue model was built first"))
    assert main(["run"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: no display to open the console on") and "xvfb-run" in err
    assert "QT_QPA_PLATFORM=offscreen" in err and err.count("\n") == 1
    monkeypatch.setenv("QT_QPA_PLATFORM", "offscreen")  # a platform chosen: Qt is left to it
    from app.display import display_problem

    assert display_problem() == ""
    monkeypatch.delenv("QT_QPA_PLATFORM")
    monkeypatch.setenv("DISPLAY", ":99")
    assert display_problem(find_library=lambda name: f"lib{name}.so.0") == ""
    # issue 50: with a display but without the library Qt's X11 platform needs, Qt aborted (exit 134)
    missing = display_problem(find_library=lambda name: None)
    assert "libxcb-cursor0" in missing and "apt-get install" in missing
    # and review says it in one line as run does, before it reads the session
    monkeypatch.delenv("DISPLAY")
    monkeypatch.setattr("app.session_commands.open_session", lambda *_: pytest.fail("read before the display"))
    assert main(["review", "some.h5"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: no display") and "xvfb-run -a palpation-console review" in err
    assert err.count("\n") == 1


@pytest.mark.parametrize("argv, said", [
    (["run", "--screenshot-after-s", "nan"], "argument --screenshot-after-s: must be more than 0"),
    (["simulate", "--max-time-s", "nan"], "argument --max-time-s: must be more than 0"),
    (["simulate", "--max-time-s", "-1"], "argument --max-time-s: must be more than 0"),
])
def test_durations_that_never_end_are_refused_in_one_line(argv, said, capsys):
    """Issue 49: nan was taken, and a screenshot never came, a simulation never ended."""
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2 and said in capsys.readouterr().err


def test_a_screenshot_into_a_missing_folder_is_refused_before_anything_runs(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("QT_QPA_PLATFORM", "offscreen")
    monkeypatch.setattr("app.rigs.prepare_rig", lambda *_: pytest.fail("the tissue model was built first"))
    assert main(["run", "--screenshot", str(tmp_path / "nowhere" / "x.png")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --screenshot ") and "does not exist" in err and err.count("\n") == 1
