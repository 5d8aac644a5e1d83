"""The paper's Table 3 ("sim" column, PSA No. 1) reproduced with one scaled trapezoidal drive."""

from __future__ import annotations

import pytest

from estimator.model.drive import STANDARD_AMPLITUDE_A
from sim_bench.benches import table3


def test_standard_drive_amplitude_is_the_fitted_one(sim):
    assert table3.fit_drive_amplitude(sim) == pytest.approx(STANDARD_AMPLITUDE_A, abs=2e-7)


def test_rows_2_to_4_reproduce_the_paper(sim):
    rows = table3.reproduce(sim)
    assert rows[0].ours_um == pytest.approx(24.50, abs=1e-4)
    for row in rows[1:]:
        assert abs(row.ours_um - row.paper_sim_um) <= 0.15, row
    # larger idle stroke: later contact, later opening, smaller stroke
    assert [r.t_open_us for r in rows] == sorted(r.t_open_us for r in rows)
    assert [r.ours_um for r in rows] == sorted((r.ours_um for r in rows), reverse=True)
