"""Calibration (eq. 25) round trip and temperature adaptation (eq. 26)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.ident.fit.adaptation import adapt_nu
from estimator.ident.learning.calibration import CalibrationTrace, calibrate, to_toml
from estimator.ident.measurement import Injection
from estimator.model.drive import sample_times, standard_drive
from estimator.model.parameters import InjectorParameters
from estimator.model.psa_lti import simulate_psa

DT = 0.5e-6


def test_psa_lti_equals_fast_simulator_without_contact(params, sim):
    t = sample_times(200e-6)
    cur = standard_drive(t)
    u, s3 = simulate_psa(params, 16.39, params.psa.resistance_ohm(16.39), cur, DT)
    r = sim.simulate(cur, 16.39, 1.0, exact=True)
    assert np.max(np.abs(u - r.voltage_v[0])) < 1e-8
    assert np.max(np.abs(s3 - r.s3_m[0])) < 1e-14


def test_calibration_recovers_known_parameters(params, tmp_path):
    true = InjectorParameters(dataclasses.replace(params.psa, kp_n_per_m=64e6, ks_n_per_m=115e6, rb_v2s_per_mn=3.0,
                                                  r0a_ohm=1500.0, r0b_v_per_n=0.44), params.valve)
    rng = np.random.default_rng(0)
    t = sample_times(200e-6)
    cur = standard_drive(t)
    traces = []
    for temp in (0.0, 30.0, 60.0, 100.0):
        nu = 15.0 + 0.06 * temp
        u, s3 = simulate_psa(true, nu, true.psa.resistance_ohm(nu), cur, DT)
        traces.append(CalibrationTrace(Injection(cur, u + 0.02 * rng.standard_normal(u.size), DT), s3, temp))
    res = calibrate(traces, params, polish_l1=False)
    assert res.kp_n_per_m == pytest.approx(64e6, rel=2e-3)
    assert res.ks_n_per_m == pytest.approx(115e6, rel=2e-3)
    assert res.rb_v2s_per_mn == pytest.approx(3.0, rel=1e-2)
    assert res.nu_of_t[0] == pytest.approx(15.0, abs=0.01) and res.nu_of_t[1] == pytest.approx(0.06, rel=1e-3)
    assert res.r0a_ohm == pytest.approx(1500.0, rel=0.03) and res.r0b_v_per_n == pytest.approx(0.44, rel=0.01)
    path = tmp_path / "p.toml"
    path.write_text(to_toml(res, params))
    loaded = InjectorParameters.from_toml(path)
    assert loaded.psa.kp_n_per_m == pytest.approx(res.kp_n_per_m)


def test_calibration_needs_two_traces(params):
    with pytest.raises(ValueError, match="at least two"):
        calibrate([], params)


@pytest.mark.parametrize("nu", [15.3, 17.9, 20.6])
def test_adaptation_recovers_nu(params, sim, nu):
    t = sample_times(200e-6)
    cur = standard_drive(t)
    u, _ = simulate_psa(params, nu, params.psa.resistance_ohm(nu), cur, DT)
    u = u + 0.1 * np.random.default_rng(1).standard_normal(u.size)
    res = adapt_nu(Injection(cur, u, DT), sim)
    assert res.status == "ok"
    assert abs(res.nu_n_per_v - nu) < 5 * res.sigma_nu + 1e-3


def test_adaptation_rejects_bad_trace(sim):
    res = adapt_nu(Injection(np.zeros(400), np.zeros(400), DT), sim)
    assert res.status == "rejected" and "flat" in res.message
