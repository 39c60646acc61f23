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
from session.info import SessionInfo
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


def test_the_live_console_gets_the_same_model_as_the_reviewer_of_its_session(recorded, reference_recorded):
    with open_session(reference_recorded) as ref:
        share = np.ones(ref.levels["pressure_pa"].shape)
        reference = Reference.from_levels(ref.levels, share, np.zeros(share.shape), "tumour-free", physics=False)
    with open_session(recorded[0]) as session:
        # what the recording was told before its first row (the live console builds its model from this)
        info = SessionInfo(config=session.config, calibration=session.calibration, rig=session.rig)
        live, offline = DepthModel.for_info(info), DepthModel.for_session(session)
        analysis = SessionAnalysis.run(session, reference=reference)
        assert analysis.tumours
        for t in analysis.tumours:
            a = live.estimate(t, session.levels, analysis.contrasts["stiffness"])
            b = offline.estimate(t, session.levels, analysis.contrasts["stiffness"])
            assert np.isfinite(a).all() and a == b
    assert live.cover is not None and live.table_height_m == offline.table_height_m
