"""A real session, recorded once for the whole package: the simulated rig palpating three areas of the
paper's flat phantom (the first two overlap; tumours under the first and the third), ramp 0.5-1.5 N.

The tissue is the Winkler model, named explicitly: it is fast, and what these tests check (recording,
stitching, detection) must not move when the simulator's default tissue model changes. The finite-element
physics of the flat field does not describe a Winkler bed, so detection here takes the face's pattern from
a reference palpation of the same phantom without its tumours, as a lab would.

The depth model's finite-element solves (``solves``) are the test's own: quick, counted, held when it asks."""

from __future__ import annotations

import threading
import tomllib

import numpy as np
import pytest
import tomli_w

from app.config import load_config
from app.recording import record_simulation
from hardware.interfaces import TactileConstraints
from hardware.sim.rig import build_sim_rig
from session import depth
from tissue.phantom import PHANTOM_DIR, load_phantom
from tissue.winkler import WinklerTissue

REGIONS_XY_M = ((0.012, 0.015), (0.018, 0.015), (0.036, 0.015))
RAMP = {"force_min_N": 0.5, "force_max_N": 1.5, "force_step_N": 0.5}


def _phantom_file(folder, name: str, with_tumours: bool):
    """The paper's flat phantom with only the three areas of :data:`REGIONS_XY_M`, as a file in ``folder``."""
    phantom = tomllib.loads((PHANTOM_DIR / "flat.toml").read_text(encoding="utf-8"))
    phantom["phantom"]["regions"] = [{"centre_xy_m": list(xy)} for xy in REGIONS_XY_M]
    if not with_tumours:
        phantom["phantom"].pop("inclusions", None)
    phantom_path = folder / f"{name}.toml"
    phantom_path.write_text(tomli_w.dumps(phantom), encoding="utf-8")
    return phantom_path


def _record(folder, name: str, with_tumours: bool):
    phantom_path = _phantom_file(folder, name, with_tumours)
    config = load_config(None, {"control": {"ramp": RAMP}, "rig": {"phantom": str(phantom_path)}})
    three_areas = load_phantom(phantom_path)
    rig = build_sim_rig(three_areas, tissue=WinklerTissue(three_areas, TactileConstraints()))
    path = folder / f"{name}.h5"
    status = record_simulation(path, config, rig=rig, max_time_s=120.0)
    return path, status


@pytest.fixture(scope="session")
def recorded(tmp_path_factory):
    """(path of the session file, the recorder's final status)."""
    return _record(tmp_path_factory.mktemp("recorded"), "session", with_tumours=True)


@pytest.fixture(scope="session")
def reference_recorded(tmp_path_factory):
    """The same three areas of the same phantom without its tumours: a reference palpation."""
    return _record(tmp_path_factory.mktemp("reference"), "reference", with_tumours=False)[0]


class Solves:
    """The depth model's finite-element solves, in a cache of the test's own: counted as they start, each
    waiting for :attr:`go` (set at first: none waits) and giving a homogeneous block's forces, which are quick
    and keep what they feed defined."""

    def __init__(self):
        self.started = 0
        self.entered = threading.Event()
        self.go = threading.Event()
        self.go.set()

    def __call__(self, grid, thickness_m, inclusion, tumour_y_m=None, store=None, sides="free"):
        self.started += 1
        self.entered.set()
        assert self.go.wait(20.0)
        return np.ones(grid.face_shape)


@pytest.fixture
def solves(tmp_path, monkeypatch):
    monkeypatch.setenv("PALPATION_CACHE_DIR", str(tmp_path / "cache"))
    made = Solves()
    monkeypatch.setattr(depth, "_block_solve", made)
    yield made
    made.go.set()  # a failed test never leaves a worker waiting
