"""The reviewer window: browse, stitch, re-analyse, timeline resolution, bad files, recent files. Read-only."""

from __future__ import annotations

import shutil
import threading
from pathlib import Path

import h5py
import numpy as np
import pytest
from PySide6 import QtCore, QtGui, QtWidgets

from app.session_commands import review_main
from control.messages import LevelRecorded
from session.detect import DetectParams
from session.flatfield import Reference
from session.reader import open_session
from session.stitch import L0Source, StitchParams
from session.synthetic import level_record, tick_rows
from session.writer import SessionRecorder
from tests.session.test_hostile_files import claiming, small_session
from tests.session.test_reader import sha256
from tests.session.test_recorder import INFO
from widgets.review import RecentSessions, ReviewWindow
from widgets.review.analysis_worker import THREAD_NAME
from widgets.tactile_map import TactileMapWidget


@pytest.fixture(autouse=True)
def _analysis_worker_ended():
    """A closed reviewer stops waiting at once, and its worker ends after the step it is in (a physics factory
    that reports no progress runs to its end): each test ends once it has, before the suite checks that nothing
    is left running."""
    yield
    for thread in threading.enumerate():
        if thread.name == THREAD_NAME:
            thread.join(60.0)
            assert not thread.is_alive(), "the reviewer's analysis worker did not end"


@pytest.fixture
def settings(tmp_path):
    return QtCore.QSettings(str(tmp_path / "review.ini"), QtCore.QSettings.Format.IniFormat)


@pytest.fixture
def window(qtbot, settings):
    w = ReviewWindow(settings=settings)
    qtbot.addWidget(w)
    w.resize(1200, 800)
    w.show()
    return w


def child(w, cls, name):
    found = w.findChild(cls, name)
    assert found is not None, name
    return found


def open_in(qtbot, w, path):
    with qtbot.waitSignal(w.session_opened, timeout=10000):
        assert w.open_file(path)


def analysed(qtbot, w, path):
    """Open ``path`` and wait for its analysis to be shown."""
    with qtbot.waitSignal(w.analysis_done, timeout=20000):
        assert w.open_file(path)


def test_browse_regions_and_levels(qtbot, window, recorded):
    path = recorded[0]
    before = sha256(path)
    open_in(qtbot, window, path)
    table = child(window, QtWidgets.QTableWidget, "regionTable")
    assert (table.rowCount(), table.columnCount()) == (3, 3)
    assert [table.horizontalHeaderItem(c).text() for c in range(3)] == ["0.5 N", "1 N", "1.5 N"]
    assert table.verticalHeaderItem(0).text().startswith("R1 (12, 15) done")
    levels = window.session.levels
    pressure = child(window, TactileMapWidget, "pressureMap")
    assert np.allclose(pressure.data_pa(), levels["pressure_pa"][0], rtol=1e-6)  # the first map, shown at once
    table.setCurrentCell(2, 1)  # third area, second level
    assert np.allclose(pressure.data_pa(), levels["pressure_pa"][7], rtol=1e-6)
    stiffness = child(window, TactileMapWidget, "stiffnessMap")
    assert np.allclose(stiffness.data_pa(), levels["stiffness_pa"][7], rtol=1e-6, equal_nan=True)
    assert "Region 3, level 2" in child(window, QtWidgets.QLabel, "recordInfo").text()
    indentation = window.findChild(QtWidgets.QWidget, "indentationMap")
    assert np.array_equal(indentation.values(), levels["dL_m"][7], equal_nan=True)
    # issue 13: dL on the TSI, in the coordinates of the maps above it (y -15..15 mm across, x -4..4 mm up)
    (y0, y1), (x0, x1) = indentation._view.viewRange()
    assert y0 < -14.5 and y1 > 14.5 and x0 < -3.8 and x1 > 3.8 and abs(y0 + y1) < 1.0 and abs(x0 + x1) < 0.5
    window.close_session()
    assert sha256(path) == before
    # ... and closing the session clears every heading and map, not only the tables
    for record_map in (pressure, stiffness):
        assert np.isnan(record_map.data_pa()).all()
        assert record_map.findChild(QtWidgets.QLabel, "maxLabel").text() == "max —"
    assert np.isnan(indentation.values()).all()
    assert child(window, QtWidgets.QLabel, "recordInfo").text() == ""
    assert window.statusBar().currentMessage() == "File > Open a session (.h5)"


@pytest.fixture(scope="module")
def reference_file(reference_recorded, tmp_path_factory):
    """The tumour-free palpation of the same areas, saved as a reference (see tests/session/conftest.py)."""
    path = tmp_path_factory.mktemp("ref") / "reference.json"
    with open_session(reference_recorded) as ref:
        share = np.ones(ref.levels["pressure_pa"].shape)
        Reference.from_levels(ref.levels, share, np.zeros(share.shape), "tumour-free", physics=False).save(path)
    return path


def test_stitched_maps_tumours_and_re_analysis(qtbot, window, recorded, reference_file):
    path = recorded[0]
    before = sha256(path)
    open_in(qtbot, window, path)
    with qtbot.waitSignal(window.analysis_done, timeout=5000):
        assert window.set_reference(reference_file)
    assert child(window, QtWidgets.QLabel, "referenceLabel").text().startswith("reference.json: 3 areas")
    window.findChild(QtWidgets.QTabWidget, "tabs").setCurrentIndex(1)
    combo = child(window, QtWidgets.QComboBox, "levelCombo")
    assert [combo.itemText(i) for i in range(combo.count())] == ["0.5 N", "1 N", "1.5 N"]
    assert combo.currentIndex() == 2  # the highest force, where most shows
    stitched_map = window.findChild(QtWidgets.QWidget, "stitchedMap")
    assert np.array_equal(stitched_map.values(), window.stitched.levels[2].stiffness_pa, equal_nan=True)
    assert stitched_map.marker_counts() == (2, 3)  # two found by the stiffness map; the phantom's three
    # issue 13: three of the nine areas are a share of the tissue, not "100 % of the grid"
    title = stitched_map.findChild(QtWidgets.QLabel).text()
    assert title.endswith("% of the tissue (72 x 30 mm) covered") and "100 %" not in title, title
    contrast_map = window.findChild(QtWidgets.QWidget, "contrastMap")  # beside it, the same map's contrast
    assert np.array_equal(contrast_map.values(), window.stitched.levels[2].extra["stiffness_contrast"],
                          equal_nan=True)
    assert contrast_map.marker_counts() == (2, 3)
    window.set_quantity("pressure_pa")
    assert np.array_equal(stitched_map.values(), window.stitched.levels[2].pressure_pa, equal_nan=True)
    window.set_quantity("stiffness_pa")
    tumours = child(window, QtWidgets.QTableWidget, "tumourTable")
    assert tumours.rowCount() == 4
    assert [tumours.item(r, 0).text() for r in range(4)] == ["stiffness", "stiffness", "force", "force"]
    headers = [tumours.horizontalHeaderItem(c).text() for c in range(tumours.columnCount())]
    assert headers[3:8] == ["Score\n(z)", "Contrast\n(%)", "First level\n(N)", "Depth, rule\n(mm)",
                            "Depth, model\n(mm, 90 %)"]
    assert float(tumours.item(0, 3).text()) > 3.0
    assert tumours.item(0, 8).text().startswith("#1, 2.0 mm deep")
    assert "of the 2 palpated tumours (of 3)" in child(window, QtWidgets.QLabel, "analysisSummary").text()
    tumours.setCurrentCell(2, 0)  # the first tumour of the force map: shown where it first appears
    assert combo.currentIndex() == 0
    assert child(window, QtWidgets.QComboBox, "quantityCombo").currentText() == "Force (pressure)"
    assert stitched_map.marker_counts() == (2, 3)
    combo.setCurrentIndex(2)

    # re-analysis from the panel, without re-recording
    with qtbot.waitSignal(window.analysis_done, timeout=5000):
        child(window, QtWidgets.QDoubleSpinBox, "accuracySpin").setValue(50.0)  # healthy tissue this scattered
    assert tumours.rowCount() == 0 and window.tumours == []
    with qtbot.waitSignal(window.analysis_done, timeout=5000):
        child(window, QtWidgets.QDoubleSpinBox, "accuracySpin").setValue(2.0)
    assert tumours.rowCount() == 4
    with qtbot.waitSignal(window.analysis_done, timeout=5000):
        child(window, QtWidgets.QDoubleSpinBox, "cellSpin").setValue(2.0)
    assert window.stitched.grid.cell_m == pytest.approx(2e-3)
    stiffness_element = window.stitched.stiffness_pa.copy()
    l0 = child(window, QtWidgets.QComboBox, "l0Combo")
    fixed = child(window, QtWidgets.QDoubleSpinBox, "l0FixedSpin")
    assert not fixed.isEnabled()
    with qtbot.waitSignal(window.analysis_done, timeout=5000):
        l0.setCurrentIndex(l0.findData("fixed"))
    assert fixed.isEnabled()
    with qtbot.waitSignal(window.analysis_done, timeout=5000):
        fixed.setValue(50.0)
    ratio = window.stitched.stiffness_pa / stiffness_element
    assert np.nanmin(ratio) > 1.8 and np.nanmax(ratio) < 2.3  # L0 doubled from about 25 mm to 50 mm
    with qtbot.waitSignal(window.analysis_done, timeout=5000):
        window.set_analysis(StitchParams(cell_m=1e-3, l0_source=L0Source.ELEMENT), DetectParams())
    assert len(window.tumours) == 4 and child(window, QtWidgets.QComboBox, "l0Combo").currentData() == "element"
    window.close_session()
    assert sha256(path) == before


def _unavailable(session, progress):
    raise ValueError("no model for this tissue")


def test_a_flat_field_physics_that_cannot_be_had_is_said_and_the_analysis_runs_without(qtbot, settings, recorded):
    w = ReviewWindow(settings=settings, physics={"model": _unavailable})
    qtbot.addWidget(w)
    with qtbot.waitSignal(w.analysis_done, timeout=10000):
        assert w.open_file(recorded[0])
    banner = child(w, QtWidgets.QLabel, "banner")
    assert "Flat-field physics 'model' unavailable: no model for this tissue" in banner.text()
    assert w.analysis is not None and "no physics" in w.analysis.flat_field
    combo = child(w, QtWidgets.QComboBox, "physicsCombo")
    assert [combo.itemText(i) for i in range(combo.count())] == ["model", "none (session baseline only)"]
    w.close_session()


def test_the_timeline_reads_every_tick_only_when_zoomed_in(qtbot, window, recorded):
    open_in(qtbot, window, recorded[0])
    timeline = window.findChild(QtWidgets.QWidget, "timeline")
    assert timeline.mode() == "overview"
    # the indentation on its own scale: the presses fill the plot, the rises between areas run off its foot
    low, high = timeline._depth.getViewBox().viewRange()[1]
    deepest = float(np.nanmax(window.session.levels["indentation_m"])) * 1e3
    assert -1.5 < low <= 0.0 and deepest < high < 1.5 * deepest
    assert timeline.points_drawn() == 2 * len(window.session.overview())
    with qtbot.waitSignal(timeline.range_loaded, timeout=5000, check_params_cb=lambda mode: mode == "full"):
        timeline.show_range(10.0, 15.0)
    assert timeline.mode() == "full"
    assert timeline.points_drawn() >= 5001  # every tick of the visible 5 s, and some either side
    with qtbot.waitSignal(timeline.range_loaded, timeout=5000, check_params_cb=lambda mode: mode == "overview"):
        timeline.show_range(0.0, 35.0)
    assert timeline.mode() == "overview"


def test_clicking_a_level_on_the_timeline_opens_it(qtbot, window, recorded):
    open_in(qtbot, window, recorded[0])
    window.findChild(QtWidgets.QTabWidget, "tabs").setCurrentIndex(1)
    timeline = window.findChild(QtWidgets.QWidget, "timeline")
    timeline.level_clicked.emit(4)
    table = child(window, QtWidgets.QTableWidget, "regionTable")
    assert (table.currentRow(), table.currentColumn()) == (1, 1)
    assert window.findChild(QtWidgets.QTabWidget, "tabs").currentIndex() == 0


def test_a_bad_file_is_explained_and_the_open_session_stays(qtbot, window, recorded, tmp_path):
    open_in(qtbot, window, recorded[0])
    bad = tmp_path / "notes.h5"
    bad.write_text("nothing to see")
    with qtbot.waitSignal(window.open_failed, timeout=5000) as blocker:
        assert not window.open_file(bad)
    assert "not an HDF5 file" in blocker.args[0]
    banner = child(window, QtWidgets.QLabel, "banner")
    assert banner.isVisible() and "Cannot open the session" in banner.text()
    assert window.session is not None and window.session.path == recorded[0]


def test_a_file_claiming_more_than_a_session_holds_or_reaching_into_another_is_explained_not_raised(
        qtbot, window, recorded, tmp_path):
    """issue 49: such files cost the reviewer gigabytes (a MemoryError out of open_file) or hung it."""
    open_in(qtbot, window, recorded[0])
    claims = claiming(tmp_path / "claims.h5", "levels", 57_616, 16)
    linked = small_session(tmp_path / "linked.h5")
    with h5py.File(linked, "r+") as f:
        del f["meta"]
        f["meta"] = h5py.ExternalLink(str(recorded[0]), "/meta")
    banner = child(window, QtWidgets.QLabel, "banner")
    for path, problem in ((claims, "/levels claims 57,616 rows (190 MB), more than a session can hold"),
                          (linked, f"/meta is a link into another file, {recorded[0]}")):
        with qtbot.waitSignal(window.open_failed, timeout=10000) as blocker:
            assert not window.open_file(path)
        assert blocker.args[0].startswith(f"{path}: ") and problem in blocker.args[0] and "\n" not in blocker.args[0]
        assert banner.isVisible() and banner.text() == f"Cannot open the session: {blocker.args[0]}"
        assert window.session is not None and window.session.path == recorded[0]


def _crashed(tmp_path) -> Path:
    """A recording of 3000 ticks and one level, as a kill -9 while recording would leave its file."""
    live = tmp_path / "live.h5"
    rec = SessionRecorder(live, INFO)
    rec.add_ticks(tick_rows(0, 3000))
    rec.add_events([LevelRecorded(1.0, level_record(0, 0, 1.0, (0.01, 0.015)))])
    assert rec.flush()
    crashed = tmp_path / "crashed.h5"
    shutil.copy(live, crashed)  # the file as a kill -9 at this instant would leave it
    rec.close()
    return crashed


def test_a_recording_that_did_not_end_cleanly_opens_with_a_warning(qtbot, window, tmp_path):
    crashed = _crashed(tmp_path)
    open_in(qtbot, window, crashed)
    banner = child(window, QtWidgets.QLabel, "banner")
    assert banner.isVisible() and "did not end cleanly" in banner.text()
    assert window.session.recovered and window.session.n_ticks == 3000 and len(window.session.levels) == 1


def test_what_the_file_said_stays_in_the_banner_beside_what_the_analysis_could_not_have(qtbot, settings, tmp_path):
    """issue 50: the reviewer showed a file's warning and replaced it at once with the flat field's."""
    crashed = _crashed(tmp_path)
    w = ReviewWindow(settings=settings, physics={"model": _unavailable})
    qtbot.addWidget(w)
    with qtbot.waitSignal(w.analysis_done, timeout=10000):
        assert w.open_file(crashed)
    text = child(w, QtWidgets.QLabel, "banner").text()
    assert "did not end cleanly" in text and "Flat-field physics 'model' unavailable" in text
    assert text.index("did not end cleanly") < text.index("unavailable")


def test_times_are_told_from_the_session_start_not_the_loop_clock(qtbot, window, tmp_path):
    """issue 13: a session recorded after the loop ran for 500 s reads from t = 0 on the timeline and in the
    record's description."""
    path = tmp_path / "late.h5"
    rec = SessionRecorder(path, INFO)
    rec.add_ticks(tick_rows(500_000, 20_000))  # loop time 500-520 s
    rec.add_events([LevelRecorded(512.0, level_record(0, 0, 1.0, (0.01, 0.015), t_s=512.0))])
    rec.close()
    open_in(qtbot, window, path)
    timeline = window.findChild(QtWidgets.QWidget, "timeline")
    t0, t1 = timeline.visible_range_s()
    assert -1.0 < t0 <= 0.0 and 19.5 < t1 < 21.0
    assert "12.00 s into the session" in child(window, QtWidgets.QLabel, "recordInfo").text()
    with qtbot.waitSignal(timeline.range_loaded, timeout=5000, check_params_cb=lambda mode: mode == "full"):
        timeline.show_range(2.0, 4.0)  # seconds into the session: loop time 502-504 s, every tick
    xs = timeline._f_measured.xData
    assert xs.min() <= 2.0 and xs.max() >= 4.0 and xs.max() < 20.5


def test_recent_files(qtbot, window, recorded, settings, tmp_path):
    open_in(qtbot, window, recorded[0])
    recent = RecentSessions(settings)
    assert recent.paths() == [recorded[0].resolve()]
    menu = QtWidgets.QMenu()
    opened = []
    recent.fill_menu(menu, opened.append)
    actions = [a for a in menu.actions() if a.data()]
    assert [a.data() for a in actions] == [str(recorded[0].resolve())]
    actions[0].trigger()
    assert opened == [recorded[0].resolve()]
    gone = tmp_path / "gone.h5"
    recent.add(gone)  # a file deleted since is not offered
    assert recent.paths() == [recorded[0].resolve()]
    recent.clear()
    assert recent.paths() == []


def test_exports_from_the_window(qtbot, window, recorded, tmp_path):
    analysed(qtbot, window, recorded[0])
    window.export_maps(tmp_path / "maps.png")
    window.export_report(tmp_path / "report.pdf")
    assert not QtGui.QImage(str(tmp_path / "maps.png")).isNull()
    assert (tmp_path / "report.pdf").read_bytes().startswith(b"%PDF")


def test_review_command(recorded, tmp_path, capsys, qapp):
    (tmp_path / "bad.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    assert review_main([str(tmp_path / "bad.h5")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "Traceback" not in err
    shot = tmp_path / "review.png"
    assert review_main([str(recorded[0]), "--screenshot", str(shot)]) == 0
    image = QtGui.QImage(str(shot))
    # headless, there is no screen to fit: the window a document wants, not the offscreen screen's 800 px
    assert (image.width(), image.height()) == (1400, 900)
    with open_session(recorded[0]) as s:
        assert s.closed_cleanly  # still untouched


def test_a_damaged_stretch_of_the_stream_is_reported_not_raised(qtbot, window, recorded, tmp_path):
    path = tmp_path / "damaged.h5"
    shutil.copy(recorded[0], path)
    with h5py.File(path, "r") as f:
        chunk = f["stream/ticks"].id.get_chunk_info(10)  # rows 10240-11263, t = 10.24-11.26 s
    with open(path, "r+b") as fh:
        fh.seek(chunk.byte_offset + 16)
        fh.write(bytes(64))
    open_in(qtbot, window, path)
    timeline = window.findChild(QtWidgets.QWidget, "timeline")
    with qtbot.waitSignal(timeline.range_loaded, timeout=5000):
        timeline.show_range(10.5, 11.0)
    info = child(window, QtWidgets.QLabel, "timelineInfo").text()
    assert info.startswith("Cannot show every tick here: the file is corrupt")
    assert "rows" in info and "/stream/ticks" in info


def test_the_whole_tissue_page_fits_a_laptop_screen(qtbot, window, recorded, reference_file):
    """Long map titles wrap: with the tumours listed, the window still fits 1280 x 800."""
    open_in(qtbot, window, recorded[0])
    with qtbot.waitSignal(window.analysis_done, timeout=5000):
        assert window.set_reference(reference_file)
    window.findChild(QtWidgets.QTabWidget, "tabs").setCurrentIndex(1)
    hint = window.minimumSizeHint()
    assert hint.width() <= 1280 and hint.height() <= 800, hint
    for name in ("stitchedMap", "contrastMap"):  # however long the title, a map can narrow
        assert window.findChild(QtWidgets.QWidget, name).minimumSizeHint().width() <= 400
    # issue 13: at 1280 x 800 the tumour table shows every column whole, without scrolling sideways
    window.resize(1280, 800)
    table = child(window, QtWidgets.QTableWidget, "tumourTable")
    qtbot.waitUntil(lambda: table.isVisible() and table.width() > 600)
    assert table.rowCount() == 4
    assert table.horizontalScrollBar().maximum() == 0
    header = table.horizontalHeader()
    for c in range(table.columnCount()):
        needed = max([header.sectionSizeFromContents(c).width()]
                     + [table.sizeHintForColumn(c)])
        assert table.columnWidth(c) >= needed, (table.horizontalHeaderItem(c).text(), table.columnWidth(c), needed)


def test_the_reviewer_is_in_the_consoles_dark_scheme_throughout(qtbot, window, recorded):
    """issue 13: the timeline was black in an otherwise light window."""
    open_in(qtbot, window, recorded[0])
    window_colour = window.palette().color(QtGui.QPalette.ColorRole.Window)
    assert window_colour.lightness() < 60
    timeline = child(window, QtWidgets.QWidget, "timelinePlots")
    assert timeline.backgroundBrush().color() == window.palette().color(QtGui.QPalette.ColorRole.Base)
    for name in ("regionTable", "tumourTable"):
        table = child(window, QtWidgets.QTableWidget, name)
        assert table.palette().color(QtGui.QPalette.ColorRole.Base).lightness() < 60
    axis_text = timeline.ci.getItem(1, 0).getAxis("bottom").textPen().color()
    assert axis_text.lightness() > 180  # light text on the dark plot


def test_quit_closes_the_reviewer(qtbot, window):
    window.show()
    qtbot.waitExposed(window)
    quit_action = window.findChild(QtGui.QAction, "quitAction")
    assert quit_action.shortcut() == QtGui.QKeySequence(QtGui.QKeySequence.StandardKey.Quit)
    quit_action.trigger()
    assert not window.isVisible()


def test_the_timeline_draws_f_d_and_f_ts_in_the_consoles_colours(qtbot):
    # issue 13: the reviewer drew F_d blue and F_ts orange, the console F_d orange and F_ts cyan
    from widgets.history_plots import HistoryPlots
    from widgets.plot_style import F_DESIRED_COLOUR, F_MEASURED_COLOUR
    from widgets.review.timeline import TimelineWidget

    timeline, history = TimelineWidget(), HistoryPlots()
    qtbot.addWidget(timeline)
    qtbot.addWidget(history)

    def rgb(curve):
        return curve.opts["pen"].color().getRgb()[:3]

    assert rgb(timeline._f_desired) == rgb(history._f_desired) == F_DESIRED_COLOUR
    assert rgb(timeline._f_measured) == rgb(history._f_measured) == F_MEASURED_COLOUR


def test_the_record_maps_open_on_their_contrast_with_the_tumours_spots_circled(qtbot, window, recorded,
                                                                             reference_file):
    open_in(qtbot, window, recorded[0])
    with qtbot.waitSignal(window.analysis_done, timeout=5000):
        assert window.set_reference(reference_file)
    stiffness = child(window, TactileMapWidget, "stiffnessMap")
    pressure = child(window, TactileMapWidget, "pressureMap")
    # the raw maps' brightest elements are the face's edge rows, so the contrast is what a reviewer sees first
    assert stiffness.contrast_view() and pressure.contrast_view()
    tumour = next(t for t in window.tumours if t.source == "stiffness")
    spot = tumour.spots[0]
    window.select_record(spot.record)
    assert child(stiffness, QtWidgets.QLabel, "maxLabel").text().endswith(" %")
    shown = window.analysis.contrasts["stiffness"].contrast[spot.record]
    rec = window.session.levels[spot.record]
    for row, col in stiffness.contrast_spots():  # circled where the spot is, on an element reading high
        x = rec["tsi_position_m"][0] + (row - 1.5) * window.session.pitch_m
        y = rec["tsi_position_m"][1] + (col - 7.0) * window.session.pitch_m
        assert np.hypot(x - spot.x_m, y - spot.y_m) <= window.session.pitch_m and shown[row, col] > 0
    assert stiffness.contrast_spots()
    child(stiffness, QtWidgets.QCheckBox, "contrastView").setChecked(False)  # the reading itself, one click away
    assert child(stiffness, QtWidgets.QLabel, "maxLabel").text().endswith(" kPa") and pressure.contrast_view()
