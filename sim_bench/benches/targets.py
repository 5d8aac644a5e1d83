"""The benches' headline targets, one table: each bench exits 1 when it misses one of its own, and the
performance page renders this table (``bench-targets`` in the documentation), so a target has one
home. Per-scenario targets (the end-to-end, tracking and accuracy scenarios') stay with their
scenarios in their registries (:mod:`sim_bench.hardware.scenarios`, :mod:`sim_bench.benches.tracking_bench`,
:mod:`sim_bench.benches.ident_bench`), each scenario unable to register without them.

A target is (figure, ``<=`` or ``>=``, limit, unit, what it is); :func:`missed` judges a bench's
figures against its rows.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import NamedTuple


class Target(NamedTuple):
    """One figure's bound: ``figure`` (the key in the bench's figures), ``op`` (``<=`` or ``>=``),
    ``limit`` (in ``unit``) and what the figure is."""

    figure: str
    op: str
    limit: float
    unit: str
    what: str


INGEST = Target("ingest_frames_per_s", ">=", 100_000, "frames/s", "decode and reassembly, one core")   # both daemon runs
TARGETS: dict[str, tuple[Target, ...]] = {
    "speed": (
        Target("warm_median_ms", "<=", 0.3, "ms", "warm per-injection update, median"),
        Target("correction_added_ms", "<=", 0.1, "ms", "the drive correction and the processor's addition to it"),
        Target("cold_median_ms", "<=", 2.0, "ms", "cold start, median"),
    ),
    "speed-sim": (
        Target("candidates_per_s_256", ">=", 20_000, "1/s", "fast simulator, candidate simulations at batch 256"),
    ),
    "daemon-bench": (
        INGEST,
        Target("daemon_p99_ms", "<=", 5.0, "ms", "daemon latency p99 at 200 injections/s"),
        Target("external_p99_ms", "<=", 10.0, "ms", "the same seen from another process through the hub"),
    ),
    "daemon-bench --sweep": (
        Target("capacity_per_s", ">=", 3000.0, "1/s", "the highest rate held (p99 ≤ 5 ms, every injection "
                                                       "estimated), learning and correction on; per core: at "
                                                       "--cpu-share S the capacity / S"),
    ),
    "daemon-bench --self-calibration": (
        INGEST,
        Target("learning_p99_ms", "<=", 15.0, "ms", "daemon p99 while four series injectors learn (every run; "
                                                     "≤ 10 ms as the median of five)"),
        Target("adopted_p99_ms", "<=", 5.0, "ms", "daemon p99 once they have adopted their models"),
    ),
    "xcp-bench": (
        Target("daq_p99_ms", "<=", 5.0, "ms", "daemon p99 at 200 injections/s with a master running DAQ"),
        Target("daq_lost", "<=", 0, "packets", "estimates without their DAQ packet, and DAQ overruns"),
        Target("hostile_uncounted", "<=", 0, "datagrams", "of 10,000 hostile ones, neither answered nor counted"),
        Target("after_flood_p99_ms", "<=", 5.0, "ms", "daemon p99 after them"),
        Target("daemon_down", "<=", 0, "", "the daemon stopped serving, or did not exit 0"),
    ),
    "fleet-bench": (
        Target("rms_lh_um", "<=", 0.1, "µm", "the lot's L_h error against its truth, RMS, every worker count"),
        Target("good_flagged", "<=", 0, "injectors", "good injectors flagged as outliers"),
        Target("errors", "<=", 0, "inputs", "inputs that could not be processed"),
    ),
    "compensation": (
        Target("opening_spread_us", "<=", 0.5, "µs", "true opening-instant spread across a lot, closed loops, "
                                                        "settled, median over injections"),
        Target("opening_spread_p95_us", "<=", 1.0, "µs", "the same, 95th percentile"),
        Target("stroke_spread_um", "<=", 0.15, "µm", "true plateau-stroke spread across a lot, closed loops, "
                                                      "settled, median over injections"),
        Target("stroke_spread_p95_um", "<=", 0.3, "µm", "the same, 95th percentile"),
        Target("at_limit_share", "<=", 0.02, "", "settled injections driven by a correction at a drive limit"),
        Target("settle_injections", "<=", 10, "injections", "from a model's adoption until the stroke stays on target"),
        Target("z_rms_min", ">=", 0.5, "", "RMS(error/σ) of the predicted stroke and opening over the lots' parts"),
        Target("z_rms_max", "<=", 1.5, "", "the same, upper bound"),
    ),
}


def limit(bench: str, figure: str) -> float:
    """The limit of ``figure`` in ``bench``'s targets (KeyError if it has none)."""
    for t in TARGETS[bench]:
        if t.figure == figure:
            return t.limit
    raise KeyError(f"{bench} has no target for {figure}")


def missed(bench: str, figures: Mapping[str, float | None]) -> list[str]:
    """The targets of ``bench`` its ``figures`` miss (a missing or NaN figure misses), one line each."""
    out = []
    for t in TARGETS[bench]:
        if t.figure not in figures:
            continue
        v = figures[t.figure]
        ok = v is not None and math.isfinite(v) and (v <= t.limit if t.op == "<=" else v >= t.limit)
        if not ok:
            shown = "none" if v is None else f"{v:.4g}"
            out.append(f"{t.figure} {shown} {t.unit} misses {t.op} {t.limit:g}".replace("  ", " "))
    return out
