"""The identification command lines as a user runs them."""

from __future__ import annotations

import json

import numpy as np

from estimator.io.traces import write_trace

from ..helpers import measured
from .test_cli_sim import run


def _trace(path, nu=17.2, lh=3.3, seed=1, **kw):
    inj, _ = measured(nu, lh, seed, **kw)
    write_trace(path, {"t_s": inj.t_s, "current_A": inj.current_a, "voltage_V": inj.voltage_v},
                {"preload_force_n": 28.0, "injector_id": 2})
    return path


def test_identify_json_keys(tmp_path):
    r = run("-m", "estimator", "identify", str(_trace(tmp_path / "a.csv")), "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    for k in ("nu_n_per_v", "lh_um", "cost_uvs", "t_contact_us", "t_open_us", "stroke_um", "status"):
        assert k in d
    assert d["status"] == "ok" and abs(d["lh_um"] - 3.3) < 0.3 and abs(d["nu_n_per_v"] - 17.2) < 0.05


def test_identify_bad_trace_status_and_exit_code(tmp_path):
    p = tmp_path / "bad.csv"
    t = np.arange(300) * 0.5e-6
    write_trace(p, {"t_s": t, "current_A": np.zeros(300), "voltage_V": np.zeros(300)})
    r = run("-m", "estimator", "identify", str(p), "--json")
    assert r.returncode == 1 and json.loads(r.stdout)["status"] == "rejected"
    t[7] = 9.0
    write_trace(p, {"t_s": t, "current_A": np.ones(300), "voltage_V": np.ones(300)})
    r = run("-m", "estimator", "identify", str(p))
    assert r.returncode == 1 and "wrong sampling" in r.stdout
    r = run("-m", "estimator", "identify", str(tmp_path / "missing.csv"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "cannot read trace" in r.stderr


def test_track_json_lines(tmp_path):
    files = [str(_trace(tmp_path / f"i{k}.csv", seed=10 + k)) for k in range(4)]
    r = run("-m", "estimator", "track", *files)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(x) for x in r.stdout.splitlines()]
    assert [x["file"] for x in lines] == files
    assert lines[0]["raw"]["evaluations"] > lines[1]["raw"]["evaluations"]
    for k in ("nu_n_per_v", "lh_um", "sigma_nu_n_per_v", "sigma_lh_um"):
        assert k in lines[-1]["filtered"]
    assert abs(lines[-1]["filtered"]["lh_um"] - 3.3) < 0.2


def test_calibrate_from_sim_bench_traces(tmp_path):
    r = run("-m", "sim_bench", "calibration-traces", "--out", str(tmp_path), "--temps", "0", "50", "100")
    assert r.returncode == 0, r.stderr
    out = tmp_path / "cal.toml"
    r = run("-m", "estimator", "calibrate", *sorted(str(p) for p in tmp_path.glob("calib_*.csv")), "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "[psa]" in out.read_text() and "N_u(T) = 15.00" in r.stdout


def test_plot_writes_pngs(tmp_path):
    r = run("-m", "estimator", "plot", str(_trace(tmp_path / "a.csv")), "--out", str(tmp_path / "fig"), "--grid", "9")
    assert r.returncode == 0, r.stderr
    for name in ("voltage_fit.png", "cost_contour.png"):
        assert (tmp_path / "fig" / name).read_bytes()[:4] == b"\x89PNG"
