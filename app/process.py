"""How the console's processes run numpy, set up by its entry point (:func:`app.cli.main`), never by an import.

Both settings go into the environment before numpy is loaded: numpy and its BLAS libraries read them as they
load, in this process and in every process started from it (the controller, the live physics, a study's
workers), which load numpy before any code of theirs could set anything. A setting of the user's own wins.
"""

from __future__ import annotations

import os
import sys

# The variables the BLAS libraries of numpy and scipy read for their thread count: whoever sets one has chosen.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS")


def keep_numpy_off_huge_pages() -> None:
    """Stop numpy asking the kernel for transparent huge pages for every large array.

    The live tissue model's solves (app/live_physics.py) allocate and free hundreds of megabytes of them, and
    on our 2-CPU virtual machine the kernel's work behind them stalled the 1 kHz loop on its own CPU: over
    140 s of the autopilot, 98-288 ticks missed and stalls of 20-40 ms with them, 22-27 and 12-15 ms without
    (the solves also ran 7 % faster, 13.3 against 14.4 s). numpy reads it once, as it is imported."""
    os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")


def limit_blas_threads() -> None:
    """Run BLAS on one thread, unless the user set a thread count.

    The console's dense linear algebra is many small solves (a phantom's precompute, the depth fits), where
    OpenBLAS's threads give little and spin on the cores that the GUI, the 1 kHz loop and a study's other
    workers need: a new phantom's precompute beside a 2-worker study took 189 s with them, 85 s with one.

    The BLAS libraries loaded from now on (numpy's, and scipy's own copy) read the limit from the environment;
    threadpoolctl applies it to those this process has loaded already, where a caller imported numpy first."""
    if any(os.environ.get(name) for name in BLAS_THREAD_VARIABLES):
        return
    os.environ.update(OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    if "numpy" in sys.modules:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1, user_api="blas")
