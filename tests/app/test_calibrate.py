"""The tactile array's calibration end to end (hardware/array_calibration.py, app/calibrate.py): presses on the
simulated cushion recover the realistic array's 7 % sensitivity pattern, the file is loaded by the config,
taken out of every frame and recorded in the session; bad files and wrong references are refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

from app.calibrate import calibrate_main
from app.config import load_config
from app.fastforward import FastForwardTimeout
from app.recording import record_simulation
from app.rigs import build_rig
from hardware.array_calibration import (
    GAIN_RANGE,
    ArrayCalibration,
    ArrayCalibrationError,
    CalibratedSensor,
    fit_gains,
)
from hardware.interfaces import TactileFrame
from hardware.settings import ConfigError
from session.array_calibration import calibration_from_session
from session.reader import open_session

REALISTIC = '[sim.sensor]\nmodel = "realistic"\n'


def _first_area(path, config_file=None) -> None:
    """A session of the flat phantom's first area at 1-2 N (the whole phantom would take 150 s of simulation)."""
    with pytest.raises(FastForwardTimeout):
        record_simulation(path, load_config(config_file, {"control": {"ramp": {"force_max_N": 2.0}}}),
                          max_time_s=14.0)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """The simulated procedure run once, as a user runs it: (calibration file, the session it was fitted from,
    the pattern the simulated array was made with)."""
    folder = tmp_path_factory.mktemp("calibrate")
    config = folder / "realistic.toml"
    config.write_text(REALISTIC)
    out = folder / "tsi.toml"
    with pytest.MonkeyPatch.context() as env:  # the suite's sandbox is per test: this runs before it
        env.setenv("PALPATION_DATA_DIR", str(folder / "data"))
        assert calibrate_main(["--config", str(config), "--out", str(out)]) == 0
    sessions = sorted((folder / "data" / "sessions").glob("*.h5"))
    rig = build_rig(load_config(config, {"rig": {"phantom": "cushion"}, "sim": {"tissue": "winkler"}}).rig)
    return out, sessions, rig.sensor.gain_pattern


def test_presses_on_the_cushion_recover_a_seven_percent_pattern_within_one_percent(calibrated):
    out, sessions, truth = calibrated
    assert len(sessions) == 1  # the presses are kept, as every palpation is
    cal = ArrayCalibration.load(out)
    truth = truth / truth.mean()
    assert np.std(truth) > 0.05  # the realistic array's pattern (7 % drawn), not the ideal one's 3 %
    assert np.max(np.abs(cal.gain / truth - 1.0)) < 0.01
    assert cal.presses == 6 and cal.gain.shape == (4, 15)
    assert "realistic" in cal.array and cal.source.endswith(".h5")


def _no_physics(session, progress):
    raise ValueError("not needed here")


def test_the_config_loads_it_the_frames_lose_the_pattern_and_the_session_records_it(calibrated, tmp_path, qtbot):
    out, _, truth = calibrated
    config_file = tmp_path / "console.toml"
    config_file.write_text(REALISTIC + f'[rig]\ncalibration = "{out}"\n')
    config = load_config(config_file)
    rig = build_rig(config.rig)
    assert isinstance(rig.sensor, CalibratedSensor)
    # a uniform load reads uniform through the calibration: the sensor's own frame divided by the gains
    loaded = TactileFrame(seq=1, t_s=0.0, pressure_pa=20e3 * truth / truth.mean())
    rig.sensor.inner.latest = lambda: loaded
    frame = rig.sensor.latest()
    assert np.ptp(frame.pressure_pa) / 20e3 < 0.02 and rig.sensor.latest() is frame

    path = tmp_path / "calibrated.h5"
    _first_area(path, config_file)
    with open_session(path) as session:
        assert session.array_calibration is not None
        np.testing.assert_allclose(session.array_calibration.gain, ArrayCalibration.load(out).gain)
        assert not session.warnings
    # the reviewer says so beside the file, where the analysis's own messages do not replace it
    from PySide6 import QtCore, QtWidgets

    from widgets.review import ReviewWindow

    window = ReviewWindow(settings=QtCore.QSettings(str(tmp_path / "review.ini"), QtCore.QSettings.Format.IniFormat),
                          physics={"model": _no_physics})
    qtbot.addWidget(window)
    with qtbot.waitSignal(window.analysis_done, timeout=60000):  # the reviewer's worker is done before the test ends
        assert window.open_file(path)
    info = window.findChild(QtWidgets.QLabel, "fileInfo")
    assert "array calibrated 20" in info.text() and "6 presses, 12." in info.toolTip()


def test_a_simulated_array_is_not_given_another_s_calibration(calibrated, tmp_path):
    out, _, _ = calibrated
    other = tmp_path / "other.toml"
    other.write_text(REALISTIC + f'seed = 5\n[rig]\ncalibration = "{out}"\n')
    with pytest.raises(ConfigError, match=r"made for the simulated array \(seed 0, realistic model\), this rig has "
                                          r"the simulated array \(seed 5, realistic model\)"):
        build_rig(load_config(other).rig)


def test_a_relative_path_is_beside_the_config_file(calibrated, tmp_path):
    out, _, _ = calibrated
    (tmp_path / "tsi.toml").write_text(out.read_text())
    (tmp_path / "console.toml").write_text('[rig]\ncalibration = "tsi.toml"\n')
    assert load_config(tmp_path / "console.toml").rig.calibration == str(tmp_path / "tsi.toml")


@pytest.mark.parametrize("text, problem", [
    ("", "not a Palpation Console array calibration"),
    ('format = "palpation-console-array-calibration"\nversion = 2\n', "this console reads 1"),
    ('format = "palpation-console-array-calibration"\nversion = 1\n', "damaged (no"),
    ("not = [toml", "not valid TOML"),
])
def test_a_bad_calibration_file_is_one_line_naming_the_key(tmp_path, text, problem):
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(None, {"rig": {"calibration": str(bad)}})
    assert err.value.key.endswith("rig.calibration") and problem in str(err.value) and "\n" not in str(err.value)


def test_a_file_for_another_array_or_with_a_broken_element_is_refused(calibrated, tmp_path):
    out, _, _ = calibrated
    data = ArrayCalibration.load(out).to_mapping()
    with pytest.raises(ArrayCalibrationError, match="outside 0.7-1.3"):
        ArrayCalibration.from_mapping({**data, "gain": [[2.0] * 15] * 4})
    short = ArrayCalibration.from_mapping({**data, "gain": [[1.0] * 15] * 3, "gain_sigma": [[0.0] * 15] * 3})
    with pytest.raises(ConfigError, match="3 x 15 elements, this one has 4 x 15"):
        CalibratedSensor(build_rig(load_config(None).rig).sensor, short)
    with pytest.raises(ArrayCalibrationError, match="no such calibration file"):
        ArrayCalibration.load(tmp_path / "missing.toml")


def test_a_continuum_block_is_not_a_uniform_reference(tmp_path):
    path = tmp_path / "block.h5"
    _first_area(path)
    with pytest.raises(ArrayCalibrationError, match="does not press every element alike"):
        calibration_from_session(path)
    with open_session(path) as session:
        assert session.array_calibration is None


def test_the_fit_ignores_each_press_offset_and_needs_presses_that_span_pressures():
    rng = np.random.default_rng(3)
    gain = np.exp(0.07 * rng.standard_normal((4, 15)))
    levels = np.linspace(5e3, 30e3, 6)
    readings, press = [], []
    for a in range(4):
        offset = 2e3 * rng.standard_normal((4, 15))  # each press reads as if it stood deeper or shallower
        for p in levels:
            readings.append(gain * (p + offset))
            press.append(a)
    cal = fit_gains(np.array(readings), np.array(press))
    np.testing.assert_allclose(cal.gain, gain / gain.mean(), rtol=1e-6)
    assert GAIN_RANGE[0] < cal.gain.min() and cal.presses == 4
    with pytest.raises(ArrayCalibrationError, match="usable press"):
        fit_gains(np.array(readings[:6]), np.array(press[:6]))
    flat = np.full((8, 4, 15), 10e3)
    with pytest.raises(ArrayCalibrationError, match="usable press"):
        fit_gains(flat, np.repeat([0, 1], 4))
    dead = np.array(readings)
    dead[:, 2, 7] = 0.0
    with pytest.raises(ArrayCalibrationError, match=r"row 2, column 7\) did not feel the reference"):
        fit_gains(dead, np.array(press))


def test_calibrate_refuses_options_that_do_not_go_together(tmp_path, capsys):
    assert calibrate_main(["--session", str(tmp_path / "s.h5"), "--seed", "3", "--out", str(tmp_path / "c.toml")]) == 2
    assert "--config and --seed belong to the simulated presses" in capsys.readouterr().err
    assert calibrate_main(["--session", str(tmp_path / "missing.h5"), "--out", str(tmp_path / "c.toml")]) == 2
    assert capsys.readouterr().err.startswith("error: ")
    assert not (tmp_path / "c.toml").exists()


def test_a_stuck_element_is_named_not_divided_by():
    levels = np.linspace(5e3, 30e3, 5)
    readings = np.array([np.full((4, 15), p) for _ in range(3) for p in levels])
    readings[:, 1, 4] = 12e3  # reads the same whatever the reference presses
    with pytest.raises(ArrayCalibrationError, match=r"element \(row 1, column 4\) does not follow"):
        fit_gains(readings, np.repeat([0, 1, 2], 5))
