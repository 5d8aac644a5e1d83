"""Benchmark of the fast simulator: candidate simulations per second for 100 µs windows."""

from __future__ import annotations

import os
import platform
import time
from typing import Any

import numpy as np

from estimator.model.drive import Drive, StandardDrive
from estimator.model.fast_sim import FastSimulator


def measure(batch_sizes: tuple[int, ...] = (1, 16, 256), window_s: float = 100e-6, seconds: float = 2.0,
            seed: int = 0, drive: Drive | None = None) -> dict:
    """Time ``FastSimulator.simulate`` on random candidates (N_u over Table 1's range, L_h in [-1, 10] µm).

    Returns a JSON-ready dict with one entry per batch size: calls, candidates per second and
    microseconds per candidate, and the machine it ran on.
    """
    sim = FastSimulator()
    cur = (drive or StandardDrive()).samples(window_s)
    rng = np.random.default_rng(seed)
    rows = []
    for b in batch_sizes:
        nu = rng.uniform(sim.params.psa.nu_min_n_per_v, sim.params.psa.nu_max_n_per_v, b)
        lh = rng.uniform(-1e-6, 10e-6, b)
        sim.simulate(cur, nu, lh)  # compile / warm the caches outside the timing
        calls = 0
        t0 = time.perf_counter()
        while True:
            sim.simulate(cur, nu, lh)
            calls += 1
            elapsed = time.perf_counter() - t0
            if elapsed >= seconds and calls >= 3:
                break
        rate = calls * b / elapsed
        rows.append({"batch": b, "calls": calls, "seconds": elapsed, "candidates_per_s": rate,
                     "us_per_candidate": 1e6 / rate})
    return {"benchmark": "speed-sim", "window_us": window_s * 1e6, "samples": int(cur.size),
            "numba_threads": os.environ.get("NUMBA_NUM_THREADS", "default"), "cpu": platform.processor()
            or platform.machine(), "python": platform.python_version(), "results": rows}


def format_table(report: dict) -> str:
    """The speed report as a text table."""
    lines = [f"fast simulator, {report['window_us']:.0f} µs window ({report['samples']} samples), one core",
             f"{'batch':>6} {'calls':>7} {'candidates/s':>13} {'µs/candidate':>13}"]
    for r in report["results"]:
        lines.append(f"{r['batch']:>6} {r['calls']:>7} {r['candidates_per_s']:>13,.0f} {r['us_per_candidate']:>13.2f}")
    return "\n".join(lines)


def yardstick_us_per_candidate(seconds: float = 1.0) -> float:
    """The machine's speed of the hour: µs per candidate at batch 256 (the figure benches print beside
    their timings, so that runs from different hours compare)."""
    return float(measure((256,), seconds=seconds)["results"][0]["us_per_candidate"])


def yardstick_fields(before: float, after: float) -> dict[str, Any]:
    """A report's yardstick from measurements before and after its timings (µs per candidate): their
    mean and both."""
    return {"yardstick_us_per_candidate": (before + after) / 2, "yardstick_before_after": [before, after]}


def yardstick_text(rep: dict) -> str:
    """The line that states a report's yardstick (:func:`yardstick_fields`)."""
    before, after = rep["yardstick_before_after"]
    return (f"machine yardstick: {rep['yardstick_us_per_candidate']:.1f} µs a candidate simulation at batch 256 "
            f"(before and after: {before:.1f}, {after:.1f})")
