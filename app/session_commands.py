"""``palpation-console review`` and ``palpation-console stitch``: argument parsing and error reporting.

Both return a process exit code: 0 done, 1 an output could not be written, 2 bad input (a file that is
not a readable session, an invalid parameter). Problems are reported in one sentence on stderr, never
as a traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from session.analysis import AnalysisParams, SessionAnalysis
from session.detect import DetectError, DetectParams
from session.info import sessions_dir
from session.reader import SessionFileError, open_session
from session.stitch import L0Source, StitchError, StitchParams

EXIT_OK, EXIT_OUTPUT, EXIT_INPUT = 0, 1, 2


def add_analysis_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("analysis (re-analyse a recording without re-recording it)")
    group.add_argument("--cell-mm", type=float, default=1.0, help="grid cell size in mm (default 1)")
    group.add_argument("--threshold", type=float, default=DetectParams.threshold,
                       help="a cell is suspicious when it rises this much above the map's median "
                            "(relative: 0.2 = 20 %%, the default)")
    group.add_argument("--min-area-mm2", type=float, default=DetectParams.min_area_m2 * 1e6,
                       help="smallest suspicious spot kept, in mm² (default 8: two elements)")
    group.add_argument("--l0", choices=[s.value for s in L0Source], default=L0Source.ELEMENT.value,
                       help="where Eq. 1's initial thickness L0 comes from: each element's onset (element, "
                            "as recorded), one per region (region), or a given thickness (fixed, with --l0-mm)")
    group.add_argument("--l0-mm", type=float, help="the thickness for --l0 fixed, in mm")


def analysis_params(args) -> AnalysisParams:
    """Raises StitchError / DetectError naming the bad option."""
    stitch = StitchParams(cell_m=args.cell_mm * 1e-3, l0_source=args.l0,
                          l0_fixed_m=None if args.l0_mm is None else args.l0_mm * 1e-3)
    detect = DetectParams(threshold=args.threshold, min_area_m2=args.min_area_mm2 * 1e-6)
    return AnalysisParams(stitch, detect)


def _parse(parser: argparse.ArgumentParser, argv: list[str] | None):
    try:
        return parser.parse_args(argv), None
    except SystemExit as stop:  # --help, or a usage error argparse already printed
        return None, int(stop.code or 0)


# ---- stitch -------------------------------------------------------------------------------------------


def stitch_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="palpation-console stitch",
        description="Stitch a recorded session into whole-tissue maps per force level, find the tumours and "
                    "their depth, and export the results.")
    parser.add_argument("file", type=Path, help="a session file (.h5)")
    parser.add_argument("-o", "--output", type=Path, help="PNG with the force and stiffness maps at every level")
    parser.add_argument("--csv", type=Path, help="the maps as CSV (one row per cell and level)")
    parser.add_argument("--json", type=Path, help="the maps as JSON")
    parser.add_argument("--tumours", type=Path, help="the tumours found, as JSON")
    parser.add_argument("--report", type=Path, help="one-page report: PDF for a .pdf name, else PNG")
    add_analysis_arguments(parser)
    return parser


def _print_summary(analysis: SessionAnalysis, out) -> None:
    session, stitched, tumours = analysis.session, analysis.stitched, analysis.tumours
    forces = ", ".join(f"{f:g}" for f in stitched.level_forces_N()) or "none"
    print(f"{session.path.name}: {len(session.regions())} regions, {len(session.levels)} recorded levels "
          f"(forces {forces} N), {stitched.covered_fraction() * 100:.0f} % of the grid covered", file=out)
    for warning in session.warnings:
        print(f"  warning: {warning}", file=out)
    if not tumours:
        print("No tumour found with these parameters.", file=out)
    for t in tumours:
        depth = f"{t.depth_m * 1e3:5.2f}" if t.depth_m == t.depth_m else "  n/a"
        print(f"  {t.source:<9} x {t.x_m * 1e3:6.1f} mm  y {t.y_m * 1e3:6.1f} mm  depth {depth} mm  "
              f"first at {t.first_level_N:g} N  (+{t.peak_rise * 100:.0f} %)", file=out)
    if analysis.has_ground_truth:
        for m in analysis.matches:
            result = (f"found {m.error_xy_m * 1e3:.1f} mm away, depth estimate {m.depth_estimate_m * 1e3:.2f} mm"
                      if m.found else "not found" if m.palpated else "not palpated")
            print(f"  truth {m.truth_index + 1} ({m.x_m * 1e3:.0f}, {m.y_m * 1e3:.0f}) mm, {m.depth_m * 1e3:.1f} mm "
                  f"deep, {m.source} map: {result}", file=out)
        print("  false positives: " + ", ".join(f"{k} {v}" for k, v in analysis.false_positives.items()), file=out)


def stitch_main(argv: list[str] | None = None) -> int:
    args, code = _parse(stitch_parser(), argv)
    if args is None:
        return code
    try:
        params = analysis_params(args)
    except (StitchError, DetectError) as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_INPUT
    try:
        session = open_session(args.file)
    except SessionFileError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_INPUT
    from session import export

    with session:
        analysis = SessionAnalysis.run(session, params)
        _print_summary(analysis, sys.stdout)
        try:
            if args.output or args.report:
                from widgets import map_painting  # Qt, only for the pictures
            if args.output:
                map_painting.render_maps_png(args.output, analysis)
                print(f"maps: {args.output}")
            if args.csv:
                export.write_maps_csv(args.csv, analysis.stitched)
                print(f"maps CSV: {args.csv}")
            if args.json:
                export.write_maps_json(args.json, analysis)
                print(f"maps JSON: {args.json}")
            if args.tumours:
                export.write_tumours_json(args.tumours, analysis)
                print(f"tumours: {args.tumours}")
            if args.report:
                map_painting.write_report(args.report, analysis)
                print(f"report: {args.report}")
        except export.ExportError as err:
            print(f"error: {err}", file=sys.stderr)
            return EXIT_OUTPUT
    return EXIT_OK


# ---- review -------------------------------------------------------------------------------------------


def review_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="palpation-console review",
        description="Open recorded sessions in the reviewer (read-only: it never changes a file).")
    parser.add_argument("file", type=Path, nargs="?",
                        help=f"a session file (.h5); without it, File > Open starts in {sessions_dir()}")
    parser.add_argument("--screenshot", type=Path, help=argparse.SUPPRESS)  # save the window as PNG and quit
    return parser


def review_main(argv: list[str] | None = None) -> int:
    args, code = _parse(review_parser(), argv)
    if args is None:
        return code
    if args.file is not None:
        try:
            open_session(args.file).close()  # report a bad file here, before any window opens
        except SessionFileError as err:
            print(f"error: {err}", file=sys.stderr)
            return EXIT_INPUT
    if args.screenshot and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6 import QtCore, QtWidgets

    from widgets.review import ReviewWindow

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(sys.argv[:1])
    window = ReviewWindow(start_folder=sessions_dir())
    window.resize(1400, 900)
    window.show()
    if args.file is not None:
        window.open_file(args.file)
    if args.screenshot:  # for documentation and headless checks: lay the window out, save it, close it
        app.processEvents()
        saved = window.grab().save(str(args.screenshot))
        window.close()
        window.deleteLater()
        # destroyed now, not by the interpreter's teardown after the application (which crashes Qt)
        QtCore.QCoreApplication.sendPostedEvents(None, QtCore.QEvent.Type.DeferredDelete)
        if not saved:
            print(f"error: cannot write {args.screenshot}", file=sys.stderr)
            return EXIT_OUTPUT
        return EXIT_OK
    app.exec()
    return EXIT_OK
