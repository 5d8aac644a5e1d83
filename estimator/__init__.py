"""Piezo injector estimator: identify N_u and L_h from amplifier current and voltage."""

import os as _os

__version__ = "0.3.0"

# One BLAS thread per process. Our matrices are 7x7 and small batches: a multi-threaded OpenBLAS
# never helps them, and its spinning worker threads turn a loaded machine into stalls (measured with
# two CPU hogs on 2 cores: 60 updates took 163 s, worst 15 s, instead of 4 s, worst 0.17 s).
# Set before numpy loads OpenBLAS; an explicit setting in the environment wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

# numba's cache keyed by the compiled sources (see numba_cache): before anything imports numba
from estimator import numba_cache as _numba_cache  # noqa: E402

_numba_cache.configure()
