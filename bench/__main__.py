"""Run the benchmarks: ``python -m bench [name ...] [--seconds S] [--out DIR]``.

Each module in :data:`BENCHMARKS` exposes ``run(out_dir: Path) -> dict`` and writes
``<out_dir>/<name>.json``; a failing benchmark is reported and the others still run.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
import traceback
from pathlib import Path

from app import process

BENCHMARKS = ["bench.loop_bench", "bench.gui_bench", "bench.rig_bench", "bench.hardware_bench", "bench.sessions_bench",
              "bench.safety_bench",
              "bench.cli_bench"]
DEFAULT_OUT = Path(__file__).resolve().parents[1] / "build" / "bench"


def _short(module: str) -> str:
    return module.rsplit(".", 1)[-1].removesuffix("_bench")


def main(argv: list[str] | None = None) -> int:
    process.keep_numpy_off_huge_pages()  # as the console runs numpy, before any benchmark loads it
    process.limit_blas_threads()
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.splitlines()[0])
    known = [_short(m) for m in BENCHMARKS]
    parser.add_argument("names", nargs="*", metavar="name", help=f"benchmarks to run (default: all of {known})")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="directory for the JSON results")
    parser.add_argument("--seconds", type=float, help="run time per configuration (PALPATION_BENCH_SECONDS)")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.names) - set(known))
    if unknown:
        parser.error(f"unknown benchmark(s) {', '.join(unknown)}; known: {', '.join(known)}")
    if args.seconds is not None:
        os.environ["PALPATION_BENCH_SECONDS"] = str(args.seconds)

    failed = []
    for module_name in BENCHMARKS:
        name = _short(module_name)
        if args.names and name not in args.names:
            continue
        started = time.monotonic()
        try:
            importlib.import_module(module_name).run(args.out)
        except Exception:  # noqa: BLE001 - report it and go on with the next benchmark
            traceback.print_exc()
            failed.append(name)
            print(f"bench: {name} FAILED", file=sys.stderr)
            continue
        print(f"bench: {name} done in {time.monotonic() - started:.0f} s -> {args.out / (name + '.json')}")
    return 1 if failed else 0


if __name__ == "__main__":  # the guard matters: spawned controller processes re-import the main module
    sys.exit(main())
