"""`palpation-console` / `python -m app`: the console and its headless commands."""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
from pathlib import Path

from app import process
from app.display import display_problem

# Imports stop at the standard library here (app.process's too), so ``--help`` and a mistyped flag answer at
# once, and another project's package found in place of one of ours is told before anything is imported from
# it (stray_packages); each command imports what it needs (Qt, numpy, the tissue model) when it runs.
DISTRIBUTION = "palpation-console"
# The top-level packages the distribution installs, the floors of docs/architecture.md.
PACKAGES = ("app", "widgets", "session", "control", "hardware", "tissue")

BACKEND_NAMES = ("sim", "udp", "crtk")  # app.rigs.BACKENDS, named without importing the backends

SENSOR_FLAG = "udp | serial:PORT | usb[:VID:PID]"
CALIBRATION_HELP = ("the tactile array's calibration file (palpation-console calibrate), taken out of every frame "
                    "and recorded in the session; overrides [rig] calibration")


def slave_address(text: str) -> dict:
    """``--slave HOST:PORT`` as a [hardware.slave] override (the port's range is checked with the config)."""
    host, sep, port = text.rpartition(":")
    host = host.removeprefix("[").removesuffix("]")  # [::1]:47600
    if not sep or not host:
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST:PORT (e.g. 127.0.0.1:47600)")
    try:
        return {"host": host, "port": int(port)}
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: the port {port!r} is not a number") from None


def sensor_choice(text: str) -> dict:
    """``--sensor`` as a [hardware.sensor] override: where the tactile array's frames come from."""
    kind, _, where = text.partition(":")
    if kind == "udp" and not where:
        return {"kind": "udp"}
    if kind == "serial" and where:
        return {"kind": "serial", "port": where}
    if kind == "usb":
        return {"kind": "usb", "vid_pid": where} if where else {"kind": "usb"}
    raise argparse.ArgumentTypeError(f"{text!r} is not one of {SENSOR_FLAG} (e.g. serial:/dev/ttyACM0)")


def seconds(text: str) -> float:
    """A duration option: a finite number of seconds, more than none and at most a day (nan was taken, and
    a screenshot never came, a simulation never ended)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not 0.0 < value <= 86400.0:
        raise argparse.ArgumentTypeError(f"must be more than 0 and at most 86400 s (a day), got {text}")
    return value


def config_overrides(args) -> dict:
    """The command line's flags as overrides of the configuration files' keys."""
    from hardware.settings import ConfigError

    overrides: dict = {}
    if getattr(args, "phantom", None):
        overrides.setdefault("rig", {})["phantom"] = args.phantom
    if getattr(args, "seed", None) is not None:
        overrides.setdefault("rig", {})["seed"] = args.seed
    if getattr(args, "calibration", None) is not None:
        overrides.setdefault("rig", {})["calibration"] = str(args.calibration.resolve())
    hardware = {name: value for name, value in (("slave", getattr(args, "slave", None)),
                                                ("sensor", getattr(args, "sensor", None))) if value is not None}
    backend = getattr(args, "backend", None)
    arm = getattr(args, "arm", None)
    if arm is not None:
        if backend != "crtk":
            raise ConfigError("--arm", "names the arm of the CRTK rig: give --backend crtk with it")
        if "slave" in hardware:
            raise ConfigError("--slave", "is the UDP link's; the CRTK rig's arm is named by --arm")
        hardware["slave"] = {"arm": arm}
    publish = getattr(args, "publish", None)
    if publish is not None:
        if backend != "crtk":
            raise ConfigError("--publish" if publish else "--no-publish",
                              "is about the CRTK rig's ROS 2 bus: give --backend crtk with it")
        hardware["bus"] = {"publish": publish}
    if hardware:
        if backend == "sim":
            flags = " and ".join(f"--{name}" for name in hardware)
            raise ConfigError(flags, "only the real rig (--backend udp) has these devices")
        overrides["hardware"] = hardware
        if backend != "crtk":
            backend = "udp"  # naming a device means driving it
    if backend is not None:
        overrides.setdefault("rig", {})["backend"] = backend
    return overrides


def _config(args):
    from app.config import load_config

    return load_config(args.config, config_overrides(args))


def stray_packages(find_spec=importlib.util.find_spec) -> str:
    """'' when the six top-level packages come from the folder this one is in, else which comes from where.

    Their names are generic: another project's ``session`` or ``tissue`` earlier on the path (PYTHONPATH, a
    package installed in another site folder) would be imported in place of ours. ``find_spec`` locates a
    package without importing it. A stray ``app`` cannot be told here: this code would not be what runs."""
    home = os.path.realpath(Path(__file__).parents[1])
    strays = []
    for name in PACKAGES:
        spec = find_spec(name)
        if spec is None:
            strays.append(f"{name} is missing")
            continue
        if spec.submodule_search_locations is not None:  # a package; a namespace package may have several
            folders = {os.path.dirname(os.path.realpath(folder)) for folder in spec.submodule_search_locations}
        else:  # a plain module, session.py
            folders = {os.path.dirname(os.path.realpath(spec.origin or ""))}
        if folders != {home}:
            strays.append(f"{name} comes from {' and '.join(sorted(folders))}")
    if not strays:
        return ""
    return (f"{'; '.join(strays)} (the rest of {DISTRIBUTION} from {home}): it shares these names with another "
            f"project's packages; install {DISTRIBUTION} in a virtual environment of its own "
            f"(e.g. pipx install {DISTRIBUTION})")


def version() -> str:
    """The installed distribution's version, or in a source checkout run without installing it, its
    pyproject.toml's."""
    from importlib import metadata

    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        pass
    import tomllib

    try:
        with open(Path(__file__).parents[1] / "pyproject.toml", "rb") as file:
            project = tomllib.load(file).get("project", {})
    except (OSError, tomllib.TOMLDecodeError):
        project = {}
    if project.get("name") != DISTRIBUTION or "version" not in project:
        return "unknown (not installed)"
    return f"{project['version']} (not installed)"


class _Version(argparse.Action):
    """``--version``, looked up only when asked for (importlib.metadata would slow every ``--help``)."""

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{DISTRIBUTION} {version()}")
        parser.exit()


def cmd_run(args) -> int:
    from app.gui import run_gui

    problem = display_problem()
    if args.screenshot is not None and not Path(args.screenshot).resolve().parent.is_dir():
        problem = f"--screenshot {args.screenshot}: the folder {Path(args.screenshot).resolve().parent} does not exist"
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    # the first use of a phantom precomputes its tissue model: run_gui shows it in the console
    return run_gui(_config(args), screenshot=args.screenshot, screenshot_after_s=args.screenshot_after_s)


def cmd_simulate(args) -> int:
    from app.simulate import simulate

    return simulate(_config(args), max_time_s=args.max_time_s, verbose=args.verbose, record=not args.no_record)


def _review(argv: list[str]) -> int:
    from app.session_commands import review_main

    return review_main(argv)


def _stitch(argv: list[str]) -> int:
    from app.session_commands import stitch_main

    return stitch_main(argv)


def _export(argv: list[str]) -> int:
    from app.session_commands import export_main

    return export_main(argv)


def _slave(argv: list[str]) -> int:
    from app.slave import slave_main

    return slave_main(argv)


def _devices(argv: list[str]) -> int:
    from app.devices import main as devices_main

    return devices_main(argv)


def _calibrate(argv: list[str]) -> int:
    from app.calibrate import calibrate_main

    return calibrate_main(argv)


def _study(argv: list[str]) -> int:
    from app.study import study_main

    return study_main(argv)


# name: (entry point, help, what --config gives it; None: it reads no configuration). Each entry imports its
# command when it runs, so that --help stays quick, and imports it by name, so that the contracts see it.
DELEGATED = {
    "review": (_review, "open a recorded session read-only in the reviewer", None),
    "stitch": (_stitch, "stitch a session into whole-tissue maps and find the tumours", None),
    "export": (_export, "write a session's ticks, frames and levels as tidy CSV or Parquet tables, or as a "
                        "rosbag2-compatible MCAP", None),
    "slave": (_slave, "run the slave side of the UDP master/slave link", "its simulated robot's [sim] table"),
    "devices": (_devices, "list the tactile sensors, masters and links this machine can see",
                "also probe the [hardware] devices it names"),
    "calibrate": (_calibrate, "measure the tactile array's element sensitivities on a uniform reference",
                  "the [sim] settings of the simulated array it presses"),
    "study": (_study, "validate tumour detection and depth on seeded simulated phantoms",
              "the [control] and [sim] settings every phantom is palpated with"),
}


def build_parser() -> argparse.ArgumentParser:
    config_help = "a TOML file overriding the shipped defaults (palpation-console's app/default.toml)"
    parser = argparse.ArgumentParser(prog="palpation-console", description=__doc__)
    parser.add_argument("--version", action=_Version, nargs=0, help="print the version and exit")
    parser.add_argument("--config", type=Path, help=config_help)
    # the same option after the subcommand (``simulate --config FILE``); SUPPRESS keeps a value given before it
    config_after = argparse.ArgumentParser(add_help=False)
    config_after.add_argument("--config", type=Path, default=argparse.SUPPRESS, help=config_help)
    sub = parser.add_subparsers(dest="command")

    run = sub.add_parser("run", help="open the console (default)", parents=[config_after])
    run.add_argument("--phantom", help="simulated rig: phantom name or TOML file")
    real = run.add_argument_group("real hardware", "override [rig] backend and the [hardware] tables of the "
                                  "config (see docs/hardware.md); --slave or --sensor imply --backend udp")
    real.add_argument("--backend", choices=BACKEND_NAMES, help="sim: the simulated rig (default); "
                      "udp: the robot behind `palpation-console slave`; crtk: a CRTK / ROS 2 arm (dVRK) over DDS")
    real.add_argument("--arm", metavar="NAME", help="crtk: the arm's ROS namespace (e.g. PSM1; default: "
                      "[hardware.slave] arm)")
    real.add_argument("--publish", action=argparse.BooleanOptionalAction, default=None,
                      help="crtk: publish the tactile frames, force, setpoint and phase as ROS 2 topics "
                      "(/palpation/...) on the arm's DDS domain, for `ros2 bag record` (default: [hardware.bus] "
                      "publish, true)")
    real.add_argument("--slave", metavar="HOST:PORT", type=slave_address,
                      help="where `palpation-console slave` listens (default 127.0.0.1:47600)")
    real.add_argument("--sensor", metavar="KIND", type=sensor_choice,
                      help=f"the tactile array: {SENSOR_FLAG}; udp (default) is forwarded by the slave; "
                      "other [hardware.sensor] keys of the config (calibration, baud, ...) are kept")
    run.add_argument("--calibration", metavar="FILE", type=Path, help=CALIBRATION_HELP)
    run.add_argument("--screenshot", metavar="PNG", help="save the window to PNG after --screenshot-after-s, then quit")
    run.add_argument("--screenshot-after-s", type=seconds, default=10.0, metavar="SECONDS",
                     help="how long after the window opens --screenshot is taken (default 10)")
    run.set_defaults(func=cmd_run)

    sim = sub.add_parser("simulate", help="palpate a phantom headlessly, print every recorded level and record "
                         "the session", parents=[config_after])
    sim.add_argument("--phantom", help="a shipped phantom's name (flat, uneven) or a TOML file")
    sim.add_argument("--seed", type=int, help="random seed of the simulated sensor")
    sim.add_argument("--calibration", metavar="FILE", type=Path, help=CALIBRATION_HELP)
    sim.add_argument("--max-time-s", type=seconds, default=600.0, help="give up after this much simulated time")
    sim.add_argument("-v", "--verbose", action="store_true", help="also print notices and refused commands")
    sim.add_argument("--no-record", action="store_true",
                     help="do not record the session (by default it goes to a new file in the sessions folder, "
                          "for stitch and review)")
    sim.set_defaults(func=cmd_simulate)

    for name, (_, help_text, _config) in DELEGATED.items():
        sub.add_parser(name, help=help_text, add_help=False)  # listed in --help; main() hands them their argv
    return parser


def _delegated(argv: list[str]) -> tuple[str, list[str]] | None:
    """(subcommand, its argv) when ``argv`` names a delegated subcommand, with a ``--config FILE`` given
    before it moved after it, where the subcommand's own parser reads it (one given after it wins)."""
    before: list[str] = []
    rest = argv
    if rest and rest[0] == "--config" and len(rest) >= 2:
        before, rest = rest[:2], rest[2:]
    elif rest and rest[0].startswith("--config="):
        before, rest = rest[:1], rest[1:]
    if not rest or rest[0] not in DELEGATED:
        return None
    return rest[0], [*before, *rest[1:]]


def main(argv: list[str] | None = None) -> int:
    stray = stray_packages()
    if stray:
        print(f"error: {stray}", file=sys.stderr)
        return 2
    # before anything imports numpy: for this process and every process it starts
    process.keep_numpy_off_huge_pages()
    process.limit_blas_threads()
    argv = list(sys.argv[1:] if argv is None else argv)
    delegated = _delegated(argv)
    if delegated is not None:  # these subcommands own their argparse
        command, sub_argv = delegated
        entry, _, config_use = DELEGATED[command]
        if config_use is None and any(a == "--config" or a.startswith("--config=") for a in sub_argv):
            print(f"error: {command} reads no configuration file: it works from what the session recorded and "
                  f"its own options (palpation-console {command} --help)", file=sys.stderr)
            return 2
        return entry(sub_argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        args = parser.parse_args([*argv, "run"])
    from hardware.interfaces import DeviceError
    from hardware.settings import ConfigError
    from tissue.phantom import PhantomError

    try:
        return args.func(args)
    except (ConfigError, PhantomError, DeviceError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
