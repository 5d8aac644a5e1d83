"""The tracking benchmark: its scenario registry, its scoring, and the command a user runs."""

from __future__ import annotations

import json

import pytest

from sim_bench.benches import tracking_bench as tb
from sim_bench.cli import main as sim_main


def test_a_scenario_without_targets_cannot_be_registered():
    with pytest.raises(ValueError, match="no targets"):
        tb.TrackingScenario("x", 10, lambda k, t: 17.0, lambda k, t: 3.0, tb.Targets(()))
    with pytest.raises(ValueError, match="twice"):
        tb.register(tb.TRACKING["steady"])


def test_scoring_fails_a_filter_worse_than_its_measurement():
    rows = []
    for k in range(30):    # a stale published L_h 0.3 µm off while the raw estimates are right
        rows.append({"k": k, "nu": 17.0, "lh_um": 3.3, "raw_nu": 17.0, "raw_lh_um": 3.01, "nu_true": 17.0,
                     "lh_true_um": 3.0, "sigma_lh_um": 0.05, "t_open_us": 40.0, "t_open_true_us": 40.0,
                     "seconds": 1e-3, "glitch": False, "status": "ok", "outliers": 0, "robust": False})
    s = tb.score(tb.TRACKING["steady"], rows, False)
    assert not s["passed"] and any("filtered L_h RMS" in f for f in s["failures"])


def test_tracking_command_prints_raw_and_filtered_and_writes_json(tmp_path, capsys):
    out = tmp_path / "t.json"
    rc = sim_main(["tracking", "--scenario", "lh-step", "--plant", "matched", "--json-out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0 and "dLh raw" in text and "PASS" in text
    rep = json.loads(out.read_text())["reports"][0]["summary"]
    assert rep["passed"] and rep["rms_lh_um"] <= rep["rms_raw_lh_um"]
