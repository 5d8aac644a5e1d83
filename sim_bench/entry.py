"""The ``injector-sim`` command: the process set up first (:func:`estimator.runtime.prepare_process`)."""

from __future__ import annotations

from estimator.runtime import prepare_process


def console_main() -> int:
    """``injector-sim`` / ``python -m sim_bench``."""
    prepare_process()
    from sim_bench.cli import main
    return main()
