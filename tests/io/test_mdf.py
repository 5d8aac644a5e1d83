"""MDF4 traces (asammdf): the same injection as CSV and as MF4 identifies to the same result; other
time bases are resampled; missing channels and files that are not MDF are one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from estimator.io.traces import write_trace

from ..helpers import measured
from ..system.test_cli_sim import run

asammdf = pytest.importorskip("asammdf")


def write_mf4(path, t, current, voltage, comment="preload_force_n=28.0\ninjector_id=2", t_voltage=None):
    from asammdf import MDF, Signal
    mdf = MDF(version="4.10")
    mdf.append([Signal(current, t, name="I_Amp", unit="A")], comment="amplifier")
    tv = t if t_voltage is None else t_voltage
    mdf.append([Signal(voltage if t_voltage is None else np.interp(tv, t, voltage), tv, name="U_PSA", unit="V")],
               comment="actuator")
    mdf.header.comment = comment
    mdf.save(str(path), overwrite=True)


def identify(path, *extra):
    r = run("-m", "estimator", "identify", str(path), "--json", *extra)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_mf4_identifies_like_the_csv(tmp_path):
    inj, _ = measured(17.3, 3.4, 21, window_s=150e-6)
    csv = tmp_path / "a.csv"
    write_trace(csv, {"t_s": inj.t_s, "current_A": inj.current_a, "voltage_V": inj.voltage_v},
                {"preload_force_n": 28.0, "injector_id": 2})
    mf4 = tmp_path / "a.mf4"
    write_mf4(mf4, inj.t_s + 0.125, inj.current_a, inj.voltage_v)     # an MDF time base need not start at 0
    a = identify(csv)
    b = identify(mf4, "--current-channel", "I_Amp", "--voltage-channel", "U_PSA")
    assert a["status"] == b["status"]
    for k in ("nu_n_per_v", "lh_um", "sigma_lh_um", "t_open_us"):
        assert a[k] == pytest.approx(b[k], rel=1e-6, abs=1e-9), k


def test_other_time_bases_are_resampled(tmp_path):
    inj, _ = measured(17.3, 3.4, 22, window_s=150e-6)
    mf4 = tmp_path / "b.mf4"
    # voltage logged on its own clock, 0.1 µs later: linear interpolation onto the current's grid
    write_mf4(mf4, inj.t_s, inj.current_a, inj.voltage_v, t_voltage=inj.t_s[:-1] + 0.1e-6)
    b = identify(mf4, "--current-channel", "I_Amp", "--voltage-channel", "U_PSA")
    # the 0.1 µs skew and the interpolation are a small model error the adequacy test may notice
    assert b["status"] in ("ok", "uncertain", "model_mismatch") and abs(b["lh_um"] - 3.4) < 0.3
    assert abs(b["lh_um"] - 3.4) <= 3 * b["sigma_lh_um"]


def test_mdf_errors_are_one_line(tmp_path):
    inj, _ = measured(17.3, 3.4, 23, window_s=150e-6)
    mf4 = tmp_path / "c.mf4"
    write_mf4(mf4, inj.t_s, inj.current_a, inj.voltage_v)
    r = run("-m", "estimator", "identify", str(mf4), "--current-channel", "I_Amp", "--voltage-channel", "U_x")
    assert r.returncode == 1 and "no channel 'U_x'" in r.stdout and "I_Amp" in r.stdout
    r = run("-m", "estimator", "identify", str(mf4))
    assert r.returncode == 1 and "--current-channel" in r.stdout
    bad = tmp_path / "bad.mf4"
    bad.write_bytes(b"not an mdf file at all")
    r = run("-m", "estimator", "plot", str(bad), "--out", str(tmp_path), "--current-channel", "a",
            "--voltage-channel", "b")
    assert r.returncode == 2 and r.stderr.startswith("error: cannot read MDF file") and "Traceback" not in r.stderr
