"""How fast the command line answers: ``palpation-console --help`` from a fresh interpreter.

Writes ``cli.json``: ``cli_help_s`` (median wall time of the whole command, interpreter start included, over
``RUNS`` runs) and ``cli_help_max_s``; ``cli_import_heavy`` lists any of Qt, pyqtgraph, scipy, h5py or the
tissue model that ``import app.cli`` loaded (none is the design: each command imports what it needs).
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

NAME = "cli"
RUNS = 7
HEAVY = ("PySide6", "pyqtgraph", "scipy", "h5py", "tissue.mechanics")


def run(out_dir: Path) -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    times = []
    for _ in range(RUNS):
        started = time.perf_counter()
        subprocess.run([sys.executable, "-m", "app", "--help"], check=True, capture_output=True)
        times.append(time.perf_counter() - started)
    probe = ("import sys, app.cli; "
             f"print(','.join(sorted({{m.split('.')[0] if not m.startswith('hardware') else m for m in sys.modules "
             f"if m.startswith({HEAVY!r})}})))")
    loaded = subprocess.run([sys.executable, "-c", probe], check=True, capture_output=True, text=True).stdout.strip()
    results = {"cli_help_s": statistics.median(times), "cli_help_max_s": max(times),
               "cli_import_heavy": [m for m in loaded.split(",") if m]}
    print(f"cli: --help in {results['cli_help_s']:.3f} s (median of {RUNS}), heavy imports: "
          f"{results['cli_import_heavy'] or 'none'}")
    (out_dir / f"{NAME}.json").write_text(json.dumps(results, indent=2, sort_keys=True) + "\n")
    return results
