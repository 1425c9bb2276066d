"""Orbit HIL bench: plant, estimator and controller as processes over Zenoh."""
import os

# The bench's linear algebra is small (6x6, 9x9); OpenBLAS's thread pool makes it slower, and on
# a loaded 2-core machine a 9x9 expm measured 12 ms instead of microseconds. Set before numpy
# loads; a user who wants threads sets the variable explicitly.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
