"""Imported by each benchmark before numpy: BLAS and OpenMP on one thread, so a figure measured
"on one core" is one (``setdefault``: a caller's own setting wins)."""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
