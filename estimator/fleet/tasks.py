"""What a Dask worker runs: one group of inputs through the pipeline; failures become rows."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

_POOLS: dict = {}   # per worker process: the simulator pool of each parameter file (tables built once)

WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
              "MKL_NUM_THREADS": "1"}


def process_group(key: str | None, paths: tuple[str, ...], cfg: Any, trace_options: dict[str, Any]) -> list[dict]:
    """Rows of every injection in ``paths`` (state carried across them when ``key`` is set); an input
    that cannot be read gives one row with status ``error`` and the reason, and the others go on."""
    for k, v in WORKER_ENV.items():
        os.environ.setdefault(k, v)
    from estimator.errors import EstimatorError
    from estimator.ident.tracker import Tracker
    from estimator.service.daemon import build_pool
    from estimator.service.estimates import iter_estimates, new_pipeline, source_kind

    pool_key = (cfg.params, cfg.max_sample_periods, cfg.sample_periods_ns)
    if pool_key not in _POOLS:
        _POOLS[pool_key] = build_pool(cfg)
    pool = _POOLS[pool_key]
    tracker = Tracker(cfg.tracker_config(), pool=pool)   # one per task: state per injector key
    pipeline = None    # built for the first capture of a keyed group (a DBC parse: ~10 ms a task)
    rows: list[dict] = []
    for path in paths:
        try:
            kind = source_kind(Path(path))
            if key is not None and kind == "capture" and pipeline is None:
                pipeline = new_pipeline(cfg, pool)
            for row in iter_estimates(Path(path), cfg, kind=kind, trace_options=trace_options, tracker=tracker,
                                      pipeline=pipeline):
                row["injector_key"] = key
                rows.append(row)
        except (EstimatorError, OSError, ValueError) as exc:
            rows.append({"source": path, "injector_key": key, "status": "error",
                         "reason": f"{type(exc).__name__}: {exc}"[:300]})
    return rows
