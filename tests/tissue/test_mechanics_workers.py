"""The tissue model's pieces computed side by side in worker processes: the same model, errors that say
what failed, and no process left behind."""

import logging
import sys

import numpy as np
import pytest

from hardware.interfaces import TactileConstraints
from tissue.mechanics import workers
from tissue.mechanics.model import ContinuumTissue, MeshSettings, precompute
from tissue.mechanics.workers import Job, WorkerError
from tissue.phantom import parse_phantom

SENSOR = TactileConstraints()
MESH = MeshSettings(spacing_m=2e-3, layers=4, top_layer_m=1e-3, drift_y_m=0.0, finite_strain=True)
PHANTOM = parse_phantom({"phantom": {
    "name": "w", "length_m": 0.024, "width_m": 0.030, "thickness_m": 0.010, "youngs_modulus_pa": 20e3,
    "poisson_ratio": 0.49, "inclusions": [{"centre_xy_m": [0.012, 0.015], "diameter_m": 0.004,
                                           "youngs_modulus_pa": 160e3, "depth_m": 0.002}]}})


def _tables(workers_n, folder, progress=None):
    return ContinuumTissue.load(PHANTOM, folder, settings=MESH, workers=workers_n, progress=progress)


def test_the_pieces_computed_in_workers_make_the_model_computed_here(tmp_path):
    reports = []
    apart = _tables(3, tmp_path / "apart", lambda f, message: reports.append((f, message)))
    here = _tables(1, tmp_path / "here")
    for z in (0.009, 0.007, 0.005):  # linear, then into the compressed layer and the finite-strain fit
        assert np.allclose(apart.element_forces_N(0.012, 0.015, z), here.element_forces_N(0.012, 0.015, z),
                           rtol=1e-9, atol=1e-12)
    assert apart.finite_strain.total_ab == pytest.approx(here.finite_strain.total_ab, rel=1e-9)
    fractions = [f for f, _ in reports]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0 and len(fractions) > 10
    # the three run at once, so each message says which it is about
    for piece in ("tables at rest: ", "compressed tables: ", "finite-strain fit: "):
        assert any(message.startswith(piece) for _, message in reports), piece
    # and what the workers computed went to the cache: loading again computes nothing
    again = _tables(3, tmp_path / "apart")
    assert again.precompute_s == apart.precompute_s


def test_an_error_in_a_worker_is_raised_here_as_it_was_raised_there():
    bad = MeshSettings(spacing_m=0.7e-3)  # does not divide the sensor's pitch
    jobs = [Job("good", "tissue.mechanics.model:precompute", (PHANTOM, MESH, SENSOR)),
            Job("bad", "tissue.mechanics.model:precompute", (PHANTOM, bad, SENSOR))]
    with pytest.raises(ValueError) as raised:
        workers.run(jobs, workers=2)
    with pytest.raises(ValueError) as here:
        precompute(PHANTOM, bad, SENSOR)
    assert str(raised.value) == str(here.value)


def test_a_worker_that_dies_is_reported_with_its_last_words(monkeypatch):
    monkeypatch.setattr(workers, "_COMMAND",
                        [sys.executable, "-c", "import sys; sys.stderr.write('out of memory\\n'); sys.exit(3)"])
    jobs = [Job(f"piece {i}", "tissue.mechanics.model:precompute", (PHANTOM, MESH, SENSOR)) for i in (1, 2)]
    with pytest.raises(WorkerError, match=r"computing the piece \d stopped with exit code 3 before its result: "
                                          r"out of memory"):
        workers.run(jobs, workers=2)


def test_without_an_interpreter_to_start_the_pieces_are_computed_here(monkeypatch, tmp_path, caplog):
    monkeypatch.setattr(workers, "_COMMAND", [str(tmp_path / "no-such-python")])
    with caplog.at_level(logging.WARNING):
        model = _tables(2, tmp_path)
    assert "could not start a worker process" in caplog.text
    assert model.element_forces_N(0.012, 0.015, 0.007).sum() > 0
