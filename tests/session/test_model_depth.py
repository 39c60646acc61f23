"""A recorded session analysed with the model-based depth (app/depth_model.py) through the one analysis.

The recording's tissue is the Winkler model (see conftest), which the finite-element library does not
describe, so only the shape of the answer is checked here; how well it covers the truth is measured by the
validation study on the continuum model (app/study.py)."""

from __future__ import annotations

import math

import numpy as np

from app.depth_model import DepthModel
from session.analysis import SessionAnalysis
from session.flatfield import Reference
from session.reader import open_session


def test_a_recorded_session_gets_model_depths_with_intervals(recorded, reference_recorded):
    with open_session(reference_recorded) as ref:
        share = np.ones(ref.levels["pressure_pa"].shape)
        reference = Reference.from_levels(ref.levels, share, np.zeros(share.shape), "tumour-free", physics=False)
    with open_session(recorded[0]) as session:
        analysis = SessionAnalysis.run(session, reference=reference, depth_model=DepthModel.for_session(session))
    assert len(analysis.tumours) == 4  # two tumours, each in both maps
    for t in analysis.tumours:
        assert 1e-3 <= t.depth_low_m <= t.depth_model_m <= t.depth_high_m <= 12e-3
    found = [m for m in analysis.matches if m.found]
    assert found and all(math.isfinite(m.depth_model_m) for m in found)
