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

from session import export
from session.analysis import AnalysisParams, SessionAnalysis
from session.depth import DepthModel, DepthModelError
from session.detect import MATCH_RADIUS_M, DepthParams, DetectError, DetectParams, widths_from_mm, widths_text_mm
from session.flatfield import FlatFieldError, Reference
from session.info import sessions_dir
from session.mcap_export import McapExportError, write_mcap
from session.physics import PHYSICS, physics_for
from session.reader import Session, SessionFileError, open_session
from session.stitch import L0Source, StitchError, StitchParams
from session.tables import TABLES, TableError, write_csv, write_parquet
from tissue.mechanics.progress import Progress, TextProgressBar

EXIT_OK, EXIT_OUTPUT, EXIT_INPUT = 0, 1, 2


def add_analysis_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("analysis (re-analyse a recording without re-recording it)")
    group.add_argument("--cell-mm", type=float, default=1.0, help="grid cell size in mm (default 1)")
    group.add_argument("--false-alarm", type=float, default=DetectParams.false_alarm_per_area,
                       help="chance that a palpated area of healthy tissue raises a spot (default "
                            f"{DetectParams.false_alarm_per_area:g}); lower finds fewer, stronger tumours")
    group.add_argument("--accuracy", type=float, default=DetectParams.accuracy,
                       help="the least relative scatter of healthy tissue from one loading to the next (default "
                            f"{DetectParams.accuracy:g} = {DetectParams.accuracy * 100:g} %%)")
    group.add_argument("--merge-radius-mm", type=float, default=DetectParams.merge_radius_m * 1e3,
                       help="spots this close are one tumour, across areas and levels (default "
                            f"{DetectParams.merge_radius_m * 1e3:g})")
    group.add_argument("--fit-radius-mm", type=float, default=DetectParams.fit_radius_m * 1e3,
                       help="the contrast this close to a tumour's strongest spot places it (default "
                            f"{DetectParams.fit_radius_m * 1e3:g})")
    group.add_argument("--blob-widths-mm", type=_widths, dest="blob_widths_m", default=DetectParams.kernel_widths_m,
                       metavar="W[,W...]",
                       help="the widths (Gaussian sigma) of the blobs the detector looks for (default "
                            f"{widths_text_mm(DetectParams.kernel_widths_m)})")
    group.add_argument("--depth-model-error", type=float, default=DepthParams.model_error,
                       help="the depth model's error in a tumour's predicted contrast, relative (default "
                            f"{DepthParams.model_error:g}); larger widens the depth intervals")
    group.add_argument("--depth-scale-error", type=float, default=DepthParams.scale_error,
                       help="the part of that error every element near a tumour shares, one scale on all its "
                            f"predicted contrast, relative (default {DepthParams.scale_error:g}); larger widens "
                            "the depth intervals")
    group.add_argument("--depth-law-spread", type=float, default=DepthParams.law_spread,
                       help="how unsure the depth model is of the tissue's law: a tumour's contrast taken to grow "
                            "with the press 1 - this to 1 + this times as fast as its finite-strain model says "
                            f"(default {DepthParams.law_spread:g}; 0 trusts that model, 1 reaches small strain)")
    group.add_argument("--physics", choices=list(PHYSICS), default="rebuilt",
                       help="the probe's expected pattern on homogeneous tissue: " + "; ".join(
                           f"{k} = {v}" for k, v in PHYSICS.items()) + " (default rebuilt)")
    group.add_argument("--reference", type=Path,
                       help="a reference palpation of tumour-free tissue (saved with --save-reference) whose "
                            "per-element baseline replaces the session's own estimate")
    group.add_argument("--no-depth-model", action="store_true",
                       help="skip the model-based depth (the paper's indentation rule is always given)")
    group.add_argument("--l0", choices=[s.value for s in L0Source], default=L0Source.ELEMENT.value,
                       help="where Eq. 1's initial thickness L0 comes from: each element's onset (element, "
                            "as recorded), one per region (region), or a given thickness (fixed, with --l0-mm)")
    group.add_argument("--l0-mm", type=float, help="the thickness for --l0 fixed, in mm")


def _widths(text: str) -> tuple[float, ...]:
    """``--blob-widths-mm``, in m."""
    try:
        return widths_from_mm(text)
    except DetectError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def analysis_params(args) -> AnalysisParams:
    """Raises StitchError / DetectError naming the bad option."""
    if args.l0 == L0Source.FIXED.value and args.l0_mm is None:
        raise StitchError("--l0 fixed needs --l0-mm, the tissue thickness in mm")
    stitch = StitchParams(cell_m=args.cell_mm * 1e-3, l0_source=args.l0,
                          l0_fixed_m=None if args.l0_mm is None else args.l0_mm * 1e-3)
    detect = DetectParams(false_alarm_per_area=args.false_alarm, accuracy=args.accuracy,
                          merge_radius_m=args.merge_radius_mm * 1e-3, fit_radius_m=args.fit_radius_mm * 1e-3,
                          kernel_widths_m=args.blob_widths_m)
    return AnalysisParams(stitch, detect,
                          DepthParams(args.depth_model_error, args.depth_scale_error, args.depth_law_spread))


def analyse(session: Session, args, progress: Progress | None = None, steps: Progress | None = None
            ) -> SessionAnalysis:
    """The session analysed as the options say; raises AnalysisInputError for physics or a reference that
    cannot be had for it. ``progress`` hears about the physics (a cache hit or a finite-element solve of the
    rebuilt block: seconds when new), ``steps`` about the analysis after it (the depth model's solves: tens of
    seconds when new)."""
    if not len(session.levels):
        # said before any option is tried, and with what the reader found (a truncated file loses its levels)
        why = f"{session.warnings[0].rstrip('.')}; " if session.recovered and session.warnings else ""
        raise AnalysisInputError(f"{why}the session holds no recorded level, so there is no palpated area to analyse")
    try:
        physics = physics_for(session, args.physics, progress=progress)
    except ValueError as err:
        raise AnalysisInputError(f"--physics {args.physics}: {err}") from None
    reference = None
    if args.reference is not None:
        try:
            reference = Reference.load(args.reference, tuple(session.levels.dtype["pressure_pa"].shape))
        except FlatFieldError as err:
            raise AnalysisInputError(str(err)) from None
    depth_model = None
    if not args.no_depth_model:
        try:
            depth_model = DepthModel.for_session(session)
        except DepthModelError as err:
            raise AnalysisInputError(f"{err} (--no-depth-model analyses without it)") from None
    try:
        return SessionAnalysis.run(session, analysis_params(args), physics, reference, depth_model, steps)
    except FlatFieldError as err:
        raise AnalysisInputError(f"--reference {args.reference}: {err}") from None
    except StitchError as err:
        raise AnalysisInputError(f"--cell-mm {args.cell_mm:g}: {err}") from None


def _model_depth(t) -> str:
    model = export.depth_model_text(t)
    return "" if model == "—" else f", {model} mm (model, 90 %)"


class AnalysisInputError(ValueError):
    """A re-analysis option that cannot be applied to this session; the message says why."""


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
    parser.add_argument("-o", "--output", type=Path, help="PNG (.png) with the force and stiffness maps at every level")
    parser.add_argument("--csv", type=Path, help="the maps as CSV (one row per cell and level)")
    parser.add_argument("--json", type=Path, help="the maps as JSON")
    parser.add_argument("--tumours", type=Path, help="the tumours found, as JSON")
    parser.add_argument("--report", type=Path, help="one-page report, PDF (.pdf) or PNG (.png)")
    parser.add_argument("--save-reference", type=Path, metavar="FILE",
                        help="this session palpated tumour-free tissue: save its per-element baseline as a "
                             "reference palpation (JSON) for --reference")
    add_analysis_arguments(parser)
    return parser


def _opened(path: Path) -> Session | None:
    """The session file at ``path``, or None once the reader's one line saying why not is printed."""
    try:
        return open_session(path)
    except SessionFileError as err:
        print(f"error: {err}", file=sys.stderr)
        return None


def _print_summary(analysis: SessionAnalysis, out) -> None:
    session, stitched, tumours = analysis.session, analysis.stitched, analysis.tumours
    forces = ", ".join(f"{f:g}" for f in stitched.level_forces_N()) or "none"
    print(f"{session.path.name}: {len(session.regions())} regions, {len(session.levels)} recorded levels "
          f"(forces {forces} N), {stitched.coverage_text(session.tissue_extent_m)}", file=out)
    print(f"  flat field: {analysis.flat_field}", file=out)
    for warning in session.warnings:
        print(f"  warning: {warning}", file=out)
    if not tumours:
        print("No tumour found with these parameters.", file=out)
    for t in tumours:
        depth = f"{t.depth_m * 1e3:5.2f}" if t.depth_m == t.depth_m else "  n/a"
        print(f"  {t.source:<9} x {t.x_m * 1e3:6.1f} mm  y {t.y_m * 1e3:6.1f} mm  z {t.score:5.1f}  "
              f"contrast {t.contrast * 100:+4.0f} %  first at {t.first_level_N:g} N  depth {depth} mm (rule)"
              + _model_depth(t), file=out)
    if analysis.has_ground_truth:
        for m in analysis.matches:
            result = (f"found {m.error_xy_m * 1e3:.1f} mm away, depth {m.depth_estimate_m * 1e3:.2f} mm (rule)"
                      + _model_depth(m) if m.found else "not found" if m.palpated else "not palpated")
            print(f"  truth {m.truth_index + 1} ({m.x_m * 1e3:.0f}, {m.y_m * 1e3:.0f}) mm, {m.depth_m * 1e3:.1f} mm "
                  f"deep, {m.source} map: {result}", file=out)
        print(f"  false positives (no true tumour within {MATCH_RADIUS_M * 1e3:g} mm): "
              + ", ".join(f"{k} {v}" for k, v in analysis.false_positives.items()), file=out)


def stitch_main(argv: list[str] | None = None) -> int:
    args, code = _parse(stitch_parser(), argv)
    if args is None:
        return code
    try:
        analysis_params(args)  # a bad option is told before the file is even opened
    except (StitchError, DetectError) as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_INPUT
    problem = _output_problem(args)
    if problem:  # before the analysis, not after it
        print(f"error: {problem}", file=sys.stderr)
        return EXIT_OUTPUT
    session = _opened(args.file)
    if session is None:
        return EXIT_INPUT
    with session:
        try:
            # the first analysis of a session rebuilds its tissue and solves the depth model's spheres: a
            # minute or more that printed nothing. The build reports many times a second, drawn every tenth of
            # one; the analysis's steps are a few hundred, each drawn: a solve is told a moment after the step
            # that asks for it, and its line then stands for seconds
            analysis = analyse(session, args, progress=TextProgressBar(), steps=TextProgressBar(interval_s=0.0))
        except AnalysisInputError as err:
            print(f"error: {err}", file=sys.stderr)
            return EXIT_INPUT
        _print_summary(analysis, sys.stdout)
        try:
            if args.save_reference:
                save_reference(args.save_reference, analysis)
                print(f"reference palpation: {args.save_reference}")
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


# the outputs whose kind the name's suffix decides
_SUFFIXES = {"output": (".png",), "report": (".pdf", ".png")}


def _output_problem(args) -> str:
    """Why an output cannot be written where it is asked (a folder that does not exist, a kind the command
    does not write), or ''."""
    for dest, option in (("output", "-o"), ("csv", "--csv"), ("json", "--json"), ("tumours", "--tumours"),
                         ("report", "--report"), ("save_reference", "--save-reference")):
        path = getattr(args, dest)
        if path is None:
            continue
        if not path.parent.is_dir():
            return f"{option} {path}: the folder {path.parent} does not exist"
        allowed = _SUFFIXES.get(dest)
        if allowed and path.suffix.lower() not in allowed:
            return f"{option} {path}: name it {' or '.join(allowed)} (the suffix decides what is written)"
    return ""


def save_reference(path: Path, analysis: SessionAnalysis) -> None:
    """Save an analysed session of tumour-free tissue as a reference palpation (raises ExportError)."""
    session = analysis.session
    pattern = analysis.contrasts["stiffness"]
    reference = Reference.from_levels(session.levels, pattern.share, pattern.share_sigma,
                                      f"reference palpation {session.path.name} ({session.uuid}, "
                                      f"{session.created_utc}); physics: {analysis.flat_field}", pattern.physics)
    try:
        reference.save(path)
    except OSError as err:
        raise export.ExportError(f"cannot write {path}: {err.strerror or err}") from None


# ---- review -------------------------------------------------------------------------------------------


def review_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="palpation-console review",
        description="Open recorded sessions in the reviewer (read-only: it never changes a file).")
    parser.add_argument("file", type=Path, nargs="?",
                        help=f"a session file (.h5); without it, File > Open starts in {sessions_dir()}")
    parser.add_argument("--screenshot", type=Path, help=argparse.SUPPRESS)  # save the window as PNG and quit
    return parser


def physics_options() -> dict:
    """The reviewer's flat-field physics choices (label -> factory(session, progress)), the default first."""
    return {"rebuilt from the session": lambda session, progress: physics_for(session, "rebuilt", progress=progress),
            "rebuilt, part of the tissue palpated (its ends not known)":
                lambda session, progress: physics_for(session, "partial", progress=progress),
            "simulated phantom (simulated sessions)":
                lambda session, progress: physics_for(session, "phantom", progress=progress)}


def review_main(argv: list[str] | None = None) -> int:
    args, code = _parse(review_parser(), argv)
    if args is None:
        return code
    if args.screenshot and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from app.display import display_problem

    problem = display_problem(command="review")
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return EXIT_INPUT
    if args.file is not None:
        try:
            open_session(args.file).close()  # report a bad file here, before any window opens
        except SessionFileError as err:
            print(f"error: {err}", file=sys.stderr)
            return EXIT_INPUT
    from PySide6 import QtCore, QtWidgets

    from widgets.review import ReviewWindow

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(sys.argv[:1])
    window = ReviewWindow(start_folder=sessions_dir(), physics=physics_options(), depth_model=DepthModel.for_session)
    if app.platformName() == "offscreen":  # no screen to fit (a headless screenshot): the size a document wants
        window.resize(1400, 900)
    else:
        screen = app.primaryScreen().availableGeometry()
        window.resize(min(1400, screen.width()), min(900, screen.height()))
    window.show()
    if args.file is not None:
        window.open_file(args.file)
    if args.screenshot:  # for documentation and headless checks: lay the window out, save it, close it
        if window.analysing:  # the window as it lands, on the findings
            done = QtCore.QEventLoop()
            window.analysing_changed.connect(lambda busy: busy or done.quit())
            done.exec()
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


# ---- export -------------------------------------------------------------------------------------------


def export_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="palpation-console export",
        description="Write a recorded session's streams as tidy tables for pandas, R or a spreadsheet: ticks (one "
                    "row per control period), frames and levels (one row per element), each with its UTC. pandas: "
                    "pd.read_csv('FOLDER/NAME-ticks.csv') or pd.read_parquet('FOLDER/NAME-frames.parquet'). Or as a "
                    "ROS 2 bag (MCAP) for Foxglove and ros2 bag, stamped in UTC.")
    parser.add_argument("file", type=Path, help="a session file (.h5)")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--csv", type=Path, metavar="FOLDER", help="write NAME-ticks.csv, -frames.csv, -levels.csv here")
    where.add_argument("--parquet", type=Path, metavar="FOLDER",
                       help="write NAME-ticks.parquet, ... here (needs pyarrow: "
                            "pip install 'palpation-console[parquet]')")
    where.add_argument("--mcap", type=Path, metavar="OUT.mcap",
                       help="write the session as a ROS 2 bag in MCAP: the TSI's pose, the forces, the loop's state, "
                            "the tactile frames, levels and events (needs mcap: pip install "
                            "'palpation-console[mcap]')")
    parser.add_argument("--tables",
                        help=f"with --csv or --parquet, which tables, comma-separated (default {','.join(TABLES)})")
    return parser


def export_main(argv: list[str] | None = None) -> int:
    args, code = _parse(export_parser(), argv)
    if args is None:
        return code
    if args.mcap is not None:
        if args.tables is not None:
            print("error: --tables applies to --csv and --parquet; --mcap writes every stream", file=sys.stderr)
            return EXIT_INPUT
        if args.mcap.suffix.lower() != ".mcap":
            print(f"error: --mcap {args.mcap}: name it .mcap (ros2 bag knows the storage by it)", file=sys.stderr)
            return EXIT_INPUT
        folder = args.mcap.parent
    else:
        tables = tuple(t.strip() for t in (args.tables or ",".join(TABLES)).split(",") if t.strip())
        unknown = [t for t in tables if t not in TABLES]
        if unknown or not tables:
            print(f"error: --tables {args.tables}: each must be one of {', '.join(TABLES)}", file=sys.stderr)
            return EXIT_INPUT
        folder = args.csv or args.parquet
    if not folder.is_dir():
        print(f"error: {folder}: no such folder", file=sys.stderr)
        return EXIT_OUTPUT
    session = _opened(args.file)
    if session is None:
        return EXIT_INPUT
    with session:
        for warning in session.warnings + ([session.clock_note] if session.clock_note else []):
            print(f"warning: {warning}", file=sys.stderr)
        try:
            if args.mcap is not None:
                counts = write_mcap(session, args.mcap)
                written = [args.mcap]
            else:
                written = (write_csv if args.csv else write_parquet)(session, folder, tables)
        except (TableError, McapExportError) as err:
            print(f"error: {err}", file=sys.stderr)
            return EXIT_OUTPUT
        except SessionFileError as err:  # damage found only when the rows were read
            print(f"error: {err}", file=sys.stderr)
            return EXIT_INPUT
    for path in written:
        print(path)
    if args.mcap is not None:
        print(", ".join(f"{topic} {n}" for topic, n in counts.items()), file=sys.stderr)
    return EXIT_OK
