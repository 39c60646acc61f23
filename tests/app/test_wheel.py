"""The wheel, built from a copy of the checkout, installed in a new virtual environment and run from elsewhere:
it holds every module and resource of the six packages, and the installed console runs without the checkout."""

import os
import shutil
import site
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from app.cli import PACKAGES

ROOT = Path(__file__).resolve().parents[2]
# what a checkout holds beside its sources, none of which a build may take
NOT_SOURCES = shutil.ignore_patterns(".git", ".venv", "build", "dist", "*.egg-info", "__pycache__", "*.pyc",
                                     ".pytest_cache", ".hypothesis", ".grimp_cache", ".import_linter_cache")

pytestmark = pytest.mark.slow


def _run(command, **kwargs) -> subprocess.CompletedProcess:
    done = subprocess.run(command, capture_output=True, text=True, timeout=100, **kwargs)
    assert done.returncode == 0, f"{command}: {done.stdout}{done.stderr}"
    return done


def test_the_wheel_installs_and_runs_outside_the_checkout(tmp_path):
    # A copy: setuptools builds in the source folder's build/, where files of an earlier build would be taken.
    source = tmp_path / "source"
    shutil.copytree(ROOT, source, ignore=NOT_SOURCES)
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path / "dist"), str(source)])
    (wheel,) = (tmp_path / "dist").glob("palpation_console-*.whl")
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]

    names = set(zipfile.ZipFile(wheel).namelist())
    dist_info = f"palpation_console-{version}.dist-info"
    shipped = {path.relative_to(source).as_posix() for name in PACKAGES for path in (source / name).rglob("*")
               if path.is_file()}
    assert shipped - names == set(), "files of the packages missing from the wheel"
    assert {name.split("/")[0] for name in names} == {*PACKAGES, dist_info}
    metadata = zipfile.ZipFile(wheel).read(f"{dist_info}/METADATA").decode()
    assert "License-Expression: MIT" in metadata and f"{dist_info}/licenses/LICENSE" in names

    # A new environment with the wheel alone installed in it. Its dependencies are the ones this suite runs
    # with: a .pth file adds the site folders of this interpreter after its own. That adds their folders only
    # (a .pth file in a folder so added is not read), so the editable install of the checkout found there
    # (its finder is started by such a .pth file) is never active, and the wheel's packages, in the new
    # environment's own site folder, come first. Installing the dependencies from the index instead would
    # take minutes and the network; --system-site-packages would show the base interpreter's, not these.
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)])
    python = venv / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q", str(wheel)])
    own_site = _run([str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"]).stdout.strip()
    (Path(own_site) / "dependencies.pth").write_text("".join(f"{folder}\n" for folder in site.getsitepackages()))

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "PALPATION_", "VIRTUAL_ENV"))}
    env.update(PALPATION_DATA_DIR=str(tmp_path / "data"), PALPATION_CACHE_DIR=str(tmp_path / "cache"),
               QT_QPA_PLATFORM="offscreen")
    # the default phantom's tissue model, which the suite's session fixture computed: a copy, so that the
    # installed console finds it in its own cache and not a minute of precompute
    shutil.copytree(os.environ["PALPATION_CACHE_DIR"], tmp_path / "cache", ignore=shutil.ignore_patterns("*.lock"))
    console = str(venv / "bin" / "palpation-console")

    assert _run([console, "--version"], cwd=elsewhere, env=env).stdout == f"palpation-console {version}\n"
    where = _run([str(python), "-c", "import app.config, session.depth, tissue.phantom; print(app.config.__file__); "
                  "print(app.config.DEFAULT_CONFIG); print(session.depth.LIBRARY_PATH); "
                  "print(tissue.phantom.PHANTOM_DIR)"], cwd=elsewhere, env=env).stdout.split()
    for path in map(Path, where):
        assert path.is_relative_to(own_site) and path.exists(), path

    done = subprocess.run([console, "simulate", "--max-time-s", "2"], cwd=elsewhere, env=env,
                          capture_output=True, text=True, timeout=100)
    # two seconds of simulated time are too few to finish: it says so, with the session recorded until then
    assert "had not finished after 2 s of simulated time" in done.stderr, done.stderr
    (session,) = (tmp_path / "data" / "sessions").glob("*.h5")
    assert f"Session recorded: {session}" in done.stdout
    assert done.returncode == 1
