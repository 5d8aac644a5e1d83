"""Captures in every python-can format replay to the same estimates; outputs are written in the
format their suffix names; an unknown suffix is refused in one line."""

from __future__ import annotations

import csv
import json

import can
import pytest

from ..helpers import injection_messages
from ..system.test_cli_sim import run

SUFFIXES = (".log", ".asc", ".blf", ".csv", ".mf4")   # .trc: python-can writes no CAN FD to it (refused below)


@pytest.fixture(scope="module")
def messages():
    return injection_messages(2, 4, 90)


def write(path, messages):
    with can.Logger(str(path)) as w:
        for m in messages:
            w.on_message_received(m)


def replayed(path, tmp_path, *extra):
    jl = tmp_path / f"{path.name}.jsonl"
    r = run("-m", "estimator", "replay", str(path), "--json", str(jl), *extra)
    assert r.returncode == 0, r.stderr
    return [json.loads(x) for x in jl.read_text().splitlines()]


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_every_format_replays_to_the_same_estimates(tmp_path, messages, suffix):
    ref_path = tmp_path / "ref.log"
    write(ref_path, messages)
    ref = replayed(ref_path, tmp_path)
    assert len(ref) == 4
    path = tmp_path / f"capture{suffix}"
    write(path, messages)
    got = replayed(path, tmp_path)
    assert [(g["counter"], g["filtered"]["lh_um"]) for g in got] == [(r["counter"], r["filtered"]["lh_um"]) for r in ref]


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_output_frames_in_the_format_of_the_suffix(tmp_path, messages, suffix):
    cap = tmp_path / "cap.log"
    write(cap, messages)
    out = tmp_path / f"out{suffix}"
    replayed(cap, tmp_path, "--out", str(out))
    frames = list(can.LogReader(str(out)))
    assert len(frames) == 4 * 4                       # state, quality, prediction, drive correction per injection
    assert {f.arbitration_id for f in frames} == {0x200, 0x201, 0x202, 0x204}


def test_csv_table_and_unknown_suffixes(tmp_path, messages):
    cap = tmp_path / "cap.blf"
    write(cap, messages)
    table = tmp_path / "est.csv"
    r = run("-m", "estimator", "replay", str(cap), "--csv", str(table))
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(table.open()))
    assert len(rows) == 4 and rows[0]["injector_id"] == "2" and abs(float(rows[-1]["lh_um"]) - 3.0) < 0.2
    r = run("-m", "estimator", "replay", str(cap), "--out", str(tmp_path / "x.trc"))
    assert r.returncode == 2 and "no CAN FD" in r.stderr
    r = run("-m", "estimator", "replay", str(cap), "--out", str(tmp_path / "x.pcap"))
    assert r.returncode == 2 and "unknown suffix '.pcap'" in r.stderr and r.stderr.count("\n") == 1
    bad = tmp_path / "cap.xyz"
    bad.write_text("")
    r = run("-m", "estimator", "replay", str(bad))
    assert r.returncode == 2 and "unknown suffix '.xyz'" in r.stderr


def test_plot_capture_draws_one_series_per_injector(tmp_path, messages):
    from estimator.plots.capture import series
    cap = tmp_path / "cap.log"
    write(cap, messages)
    out = tmp_path / "est.blf"
    replayed(cap, tmp_path, "--out", str(out))
    s = series(out)
    assert set(s) == {2} and len(s[2]["lh"]) == 4 and len(s[2]["t_open"]) == 4
    png = tmp_path / "fig.png"
    r = run("-m", "estimator", "plot-capture", str(out), "--out", str(png))
    assert r.returncode == 0, r.stderr
    assert png.read_bytes()[:4] == b"\x89PNG"
    r = run("-m", "estimator", "plot-capture", str(cap), "--out", str(png))     # injection frames only
    assert r.returncode == 2 and "no estimates" in r.stderr


def test_plot_estimates_draws_the_rows_replay_wrote(tmp_path, messages):
    cap = tmp_path / "cap.blf"
    write(cap, messages)
    table = tmp_path / "est.csv"
    assert run("-m", "estimator", "replay", str(cap), "--csv", str(table)).returncode == 0
    png = tmp_path / "est.png"
    r = run("-m", "estimator", "plot-estimates", str(table), "--out", str(png))
    assert r.returncode == 0, r.stderr
    assert png.read_bytes()[:4] == b"\x89PNG"
    not_rows = tmp_path / "trace.csv"
    not_rows.write_text("t_s,current_A,voltage_V\n0,0,0\n")
    r = run("-m", "estimator", "plot-estimates", str(not_rows), "--out", str(png))
    assert r.returncode == 2 and "not the estimator's rows" in r.stderr and r.stderr.count("\n") == 1
