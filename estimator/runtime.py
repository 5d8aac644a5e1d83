"""What a process of ours sets up before numpy loads: the command-line entry points call
:func:`prepare_process` first (``python -m estimator``, ``injector-estimator``, the benches).

One BLAS thread per process. Our matrices are 7x7 and small batches: a multi-threaded OpenBLAS never
helps them, and its spinning worker threads turn a loaded machine into stalls (docs: design
decisions). Child processes (the calibration worker, the fleet's Dask workers) inherit the setting.
An explicit setting in the environment wins. A program that imports the package as a library keeps
its own settings.
"""

from __future__ import annotations

import os

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def prepare_process() -> None:
    """One BLAS thread unless the environment says otherwise (before numpy is imported)."""
    for var in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(var, "1")


def console_main() -> int:
    """The ``injector-estimator`` command."""
    prepare_process()
    from estimator.cli import main
    return main()
