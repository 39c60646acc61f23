import os

# The console's dense linear algebra is many small solves (a phantom's precompute, the depth fits), where
# OpenBLAS's threads give little and spin on the cores that the GUI, the 1 kHz loop and a study's other
# workers need: a new phantom's precompute beside a 2-worker study took 189 s with them, 85 s with one.
# It must be set before numpy loads OpenBLAS; a setting of the user's own wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# numpy asks the kernel for transparent huge pages for every large array. The live tissue model's solves
# (app/live_physics.py) allocate and free hundreds of megabytes of them, and on our 2-CPU virtual machine
# the kernel's work behind them stalled the 1 kHz loop on its own CPU: over 140 s of the autopilot, 98-288
# ticks missed and stalls of 20-40 ms with them, 22-27 and 12-15 ms without (the solves also ran 7 % faster,
# 13.3 against 14.4 s). A setting of the user's own wins.
os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")
