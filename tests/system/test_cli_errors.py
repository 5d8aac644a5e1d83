"""Every CLI error path: one readable line and a non-zero exit; batches go on past a
bad file and report it; what `calibrate` writes is usable with --params."""

from __future__ import annotations

import json

import pytest

from .test_cli_ident import _trace
from .test_cli_sim import run


def one_error_line(r, code: int = 2) -> str:
    assert r.returncode == code, (r.stdout, r.stderr)
    lines = [x for x in r.stderr.strip().splitlines() if not x.startswith(("20", "WARNING", "INFO"))]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in r.stderr, r.stderr
    return lines[0]


@pytest.fixture(scope="module")
def latin1(tmp_path_factory):
    p = tmp_path_factory.mktemp("l1") / "latin1.csv"
    p.write_bytes("# Messung für Injektor\nt_s,current_A,voltage_V\n0,0,0\n".encode("latin-1"))
    return p


def test_latin1_trace_is_a_clear_error_everywhere(tmp_path, latin1):
    r = run("-m", "estimator", "identify", str(latin1))
    assert r.returncode == 1 and "not UTF-8" in r.stdout and "Traceback" not in r.stderr
    assert "not UTF-8" in one_error_line(run("-m", "estimator", "plot", str(latin1), "--out", str(tmp_path)))
    assert "not UTF-8" in one_error_line(run("-m", "estimator", "calibrate", str(latin1), str(latin1)))


def test_track_batch_goes_on_past_a_bad_file(tmp_path, latin1):
    a = str(_trace(tmp_path / "a.csv", seed=3))
    b = str(_trace(tmp_path / "b.csv", seed=4))
    r = run("-m", "estimator", "track", a, str(latin1), str(tmp_path / "missing.csv"), b)
    assert r.returncode == 1
    lines = [json.loads(x) for x in r.stdout.splitlines()]
    assert [x["status"] for x in lines] == ["ok", "rejected", "rejected", lines[3]["status"]]
    assert lines[3]["status"] in ("ok", "uncertain") and lines[3]["raw"]["evaluations"] < lines[0]["raw"]["evaluations"]
    assert "2 of 4 file(s) could not be read" in r.stderr


@pytest.mark.parametrize("grid", ["0", "1", "-3"])
def test_plot_grid_out_of_range(tmp_path, grid):
    t = str(_trace(tmp_path / "a.csv"))
    assert "--grid" in one_error_line(run("-m", "estimator", "plot", t, "--out", str(tmp_path / "f"), "--grid", grid))


@pytest.fixture(scope="module")
def calib(tmp_path_factory):
    d = tmp_path_factory.mktemp("cal")
    r = run("-m", "sim_bench", "calibration-traces", "--out", str(d), "--temps", "20", "80")
    assert r.returncode == 0, r.stderr
    return sorted(d.glob("calib_*.csv"))


def test_calibrate_bad_inputs(tmp_path, calib):
    same = tmp_path / "same.csv"
    same.write_text(calib[0].read_text())
    assert "different temperatures" in one_error_line(run("-m", "estimator", "calibrate", str(calib[0]), str(same)))
    assert "window 0" in one_error_line(run("-m", "estimator", "calibrate", *map(str, calib), "--window-us", "0"))


def test_calibrate_output_is_used_by_params(tmp_path, calib):
    out = tmp_path / "cal.toml"
    r = run("-m", "estimator", "calibrate", *map(str, calib), "--out", str(out))
    assert r.returncode == 0, r.stderr
    t = str(_trace(tmp_path / "a.csv"))
    r = run("-m", "estimator", "identify", t, "--json", "--params", str(out))
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["status"] in ("ok", "uncertain")
    r = run("-m", "sim_bench", "simulate", "--out", str(tmp_path / "s.csv"), "--params", str(out))
    assert r.returncode == 0, r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text("[psa]\n")
    assert "parameter" in one_error_line(run("-m", "estimator", "identify", t, "--params", str(bad)))


def test_simulate_absurd_idle_stroke(tmp_path):
    assert "--lh-um" in one_error_line(run("-m", "sim_bench", "simulate", "--lh-um", "1e9", "--out",
                                           str(tmp_path / "x.csv")))


def test_bench_zero_seconds(tmp_path):
    assert "--seconds 0" in one_error_line(run("-m", "sim_bench", "bench", "--seconds", "0", "--out", str(tmp_path)))


def test_selfcal_absurd_part_counts():
    assert "--minima 5000" in one_error_line(run("-m", "sim_bench", "selfcal", "--minima", "5000"))
    assert "--refusals 5000" in one_error_line(run("-m", "sim_bench", "selfcal", "--refusals", "5000"))


def test_replay_skips_a_garbage_line_and_names_it(tmp_path):
    import can

    from ..helpers import injection_messages
    cap = tmp_path / "cap.log"
    w = can.CanutilsLogWriter(str(cap), channel="vcan0")
    for msg in injection_messages(1, 3, 80, frame_dt_s=1e-4, gap_s=0.1):
        w.on_message_received(msg)
    w.stop()
    lines = cap.read_text().splitlines()
    lines.insert(5, "(1000.1) vcan0 this is not a frame")
    lines.insert(9, "\x00\x01garbage")
    cap.write_text("\n".join(lines) + "\n")
    jl = tmp_path / "out.jsonl"
    r = run("-m", "estimator", "replay", str(cap), "--json", str(jl))
    assert r.returncode == 1
    assert f"{cap}:6: skipped" in r.stderr and f"{cap}:10: skipped" in r.stderr
    assert "2 line(s)" in r.stderr and "first at line 6" in r.stderr
    # the injection whose block line was garbled is lost (counted), the others are estimated
    assert len(jl.read_text().splitlines()) >= 2


def test_tracking_preload_is_an_option_of_the_lots_life():
    assert "lot-life" in one_error_line(run("-m", "sim_bench", "tracking", "--scenario", "steady", "--preload", "100"))
    r = run("-m", "sim_bench", "tracking", "--scenario", "lot-life", "--preload", "5")
    assert r.returncode == 2 and "outside 28-300 N" in r.stderr and "Traceback" not in r.stderr
