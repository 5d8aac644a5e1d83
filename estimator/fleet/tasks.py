"""What a Dask worker runs: one group of inputs through the pipeline; failures become rows."""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from pathlib import Path
from typing import Any

_POOLS: dict = {}   # per worker process: the simulator pool of each parameter file (tables built once)
_CODECS: dict = {}  # per worker process: the codec of each DBC file (parsed once)

WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
              "MKL_NUM_THREADS": "1"}

# glibc's mallopt parameters (malloc.h) and what a worker sets them to
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
HEAP_TRIM_BYTES = 128 << 20    # free heap kept at the top before it is given back to the OS
HEAP_MMAP_BYTES = 16 << 20     # allocations from this size on get their own mapping
_heap_set: bool | None = None


def keep_heap() -> bool:
    """Let this process reuse freed memory for the cold start's arrays instead of mapping fresh pages.

    Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_=65536``. Setting it switches off glibc's
    adaptive thresholds, so every array of 128 KiB or more (a cold start allocates dozens: the grid's
    voltages and recorded states, 0.3-0.5 MB each) is mapped and unmapped again, with a page fault
    for every page it touches: a lot file cost 20 ms on a worker against 12.6 ms in a plain process.
    With the trim threshold at 128 MiB and the mapping threshold at 16 MiB, as a plain process
    effectively has them after its first large allocations, it costs the same on a worker (any
    cluster: this runs in the task). glibc only (elsewhere nothing is changed); once per process;
    returns whether the settings were applied."""
    global _heap_set
    if _heap_set is None:
        _heap_set = False
        name = ctypes.util.find_library("c") if sys.platform.startswith("linux") else None
        if name:
            try:
                libc = ctypes.CDLL(name)
                _heap_set = bool(libc.mallopt(M_MMAP_THRESHOLD, HEAP_MMAP_BYTES)) and bool(
                    libc.mallopt(M_TRIM_THRESHOLD, HEAP_TRIM_BYTES))
            except (OSError, AttributeError):   # not glibc (no mallopt)
                _heap_set = False
    return _heap_set


def _worker_parts(cfg: Any) -> tuple[Any, Any]:
    """This worker's simulator pool and codec for ``cfg`` (built on first use, then shared), with the
    worker's environment and heap settings applied."""
    for k, v in WORKER_ENV.items():
        os.environ.setdefault(k, v)
    keep_heap()
    from estimator.pipeline import build_codec, build_pool

    pool_key = (cfg.params, cfg.max_sample_periods, cfg.sample_periods_ns)
    if pool_key not in _POOLS:
        _POOLS[pool_key] = build_pool(cfg)
    if cfg.dbc not in _CODECS:
        _CODECS[cfg.dbc] = build_codec(cfg)
    return _POOLS[pool_key], _CODECS[cfg.dbc]


def warm_worker(cfg: Any) -> bool:
    """Get a worker ready before its first task: its pool and codec built and every compiled kernel
    loaded from numba's cache (:meth:`Tracker.warm_up`), so the run's time splits into the cluster's
    start and the work (``FleetResult.seconds_start``). Returns True (for ``Client.run``)."""
    from estimator.ident.tracking.tracker import Tracker

    pool, _ = _worker_parts(cfg)
    Tracker(cfg.tracker_config(), pool=pool).warm_up()
    return True


def process_group(key: str | None, paths: tuple[str, ...], cfg: Any, trace_options: dict[str, Any],
                  tracker_config: Any = None) -> list[dict]:
    """Rows of every injection in ``paths`` (state carried across them when ``key`` is set); an input
    that cannot be read gives one row with status ``error`` and the reason, and the others go on.
    ``tracker_config``: ``cfg.tracker_config()``, if the caller has it (the same for every group)."""
    from estimator.errors import EstimatorError
    from estimator.ident.tracking.tracker import Tracker
    from estimator.pipeline.estimates import iter_estimates, new_pipeline, source_kind

    pool, codec = _worker_parts(cfg)
    tracker = Tracker(tracker_config or cfg.tracker_config(), pool=pool,   # one per group: state per injector key
                      self_calibration=cfg.self_calibration_config())
    pipeline = None    # a keyed group's captures continue one pipeline; an unkeyed capture gets its own
    rows: list[dict] = []
    for path in paths:
        try:
            kind = source_kind(Path(path))
            if kind == "capture" and (pipeline is None or key is None):
                pipeline = new_pipeline(cfg, pool, codec)
            for row in iter_estimates(Path(path), cfg, kind=kind, trace_options=trace_options, tracker=tracker,
                                      pipeline=pipeline):
                row["injector_key"] = key
                rows.append(row)
        except (EstimatorError, OSError, ValueError) as exc:
            rows.append({"source": path, "injector_key": key, "status": "error",
                         "reason": f"{type(exc).__name__}: {exc}"[:300]})
    return rows


def process_groups(groups: tuple[tuple[str | None, tuple[str, ...]], ...], cfg: Any,
                   trace_options: dict[str, Any]) -> list[dict]:
    """:func:`process_group` of several (key, paths) groups in one task, each with its own tracker: the
    rows are the same as with a task per group (a Dask task costs the scheduler and the client ≈ 2 ms
    of CPU, which on a small machine they take from the workers' cores)."""
    rows: list[dict] = []
    tracker_config = cfg.tracker_config()
    for key, paths in groups:
        rows.extend(process_group(key, paths, cfg, trace_options, tracker_config))
    return rows
