"""Contact onset, L0, dL and Eq. 1 stiffness."""

import math

import numpy as np
import pytest

from control.analysis import (
    NOISE_MIN_FRAMES,
    AirNoise,
    ContactTracker,
    PoseHistory,
    contact_thresholds,
    element_analysis,
)
from control.config import ContactSettings

A = 4e-6
SHAPE = (4, 15)


def test_eq1_numbers():
    contact = ContactSettings(table_height_m=0.0)
    p = np.full(SHAPE, 20e3)  # F = 0.08 N per element
    onset = np.full(SHAPE, 0.025)  # L0 = 25 mm
    # dL = 2.5 mm
    L0, dL, E, in_contact, depth = element_analysis(p, onset, 0.0225, contact.onset_threshold_pa, contact, A)
    assert in_contact.all()
    np.testing.assert_allclose(L0, 0.025)
    np.testing.assert_allclose(dL, 0.0025)
    # E = F L0 / (A dL) = 0.08 * 0.025 / (4e-6 * 0.0025) = 200 kPa
    np.testing.assert_allclose(E, 200e3)
    assert depth == pytest.approx(0.0025)


def test_elements_never_in_contact_are_nan_not_inf():
    contact = ContactSettings()
    p = np.zeros(SHAPE)
    p[1, 3] = 5e3
    onset = np.full(SHAPE, np.nan)
    onset[1, 3] = 0.025
    onset[2, 3] = 0.0201  # known onset but dL below min_indentation: noise-dominated, NaN
    p[2, 3] = 5e3
    with np.errstate(all="raise"):
        _, dL, E, in_contact, depth = element_analysis(p, onset, 0.020, contact.onset_threshold_pa, contact, A)
    assert np.isfinite(E[1, 3]) and E[1, 3] == pytest.approx(5e3 * 0.025 / 0.005)
    assert np.isnan(E[2, 3])
    assert np.isnan(np.delete(E.ravel(), [1 * 15 + 3])).all()
    assert not np.isinf(E).any()
    assert depth == pytest.approx((0.005 + 0.0001) / 2)


def test_a_reading_left_while_the_face_is_lifted_above_the_surface_is_no_negative_depth():
    """issue 50: the creep of the array kept elements reading while retracting, and the depth read -8.2 mm."""
    contact = ContactSettings(table_height_m=0.0)
    onset = np.full(SHAPE, 0.025)
    _, dL, E, in_contact, depth = element_analysis(np.full(SHAPE, 2e3), onset, 0.033, contact.onset_threshold_pa,
                                                   contact, A)
    assert in_contact.all() and depth == 0.0 and np.isnan(E).all()
    onset[0] = 0.034  # one row still under the face: the depth is its share, never less than zero
    _, _, _, _, depth = element_analysis(np.full(SHAPE, 2e3), onset, 0.033, contact.onset_threshold_pa, contact, A)
    assert depth == pytest.approx(0.001 * 15 / 60)


def test_no_contact_gives_nan_depth():
    nowhere = np.full(SHAPE, np.nan)
    _, _, E, in_contact, depth = element_analysis(np.zeros(SHAPE), nowhere, 0.02, 300.0, ContactSettings(), A)
    assert np.isnan(depth) and np.isnan(E).all() and not in_contact.any()


def test_onset_extrapolated_back_to_zero_pressure_on_a_linear_rise():
    contact = ContactSettings(onset_threshold_pa=300, confirm_threshold_pa=900)
    tracker = ContactTracker(contact, SHAPE)
    surface = np.linspace(0.024, 0.026, 60).reshape(SHAPE)  # a sloping surface: onsets differ per element
    slope = 800e3  # Pa per m of indentation
    for z in np.arange(0.030, 0.018, -0.00037):  # frames every 0.37 mm of descent
        tracker.update(slope * np.clip(surface - z, 0, None), z)
    np.testing.assert_allclose(tracker.onset_height_m, surface, atol=1e-9)


def test_the_top_is_the_highest_onset_until_the_summed_reading_places_the_first_touch_higher():
    """What the indentation ceiling and the ramp's cap by depth count from: -inf before any touch, the highest
    onset once one is tracked even while the summed reading has not risen through both of its steps (NaN),
    and the summed reading's first touch where that lies higher."""
    tracker = ContactTracker(ContactSettings(onset_threshold_pa=300, confirm_threshold_pa=900), SHAPE)
    assert tracker.top_m() == -math.inf
    tracker.onset_height_m[0, 0] = 0.025
    assert math.isnan(tracker.first_touch_m()) and tracker.top_m() == 0.025
    tracker._sum_heights_m[:] = (0.0262, 0.0258)  # risen through both steps: placed above the onsets
    assert tracker.first_touch_m() > 0.0262 and tracker.top_m() == tracker.first_touch_m()


def test_element_in_contact_before_tracking_stays_unknown():
    tracker = ContactTracker(ContactSettings(), SHAPE)
    p = np.zeros(SHAPE)
    p[0, 0] = 2e3
    tracker.update(p, 0.03)
    tracker.update(p * 2, 0.029)
    assert np.isnan(tracker.onset_height_m[0, 0]) and tracker.blind[0, 0]


@pytest.mark.parametrize("residual_pa, known", [(2800.0, True), (450.0, True), (600.0, False)])
def test_a_creep_residual_decaying_in_air_does_not_hide_the_onset(residual_pa, known):
    """After a press near saturation an element reads a few % of it in air, decaying over seconds (the
    simulated sensor's creep: 3 %, 2 s). Once it has fallen below p_on or to half, it was air, and the
    element's onset is tracked on its reading above that floor; one that has not fallen so far by contact
    stays unknown, as it would if it had been pressing tissue all along."""
    tracker = ContactTracker(ContactSettings(onset_threshold_pa=300, confirm_threshold_pa=900), SHAPE)
    surface, slope, speed = 0.025, 800e3, 0.004  # 4 mm/s descent from 33 mm
    tau = 2.0 if residual_pa != 600.0 else 1e9  # a residual that does not decay is indistinguishable
    for t in np.arange(0.0, 3.0, 0.01):
        z = 0.033 - speed * t
        p = slope * np.clip(surface - z, 0, None) * np.ones(SHAPE)
        p[1, 3] += residual_pa * np.exp(-t / tau)
        tracker.update(p, z)
    assert np.isclose(tracker.onset_height_m[0, 0], surface, atol=1e-9)
    if known:
        # the residual decays by up to ~12 Pa over a 0.04 mm frame step: a few um off
        assert tracker.onset_height_m[1, 3] == pytest.approx(surface, abs=20e-6)
    else:
        assert np.isnan(tracker.onset_height_m[1, 3]) and tracker.blind[1, 3]


def test_pose_history_interpolates_at_the_frames_timestamp():
    h = PoseHistory(0.1, 1000)
    for k in range(300):
        h.push(k * 1e-3, (0.0, 0.0, 0.03 - k * 1e-5))
    assert h.at(0.2505)[2] == pytest.approx(0.03 - 250.5e-5)
    assert h.at(-1.0)[2] == pytest.approx(0.03 - 198e-5)  # clamped to the oldest sample held
    with pytest.raises(LookupError):
        PoseHistory(0.1, 1000).at(0.0)


def test_a_noise_blip_is_not_taken_for_contact():
    tracker = ContactTracker(ContactSettings(onset_threshold_pa=300, confirm_threshold_pa=900), SHAPE)
    p = np.zeros(SHAPE)
    tracker.update(p, 0.030)
    p[2, 7] = 400.0  # one noisy frame above p_on
    tracker.update(p, 0.0299)
    p[2, 7] = 0.0
    tracker.update(p, 0.0298)
    assert np.isnan(tracker.onset_height_m).all()


def test_air_noise_is_each_elements_own_never_below_the_faces_median():
    rng = np.random.default_rng(3)
    sigma = np.full(SHAPE, 200.0)
    sigma[1, 4] = 1000.0
    noise = AirNoise(SHAPE)
    drift = np.linspace(0.0, 5e3, 300)  # a creep residual decaying, the probe lowered onto nothing
    for k in range(300):
        assert (noise.sigma_pa() is None) == (k < NOISE_MIN_FRAMES)
        frame = drift[k] + sigma * rng.standard_normal(SHAPE)
        if k % 40 == 0:
            frame += 20e3  # a frame pressing something now and then
        noise.push(frame)
    estimate = noise.sigma_pa()
    assert np.median(estimate) == pytest.approx(200.0, rel=0.05)
    # the noisy element keeps its own; the half of the face whose own estimate fell short sits on the floor
    assert estimate[1, 4] == pytest.approx(1000.0, rel=0.2) and np.count_nonzero(estimate == estimate.min()) >= 30
    onset, confirm = contact_thresholds(ContactSettings(onset_threshold_pa=300, confirm_threshold_pa=900),
                                        estimate)
    assert onset[1, 4] == 5 * estimate[1, 4] and onset.min() == 5 * estimate.min()
    np.testing.assert_allclose(confirm, 3 * onset)
    quiet, _ = contact_thresholds(ContactSettings(onset_threshold_pa=300, confirm_threshold_pa=900),
                                  np.full(SHAPE, 10.0))
    assert (quiet == 300).all()  # never below the configured thresholds


def test_air_noise_of_a_converters_steps_is_not_rounded_to_them():
    """The simulated sensor's 12-bit converter reads in 24.4 Pa steps. The median absolute deviation of such
    readings moves in whole steps: at its default 50 Pa of noise it gave some elements 77 Pa for 51 Pa, and
    at 60 Pa every element 51 or 77 Pa."""
    rng = np.random.default_rng(5)
    step = 100e3 / 4096
    noise = AirNoise(SHAPE)
    for _ in range(256):
        noise.push(np.round((500.0 + 60.0 * rng.standard_normal(SHAPE)) / step) * step)
    expected = np.hypot(60.0, step / np.sqrt(12.0))  # the rounding is noise too
    np.testing.assert_allclose(noise.sigma_pa(), expected, rtol=0.15)
