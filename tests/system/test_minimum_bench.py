"""The calibration-minima bench: its verdict, and one part calibrated the two ways."""

from __future__ import annotations

from typing import Any

import pytest

from estimator.ident.learning.selfcal import SelfCalConfig
from sim_bench.benches import minimum_bench


def _row(seed: int, gap: float, err: float, deeper: float, sigma: float = 0.05) -> dict[str, Any]:
    moved = abs(err - deeper)
    return {"seed": seed, "cost_gap": gap, "lh_err_um": err, "sigma_lh_um": sigma, "deeper_lh_err_um": deeper,
            "deeper_sigma_lh_um": sigma, "lh_moved_sigma": moved / sigma,
            "short": gap > minimum_bench.COST_GAP and moved > sigma, "seconds": 1.0}


def test_a_calibration_stopped_short_of_the_deeper_minimum_fails_the_bench(monkeypatch: pytest.MonkeyPatch) -> None:
    """Above the deeper minimum with L_h more than its σ from it: counted and failed; above it with L_h
    within its σ, or as deep: counted as stopped above only."""
    rows = {0: _row(0, 0.0, 0.01, 0.01), 1: _row(1, 30.0, 0.02, 0.03), 2: _row(2, 60.0, -0.25, 0.0)}
    monkeypatch.setattr(minimum_bench, "part_row", lambda seed, config: rows[seed - minimum_bench.SEED_GOOD])
    rep = minimum_bench.run(3)
    s = rep["summary"]
    assert (s["short"], s["stopped_above"], s["short_seeds"]) == (1, 2, [2]) and not rep["passed"]
    assert "1 of 3 calibrations stopped short" in s["failures"][0] and "5.0σ" in s["failures"][0]
    assert "FAIL" in minimum_bench.format_report(rep)
    rows[2] = _row(2, 0.0, 0.0, 0.0)
    assert minimum_bench.run(3)["passed"]


def test_one_part_is_calibrated_from_the_tables_and_from_its_own_parameters() -> None:
    """A good part's first learning window: ten injections over a wide span; the calibration from its
    own parameters is at least as deep as the learner's."""
    row = minimum_bench.part_row(minimum_bench.SEED_GOOD, SelfCalConfig())
    assert row["adequate"] and row["injections"] == SelfCalConfig().window - SelfCalConfig().held_out
    lo, hi = row["preload_n"]
    assert (hi - lo) / ((hi + lo) / 2) > 0.4
    assert row["cost_gap"] >= -1e-6 and abs(row["deeper_lh_err_um"]) < 3 * row["deeper_sigma_lh_um"]
