import os

# The console's dense linear algebra is many small solves (a phantom's precompute, the depth fits), where
# OpenBLAS's threads give little and spin on the cores that the GUI, the 1 kHz loop and a study's other
# workers need: a new phantom's precompute beside a 2-worker study took 189 s with them, 85 s with one.
# It must be set before numpy loads OpenBLAS; a setting of the user's own wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
