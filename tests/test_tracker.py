"""The recursive per-injection estimator: convergence, tracking, outliers, state round trip."""

from __future__ import annotations

import json

import numpy as np
import pytest

from estimator.ident.measurement import Injection
from estimator.ident.tracker import Tracker, TrackerConfig, TrackerState

from .helpers import measured


def test_converges_and_warm_updates_are_cheap(sim):
    tr = Tracker(sim=sim)
    results = [tr.update(measured(17.3, 4.2, 300 + k)[0]) for k in range(40)]
    assert results[0].evaluations > 200           # cold start: grid
    assert max(r.evaluations for r in results[1:]) < 40   # warm: a few line-search points
    assert all(r.status == "ok" for r in results)
    last = results[-1]
    assert abs(last.lh_m * 1e6 - 4.2) < 0.05 and abs(last.nu_n_per_v - 17.3) < 0.01
    assert last.sigma_lh_m < results[1].sigma_lh_m   # the filter accumulates information
    assert np.isfinite(last.t_open_s) and np.isfinite(last.stroke_m)


def test_follows_a_temperature_step_in_nu(sim):
    tr = Tracker(sim=sim)
    for k in range(10):
        tr.update(measured(16.0, 3.0, 400 + k)[0])
    for k in range(25):
        r = tr.update(measured(16.6, 3.0, 500 + k)[0])
    assert abs(r.nu_n_per_v - 16.6) < 0.02 and abs(r.lh_m * 1e6 - 3.0) < 0.1


def test_outlier_rejected_then_reacquired(sim):
    cfg = TrackerConfig(max_consecutive_outliers=3)
    tr = Tracker(cfg, sim)
    for k in range(12):
        base = tr.update(measured(17.0, 2.0, 600 + k)[0])
    other = [measured(17.0, 6.0, 700 + k)[0] for k in range(3)]
    r1 = tr.update(other[0])
    assert r1.status == "rejected" and "outlier" in r1.reason
    assert r1.lh_m == pytest.approx(base.lh_m)        # one bad injection does not move the estimate
    r2 = tr.update(other[1])
    assert r2.status == "rejected"
    r3 = tr.update(other[2])                          # persistent: the injector really changed
    assert r3.status == "ok" and "re-acquired" in r3.reason and abs(r3.lh_m * 1e6 - 6.0) < 0.3


def test_bad_trace_rejected_state_kept(sim):
    tr = Tracker(sim=sim)
    good = tr.update(measured(17.0, 2.0, 800)[0])
    inj = measured(17.0, 2.0, 801)[0]
    bad = Injection(np.full(inj.n, np.nan), inj.voltage_v, inj.dt_s)
    r = tr.update(bad)
    assert r.status == "rejected" and "NaN" in r.reason
    assert tr.states[0].accepted == 1 and tr.states[0].rejected == 1
    assert r.lh_m == good.lh_m


def test_state_round_trips_through_json_and_resumes(sim):
    tr = Tracker(sim=sim)
    for k in range(5):
        tr.update(measured(18.0, 5.0, 900 + k)[0])
    blob = json.dumps(tr.states[0].to_dict())
    tr2 = Tracker(sim=sim)
    tr2.states[0] = TrackerState.from_dict(json.loads(blob))
    r = tr2.update(measured(18.0, 5.0, 950)[0])
    assert r.evaluations < 40 and abs(r.lh_m * 1e6 - 5.0) < 0.1   # warm, not a cold start
    with pytest.raises(ValueError):
        TrackerState.from_dict({"version": 99})
    with pytest.raises(ValueError):
        TrackerState.from_dict({**tr.states[0].to_dict(), "x": [float("nan"), 1.0]})


def test_prior_and_reset(sim):
    tr = Tracker(sim=sim)
    tr.set_prior(3, 17.0, 2.0)
    inj, _ = measured(17.05, 2.1, 1000)
    r = tr.update(Injection(inj.current_a, inj.voltage_v, inj.dt_s, injector_id=3))
    assert r.evaluations < 40 and abs(r.lh_m * 1e6 - 2.1) < 0.15
    tr.reset(3)
    assert 3 not in tr.states


def test_mismatch_switches_to_robust_mode(sim):
    tr = Tracker(sim=sim)
    rs = [tr.update(measured(16.4, 5.0, 1100 + k, mismatch=True)[0]) for k in range(8)]
    assert tr.states[0].robust
    assert abs(rs[-1].lh_m * 1e6 - 5.0) < 0.5
