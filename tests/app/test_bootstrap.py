"""scripts/bootstrap.sh's system packages, run against stand-ins for dpkg, apt-get, sudo and id: what it finds
missing, what it installs as root and what it asks a user without the rights to run."""

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
QT_AND_USB = ["libegl1", "libgl1", "libxkbcommon0", "libxkbcommon-x11-0", "libfontconfig1", "libdbus-1-3",
              "libxcb-cursor0", "libxcb-icccm4", "libxcb-keysyms1", "libxcb-image0", "libxcb-render-util0",
              "libxcb-shape0", "libxcb-xinerama0", "libusb-1.0-0"]

STANDINS = {
    "dpkg": 'echo amd64\n',
    # installed: the packages listed in $FAKE/installed, for amd64 only
    "dpkg-query": 'p=${@: -1}; [ "${p#*:}" = amd64 ] && grep -qxF "${p%%:*}" "$FAKE/installed" && printf "ii " '
                  '|| { echo "dpkg-query: no packages found matching $p" >&2; exit 1; }\n',
    "id": 'echo "$FAKE_UID"\n',
    "sudo": 'exit 1\n',  # a password would be asked for
    # logs its arguments; an install adds its packages to $FAKE/installed
    "apt-get": 'echo "$*" >>"$FAKE/apt.log"\n'
               '[ "$1" = install ] && shift 4 && printf "%s\\n" "$@" >>"$FAKE/installed"; true\n',
    # the venv step: far enough
    "python3": 'echo "python3 $*" >>"$FAKE/apt.log"; exit 3\n',
}


@pytest.fixture
def machine(tmp_path):
    """A copy of the script in a checkout of its own, and a bin folder of stand-ins ahead of the real ones."""
    checkout = tmp_path / "checkout"
    (checkout / "scripts").mkdir(parents=True)
    shutil.copy(ROOT / "scripts" / "bootstrap.sh", checkout / "scripts")
    for name in ("pyproject.toml", "constraints.txt"):
        shutil.copy(ROOT / name, checkout)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name, body in STANDINS.items():
        (bin_dir / name).write_text("#!/bin/bash\n" + body)
        (bin_dir / name).chmod(0o755)

    def run(mode: str, uid: int, installed: list[str]) -> subprocess.CompletedProcess:
        (tmp_path / "installed").write_text("".join(f"{name}\n" for name in installed))
        env = {"PATH": f"{bin_dir}:/usr/bin:/bin", "FAKE": str(tmp_path), "FAKE_UID": str(uid),
               "PYTHON": str(bin_dir / "python3")}
        return subprocess.run(["bash", str(checkout / "scripts" / "bootstrap.sh"), mode], env=env,
                              capture_output=True, text=True, timeout=60)

    run.log = tmp_path / "apt.log"
    run.checkout = checkout
    return run


def test_a_user_without_the_rights_is_given_the_one_command_to_run(machine):
    done = machine("test", uid=1000, installed=[p for p in QT_AND_USB if p != "libgl1"])
    assert done.returncode == 1
    assert done.stderr.splitlines()[-1] == "  sudo apt-get install -y libgl1 xvfb hdf5-tools"
    assert not machine.log.exists()  # neither apt-get nor the venv step ran
    assert not (machine.checkout / ".venv").exists()


def test_running_needs_no_hdf5_tools(machine):
    done = machine("run", uid=1000, installed=QT_AND_USB)
    assert done.stderr.splitlines()[-1] == "  sudo apt-get install -y xvfb"


def test_root_installs_what_is_missing_and_goes_on(machine):
    done = machine("test", uid=0, installed=[*QT_AND_USB, "hdf5-tools"][1:])
    assert done.returncode == 3, done.stderr  # the stand-in python3: the script reached the venv step
    assert done.stdout == "bootstrap: installing system packages: libegl1 xvfb\n"
    assert machine.log.read_text().splitlines() == [
        "update -qq", "install -y -qq --no-install-recommends libegl1 xvfb", "python3 -m venv --clear .venv"]


def test_nothing_is_installed_when_nothing_is_missing(machine):
    done = machine("test", uid=1000, installed=[*QT_AND_USB, "xvfb", "hdf5-tools"])
    assert done.returncode == 3, done.stderr
    assert machine.log.read_text().splitlines() == ["python3 -m venv --clear .venv"]


def test_it_says_how_to_call_it(machine):
    done = machine("", uid=1000, installed=[])
    assert done.returncode == 2
    assert done.stderr == "usage: scripts/bootstrap.sh run|test\n"

