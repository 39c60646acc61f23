"""What the distribution says about itself: its version, where its six packages come from, its pins."""

import os
import subprocess
import sys
import tomllib
from importlib import machinery, metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from app import cli

ROOT = Path(__file__).resolve().parents[2]


def test_version_prints_the_installed_distributions_version(capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out == f"palpation-console {metadata.version('palpation-console')}\n"


def test_a_checkout_that_is_not_installed_tells_its_pyprojects_version(monkeypatch):
    def not_installed(name):
        raise metadata.PackageNotFoundError(name)

    monkeypatch.setattr(metadata, "version", not_installed)
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert cli.version() == f"{project['version']} (not installed)"


def _specs(home: str, **elsewhere):
    """A find_spec for the six packages, each a regular package in ``home`` unless named in ``elsewhere``:
    None (not found), ("module", folder) or ("package", folder)."""

    def find_spec(name):
        kind, folder = elsewhere.get(name, ("package", home))
        if kind is None:
            return None
        if kind == "module":
            return machinery.ModuleSpec(name, None, origin=os.path.join(folder, f"{name}.py"))
        spec = machinery.ModuleSpec(name, None, origin=os.path.join(folder, name, "__init__.py"), is_package=True)
        spec.submodule_search_locations = [os.path.join(folder, name)]
        return spec

    return find_spec


def test_the_six_packages_from_one_folder_pass():
    home = os.path.realpath(Path(cli.__file__).parents[1])
    assert cli.stray_packages(_specs(home)) == ""


def test_another_projects_package_or_module_of_one_of_our_names_is_told_with_where_it_comes_from(tmp_path):
    home = os.path.realpath(Path(cli.__file__).parents[1])
    other = str(tmp_path)
    stray = cli.stray_packages(_specs(home, session=("package", other), tissue=("module", other),
                                      widgets=(None, None)))
    assert stray.startswith(f"widgets is missing; session comes from {other}; tissue comes from {other} "
                            f"(the rest of palpation-console from {home}): ")
    assert stray.endswith("install palpation-console in a virtual environment of its own "
                          "(e.g. pipx install palpation-console)")
    assert "\n" not in stray


def test_the_command_line_stops_before_importing_a_stray_package(tmp_path):
    """Another project's ``session`` ahead of ours on the path: one line, exit 2, and it is never imported."""
    other = tmp_path / "other"
    (other / "session").mkdir(parents=True)
    (other / "session" / "__init__.py").write_text("raise SystemExit('the stray session was imported')\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    env["PYTHONPATH"] = os.pathsep.join([str(other), str(ROOT)])  # ours found after it, installed or not
    done = subprocess.run([sys.executable, "-m", "app", "simulate"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert done.stdout == ""
    assert done.stderr.startswith(f"error: session comes from {os.path.realpath(other)} (the rest of ")
    assert done.stderr.count("\n") == 1


def test_every_dependency_is_pinned_within_its_range():
    """constraints.txt, which make and CI install with, names every dependency of pyproject.toml (each extra's
    too) at a version the dependency allows: pip would otherwise refuse the pins, or resolve the name afresh."""
    lines = (ROOT / "constraints.txt").read_text().splitlines()
    pins = dict(line.split("==") for line in lines if line and not line.startswith("#"))
    pins = {canonicalize_name(name): version for name, version in pins.items()}
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"].values()
    for requirement in map(Requirement, [*project["dependencies"], *(r for extra in extras for r in extra)]):
        pinned = pins.get(canonicalize_name(requirement.name))
        assert pinned is not None, f"{requirement.name} is not pinned in constraints.txt (make constraints)"
        assert requirement.specifier.contains(pinned), f"constraints.txt pins {requirement.name} {pinned}"
