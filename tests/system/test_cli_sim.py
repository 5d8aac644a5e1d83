"""The sim_bench and estimator command lines as a user runs them (subprocesses)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from estimator.io.traces import read_trace, write_trace

from ..conftest import REPO


def run(*args: str, cwd=REPO) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=240)


def test_simulate_writes_trace_with_metadata(tmp_path):
    out = tmp_path / "trace.csv"
    r = run("-m", "sim_bench", "simulate", "--nu", "16.39", "--lh-um", "2.5", "--t-end-us", "300", "--out", str(out))
    assert r.returncode == 0, r.stderr
    tr = read_trace(out)
    assert list(tr.columns) == ["t_s", "current_A", "voltage_V", "s3_m", "s4_m", "mode"]
    assert tr.meta_float("nu_n_per_v") == 16.39 and tr.meta_float("lh_um") == 2.5
    assert tr.column("t_s").size == 601
    assert set(np.unique(tr.column("mode"))) >= {1.0, 2.0, 3.0}


def test_simulate_with_current_file_resamples(tmp_path):
    cur = tmp_path / "cur.csv"
    t = np.array([0.0, 20e-6, 160e-6, 180e-6, 300e-6])
    write_trace(cur, {"t_s": t, "current_A": np.array([0.0, 4.0, 4.0, 0.0, 0.0])})
    out = tmp_path / "o.csv"
    r = run("-m", "sim_bench", "simulate", "--current", str(cur), "--lh-um", "1", "--t-end-us", "250", "--out", str(out))
    assert r.returncode == 0, r.stderr
    tr = read_trace(out)
    current = tr.column("current_A")
    assert current[20] == 2.0 and current[10] == 1.0   # 10 µs and 5 µs into the 20 µs ramp to 4 A
    assert current[300] == 4.0 and current[-1] == 0.0   # 150 µs: flat part; 250 µs: after the fall
    assert np.max(tr.column("voltage_V")) > 50


def test_simulate_bad_input_one_line_nonzero(tmp_path):
    r = run("-m", "sim_bench", "simulate", "--nu", "40", "--out", str(tmp_path / "x.csv"))
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "N_u = 40.0 N/V is outside" in r.stderr
    r = run("-m", "sim_bench", "simulate", "--current", str(tmp_path / "missing.csv"), "--out", str(tmp_path / "x.csv"))
    assert r.returncode == 2 and "cannot read trace" in r.stderr


def test_table3_cli_prints_all_rows_and_writes_json(tmp_path):
    js = tmp_path / "t3.json"
    r = run("-m", "sim_bench", "table3", "--paper-only", "--json-out", str(js))
    assert r.returncode == 0, r.stderr
    for lh in ("0.6", "2.5", "6.8", "8.4"):
        assert f" {lh} " in r.stdout
    rep = json.loads(js.read_text())
    assert len(rep["paper_psa1"]) == 4 and rep["max_abs_diff_um"] <= 0.15
    assert "identified" not in rep


def test_speed_sim_cli_writes_json(tmp_path):
    js = tmp_path / "speed.json"
    r = run("-m", "sim_bench", "speed-sim", "--batch", "1", "4", "--seconds", "0.2", "--json-out", str(js))
    assert r.returncode == 0, r.stderr
    rep = json.loads(js.read_text())
    assert [row["batch"] for row in rep["results"]] == [1, 4]
    assert all(row["candidates_per_s"] > 0 for row in rep["results"])
    assert "candidates/s" in r.stdout


def test_estimator_entry_point():
    r = run("-m", "estimator", "params")
    assert r.returncode == 0 and "kp_n_per_m" in r.stdout


def test_speed_judges_its_own_targets():
    """``speed`` exits on its targets: the failures come from the measured figures, not a constant."""
    from sim_bench.benches.ident_bench import speed_failures
    from sim_bench.benches.targets import limit

    good = {"warm_median_ms": 0.2, "correction_added_ms": 0.09, "cold_median_ms": 0.9}
    assert speed_failures(good) == []
    slow = dict(good, correction_added_ms=limit("speed", "correction_added_ms") + 0.05)
    assert [f.split()[0] for f in speed_failures(slow)] == ["correction_added_ms"]
    assert len(speed_failures(dict(good, warm_median_ms=float("nan")))) == 1   # NaN is a miss, never a pass
    assert len(speed_failures(dict(good, correction_added_ms=float("nan")))) == 1


def test_one_table_of_targets_that_the_benches_judge_with():
    """sim_bench.benches.targets holds each bench's headline targets; a missing, NaN or out-of-bound figure is a
    miss; daemon-bench judges the phase at the rate asked for, learning or not."""
    from sim_bench.benches.daemon_bench import failures
    from sim_bench.benches.targets import TARGETS, limit, missed

    for bench, targets in TARGETS.items():
        assert len({t.figure for t in targets}) == len(targets) and {t.op for t in targets} <= {"<=", ">="}, bench
    assert missed("speed-sim", {"candidates_per_s_256": 25_000.0}) == []
    assert missed("speed-sim", {"candidates_per_s_256": 19_999.0})[0].startswith("candidates_per_s_256")
    assert missed("speed-sim", {"candidates_per_s_256": float("nan")}) and missed("speed-sim", {"candidates_per_s_256": None})
    ing = {"frames_per_s": 200_000.0}
    nominal = {"daemon_latency_p99_ms": 2.0, "external_latency_p99_ms": 3.0}
    assert failures(ing, {"nominal": nominal}) == []
    slow = {"nominal": dict(nominal, daemon_latency_p99_ms=limit("daemon-bench", "daemon_p99_ms") + 1)}
    assert [f.split()[0] for f in failures(ing, slow)] == ["daemon_p99_ms"]
    learning = {"self_calibration": True, "nominal": dict(nominal, daemon_latency_p99_ms=9.0),
                "adopted": {"daemon_latency_p99_ms": 6.0}}
    assert [f.split()[0] for f in failures(ing, learning)] == ["adopted_p99_ms"]


def test_a_daemon_started_from_another_directory_keeps_its_state_where_the_caller_said(tmp_path, monkeypatch):
    """The benches run the daemon in the repository; a relative state directory or configuration
    given from elsewhere must still be the caller's (a bench run from a scratch directory once shared
    one state directory with every other such run, and started from their learned models)."""
    from pathlib import Path

    from sim_bench.hardware.procs import DaemonProcess

    monkeypatch.chdir(tmp_path)
    d = DaemonProcess("virtual", Path("daemon.log"), state_dir=Path("bench-results/state"), config=Path("c.toml"))
    try:
        assert Path(d.args[d.args.index("--state-dir") + 1]) == tmp_path / "bench-results" / "state"
        assert Path(d.args[d.args.index("--config") + 1]) == tmp_path / "c.toml"
    finally:
        d.notify.sock.close()
