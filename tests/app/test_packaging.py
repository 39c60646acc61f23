"""What the distribution says about itself."""

import tomllib
from importlib import metadata
from pathlib import Path

import pytest

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
