"""The library API: one row per injection from a capture or a trace file, through the same pipeline
as the daemon and ``replay`` (:func:`estimator.pipeline.build_pipeline`).

>>> from estimator.pipeline.estimates import iter_estimates
>>> for row in iter_estimates(Path("bench.blf")):
...     print(row["injector_id"], row["lh_um"], row["status"])

Rows have the keys ``ROW_FIELDS`` plus ``source``. A capture is any python-can log (by suffix); a
trace is a CSV trace (``t_s,current_A,voltage_V`` columns) or an MDF4 file (``trace_options`` with
``current_channel``, ``voltage_channel``, ...). A ``.csv`` is told apart by its header row.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from estimator.codec.records import Codec
from estimator.ident.simulators import SimulatorPool
from estimator.ident.tracking.tracker import Tracker
from estimator.io.captures import CAPTURE_SUFFIXES
from estimator.io.mdf import is_mdf, read_any_trace
from estimator.io.traces import csv_head, injection_from_trace
from estimator.pipeline.build import Pipeline, build_pipeline, build_tracker
from estimator.pipeline.config import EstimatorConfig
from estimator.pipeline.processor import ROW_FIELDS, Published
from estimator.pipeline.replay import iter_capture

FIELDS = ("source", *ROW_FIELDS)
CAPTURE_CSV_HEADER = "timestamp,arbitration_id"   # python-can's CSV logger


def is_capture_header(first_line: str | None) -> bool:
    """True for the header row of python-can's CSV logger (a capture, not a trace)."""
    return first_line is not None and first_line.startswith(CAPTURE_CSV_HEADER)


def source_kind(path: Path) -> str:
    """``capture`` (python-can log) or ``trace`` (one injection: CSV trace or MDF4 with channels)."""
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return "capture" if is_capture_header(csv_head(path)[1]) else "trace"
    if is_mdf(path):
        return "trace"   # MDF4 captures of bus traffic: pass kind="capture"
    return "capture" if suffix in CAPTURE_SUFFIXES else "trace"


def iter_estimates(source: Path, cfg: EstimatorConfig | None = None, *, kind: str | None = None,
                   trace_options: dict[str, Any] | None = None, tracker: Tracker | None = None,
                   pipeline: Pipeline | None = None) -> Iterator[dict[str, Any]]:
    """Rows for every injection in ``source``. ``tracker`` / ``pipeline`` carry state across sources of
    one injector (traces / captures). Raises OSError/ValueError/EstimatorError for unreadable files."""
    cfg = cfg or EstimatorConfig()
    source = Path(source)
    kind = kind or source_kind(source)
    if kind == "capture":
        for pub, t in iter_capture(source, cfg, pipeline=pipeline):
            yield {"source": str(source), **pub.to_row(t)}
        return
    trace = read_any_trace(source, **(trace_options or {}))
    inj = injection_from_trace(trace)
    tracker = tracker if tracker is not None else build_tracker(cfg)
    res = tracker.update(inj)
    counter = int(trace.meta_float("counter", 0.0) or 0)
    t = inj.time_s if math.isfinite(inj.time_s) else float("nan")
    pub = Published(inj.injector_id, counter, t, res, learning=tracker.calibration.get(inj.injector_id))
    yield {"source": str(source), **pub.to_row(t)}


def new_pipeline(cfg: EstimatorConfig | None = None, pool: SimulatorPool | None = None, codec: Codec | None = None) -> Pipeline:
    """A fresh pipeline for :func:`iter_estimates` (captures of one injector in time order), on
    ``pool`` and ``codec`` if given (shared, stateless parts: see :func:`build_pipeline`)."""
    return build_pipeline(cfg or EstimatorConfig(), pool, codec)
