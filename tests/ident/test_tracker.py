"""The recursive per-injection estimator: convergence, drift, steps, glitches, honest status, state round trip."""

from __future__ import annotations

import json

import numpy as np
import pytest

from estimator.ident.config import TrackerConfig
from estimator.ident.measurement import Injection
from estimator.ident.status import Status
from estimator.ident.tracking import kalman
from estimator.ident.tracking.tracker import Tracker, TrackerState

from ..helpers import COLD_MIN_EVALUATIONS, WARM_MAX_EVALUATIONS, measured, record_codes


def at(inj: Injection, time_s: float, temperature_c: float = float("nan"), gain: float = 1.0) -> Injection:
    """The injection stamped with a time (s) and temperature (degC); ``gain`` scales the measured current."""
    return Injection(inj.current_a * gain, inj.voltage_v, inj.dt_s, inj.f_open_n, 0, 0, temperature_c, time_s)


def test_converges_and_warm_updates_are_cheap(sim):
    tr = Tracker(sim=sim)
    results = [tr.update(at(measured(17.3, 4.2, 300 + k)[0], 0.04 * k)) for k in range(40)]
    assert results[0].evaluations >= COLD_MIN_EVALUATIONS   # cold start
    assert max(r.evaluations for r in results[1:]) <= WARM_MAX_EVALUATIONS   # warm: a few compiled cycles
    assert all(r.status == Status.OK for r in results)
    last = results[-1]
    assert abs(last.lh_m * 1e6 - 4.2) < 0.05 and abs(last.nu_n_per_v - 17.3) < 0.01
    assert last.sigma_lh_m < results[1].sigma_lh_m   # the filter accumulates information
    assert np.isfinite(last.t_open_s) and np.isfinite(last.stroke_m)


def test_fast_ramp_followed_without_lag_or_rejection(sim):
    """N_u +0.068 N/V per injection at 1 injection/s (15.5 -> 19.5 over 60), no temperature."""
    tr = Tracker(sim=sim)
    nu = lambda k: 16.0 + 0.068 * max(k - 10, 0)   # noqa: E731
    res = [tr.update(at(measured(nu(k), 3.0, 1200 + k)[0], float(k))) for k in range(30)]
    assert not any(r.status == Status.REJECTED for r in res)
    for k, r in enumerate(res):
        assert abs(r.lh_m * 1e6 - 3.0) < 0.1, k
        if k >= 12:                                 # from the 3rd injection after the ramp's start
            assert abs(r.nu_n_per_v / nu(k) - 1) < 1e-3, k
    assert res[-1].rate_n_per_v_s == pytest.approx(0.068, rel=0.2)   # the drift rate was learned


def test_step_taken_at_the_second_injection_and_never_published_stale(sim):
    tr = Tracker(sim=sim)
    for k in range(20):
        tr.update(at(measured(17.0, 3.0, 1300 + k)[0], 0.04 * k))
    first = tr.update(at(measured(17.0, 4.0, 1400)[0], 0.8))
    assert first.status == Status.UNCONFIRMED        # not the old estimate with status ok
    assert abs(first.lh_m * 1e6 - 4.0) < 0.2         # its own estimate: 1 µm off the filter
    second = tr.update(at(measured(17.0, 4.0, 1401)[0], 0.84))
    assert second.status == Status.OK and "L_h confirmed" in second.reason
    assert abs(second.lh_m * 1e6 - 4.0) < 0.15 and second.outliers == 0
    assert (first.accepted, second.accepted) == (0, 2)   # the doubt is counted once, when confirmed
    assert abs(second.nu_n_per_v - 17.0) < 0.01      # N_u kept what it knew


def test_glitch_rejected_counted_and_estimate_unmoved(sim):
    tr = Tracker(sim=sim)
    for k in range(20):
        before = tr.update(at(measured(17.2, 4.0, 1500 + k)[0], 0.04 * k))
    glitch = tr.update(at(measured(17.2, 4.0, 1600)[0], 0.8, gain=1.2))   # 20 % current-gain error
    assert glitch.status == Status.REJECTED and glitch.outliers == 1 and "outlier" in glitch.reason
    wear_m = tr.states[0].x[kalman.WEAR] * 1e-6       # the filter's own prediction: one injection's wear on
    assert glitch.lh_m == pytest.approx(before.lh_m + wear_m, abs=1e-9) and not tr.states[0].robust
    after = tr.update(at(measured(17.2, 4.0, 1601)[0], 0.84))
    assert after.status == Status.OK and abs(after.lh_m * 1e6 - 4.0) < 0.05


def test_unconfirmed_doubt_discarded_when_the_next_injection_agrees(sim):
    tr = Tracker(sim=sim)
    for k in range(15):
        tr.update(at(measured(17.0, 2.0, 1700 + k)[0], 0.04 * k))
    odd = tr.update(at(measured(17.0, 3.0, 1800)[0], 0.6))   # a clean fit, 1 µm away, once
    assert odd.status == Status.UNCONFIRMED and odd.outliers == 0
    back = tr.update(at(measured(17.0, 2.0, 1801)[0], 0.64))
    assert back.status == Status.OK and back.outliers == 1     # the doubt is counted as an outlier now
    assert (odd.accepted, back.accepted) == (0, 1)
    assert abs(back.lh_m * 1e6 - 2.0) < 0.05                   # and never entered the filter
    assert tr.states[0].pending is None


def test_disagreeing_doubts_reacquire(sim):
    tr = Tracker(TrackerConfig(max_consecutive_outliers=3), sim)
    for k in range(12):
        tr.update(at(measured(17.0, 2.0, 600 + k)[0], 0.04 * k))
    results = [tr.update(at(measured(17.0, lh, 700 + k)[0], 0.5 + 0.04 * k)) for k, lh in enumerate((5.0, 8.0, 3.5))]
    assert [r.status for r in results[:2]] == [Status.UNCONFIRMED, Status.UNCONFIRMED]
    assert results[1].outliers == 1                  # 5 µm and 8 µm do not agree: the first was an outlier
    assert "re-acquired" in results[2].reason and abs(results[2].lh_m * 1e6 - 3.5) < 0.3


@pytest.mark.parametrize("nu", [15.03, 15.15, 20.92])
def test_cold_start_near_the_range_edges_is_not_trapped(sim, nu):
    tr = Tracker(sim=sim)
    res = [tr.update(at(measured(nu, 3.0, 1900 + k)[0], 0.04 * k)) for k in range(3)]
    assert not tr.states[0].robust and not res[0].raw.robust    # no false model-error alarm
    assert res[0].status == Status.OK
    assert abs(res[0].nu_n_per_v / nu - 1) < 3e-3 and abs(res[0].lh_m * 1e6 - 3.0) < 0.3


def test_large_sigma_is_uncertain_not_ok(sim):
    tr = Tracker(sim=sim)
    inj, _ = measured(17.0, 4.0, 2100, adc=__import__("sim_bench.hardware.plant", fromlist=["AdcConfig"]).AdcConfig(
        voltage_noise_v=1.0))
    r = tr.update(at(inj, 0.0))
    assert r.sigma_lh_m * 1e6 > 0.25 and r.status == Status.UNCERTAIN and "sigma" in r.reason


def test_temperature_slope_learned_and_used(sim):
    """A warm-up with FuelTemperature: the slope moves from the prior (0.06) toward the injector's (0.045)."""
    tr = Tracker(sim=sim)
    for k in range(120):
        temp = 20.0 + 0.5 * k
        r = tr.update(at(measured(16.0 + 0.045 * temp, 3.0, 2200 + k)[0], float(k), temp))
        assert abs(r.nu_n_per_v / (16.0 + 0.045 * temp) - 1) < 1e-3
    assert 0.040 < r.slope_n_per_v_degc < 0.058


def test_robust_mode_switches_on_and_off_again(sim):
    tr = Tracker(TrackerConfig(robust_off_after=10), sim)
    for k in range(6):
        tr.update(at(measured(16.4, 5.0, 1100 + k, mismatch=True)[0], 0.04 * k))
    assert tr.states[0].robust
    for k in range(14):
        tr.update(at(measured(16.4, 5.0, 1150 + k)[0], 0.3 + 0.04 * k))
    assert not tr.states[0].robust                    # the evidence is gone


def test_a_cold_start_that_chose_the_robust_cost_switches_the_mode_at_once(sim, monkeypatch):
    """A first estimate with model error puts the tracker in robust mode with it: the injections after
    it are warm robust updates, none rejected, and the cold start runs once (it used to run twice and
    leave the tracker plain, so the next two injections were rejected as outliers)."""
    import estimator.ident.tracking.recursive as tracker_mod
    colds = []
    real = tracker_mod._cold_estimate
    monkeypatch.setattr(tracker_mod, "_cold_estimate", lambda *a: colds.append(1) or real(*a))
    tr = Tracker(sim=sim)
    results = [tr.update(at(measured(17.3, 4.2, 500 + k, mismatch=True)[0], 0.04 * k)) for k in range(6)]
    assert results[0].raw.robust and tr.states[0].robust and len(colds) == 1
    assert all(r.status == Status.MODEL_MISMATCH and r.raw.robust and r.outliers == 0 for r in results)
    assert results[-1].sigma_lh_m < results[0].sigma_lh_m      # one filter since the first injection
    assert abs(results[-1].lh_m * 1e6 - 4.2) < 0.15


def test_a_cold_starts_valve_prediction_is_published_not_made_again(sim, monkeypatch):
    """The first injection's published contact, opening and stroke are its cold start's own prediction
    (one prediction simulated, not two, the numbers a prediction at the published point gives); a warm
    update's are predicted for its filtered point."""
    import estimator.ident.tracking.recursive as tracker_mod
    from estimator.ident.fit.idle_stroke import predict_valve
    calls = []
    monkeypatch.setattr(tracker_mod, "predict_valve", lambda *a: calls.append(1) or predict_valve(*a))
    tr = Tracker(sim=sim)
    inj = measured(17.0, 3.0, 820)[0]
    first = tr.update(inj)
    assert first.raw.evaluations >= COLD_MIN_EVALUATIONS and calls == [] and np.isfinite(first.stroke_m)
    assert (first.t_contact_s, first.t_open_s, first.stroke_m) == predict_valve(sim, inj, first.nu_n_per_v,
                                                                                first.lh_m)
    second = tr.update(at(measured(17.0, 3.0, 821)[0], 0.04))
    assert second.raw.evaluations <= WARM_MAX_EVALUATIONS and calls == [1] and np.isfinite(second.stroke_m)


def test_bad_trace_rejected_state_kept(sim):
    tr = Tracker(sim=sim)
    good = tr.update(measured(17.0, 2.0, 800)[0])
    inj = measured(17.0, 2.0, 801)[0]
    bad = Injection(np.full(inj.n, np.nan), inj.voltage_v, inj.dt_s)
    r = tr.update(bad)
    assert r.status == Status.REJECTED and "NaN" in r.reason and r.outliers == 0
    assert tr.states[0].accepted == 1 and tr.states[0].rejected == 1
    assert r.lh_m == pytest.approx(good.lh_m, abs=1e-9)


def test_state_round_trips_through_json_and_resumes(sim):
    tr = Tracker(sim=sim)
    for k in range(5):
        tr.update(measured(18.0, 5.0, 900 + k)[0])
    blob = json.dumps(tr.states[0].to_dict(), allow_nan=False)   # strict JSON: unknowns are null
    tr2 = Tracker(sim=sim)
    tr2.states[0] = TrackerState.from_dict(json.loads(blob))
    r = tr2.update(measured(18.0, 5.0, 950)[0])
    assert r.evaluations <= WARM_MAX_EVALUATIONS and abs(r.lh_m * 1e6 - 5.0) < 0.1   # warm, not a cold start


@pytest.mark.parametrize("change", [
    {"version": 99}, {"x": [float("nan"), 1.0, 0.0, 0.06]}, {"x": [17.0, 3.0]}, {"x": [100.0, 500.0, 0.0, 0.06]},
    {"accepted": "many"}, {"accepted": -1}, {"robust": "yes"}, {"p": [[1, 0], [0, 1]]},
    {"p": [[-1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, {"steps": [0.0, 1.0]},
    {"time_s": "now"}, {"pending": [1, 2]}, {"pending": {"z": [1.0], "r": [[1, 0], [0, 1]], "counter": 1}},
    {"directions": "x"},
])
def test_state_validation_rejects_every_bad_field(sim, change):
    tr = Tracker(sim=sim)
    tr.update(measured(18.0, 5.0, 990)[0])
    d = {**tr.states[0].to_dict(), **change}
    with pytest.raises(ValueError):
        TrackerState.from_dict(d)


def test_prior_and_reset(sim):
    tr = Tracker(sim=sim)
    tr.set_prior(3, 17.0, 2.0)
    inj, _ = measured(17.05, 2.1, 1000)
    r = tr.update(Injection(inj.current_a, inj.voltage_v, inj.dt_s, injector_id=3))
    assert r.evaluations <= WARM_MAX_EVALUATIONS and abs(r.lh_m * 1e6 - 2.1) < 0.15
    tr.reset(3)
    assert 3 not in tr.states


def test_warm_up_runs_a_cold_start_and_compiled_warm_updates_without_touching_the_states(monkeypatch):
    from estimator.ident.fit import fit_kernel, local_fit
    codes = record_codes(monkeypatch, local_fit, "run_cycle")
    tr = Tracker(TrackerConfig())
    tr.set_prior(3, 17.0, 2.0)
    before = tr.states[3].to_dict()
    tr.warm_up()
    assert list(tr.states) == [3] and tr.states[3].to_dict() == before
    assert codes == [fit_kernel.FIT] * 2      # both warm updates were one compiled cycle each
    assert len(tr.pool) == 1                           # the default sample period's simulator, shared


def test_a_state_saved_before_the_wear_rate_loads_without_wear():
    """A daemon's state file written by a filter of four states (no wear rate) still loads: no wear,
    the wear rate's prior variance, everything else as it was saved."""
    from estimator.ident.tracking.tracker_state import wear_variance

    saved = TrackerState().with_prior(17.5, 3.2).to_dict()
    saved["x"] = saved["x"][:4]
    saved["p"] = [row[:4] for row in saved["p"][:4]]
    back = TrackerState.from_dict(json.loads(json.dumps(saved)))
    assert back.x[:4] == saved["x"] and back.x[kalman.WEAR] == 0.0
    assert back.p[kalman.WEAR][kalman.WEAR] == wear_variance(TrackerConfig())
    assert [row[:4] for row in back.p[:4]] == saved["p"]
    assert Tracker().restore({0: back}) == []


def test_a_refined_model_keeps_what_the_filter_learned_of_the_part_and_a_new_model_does_not(sim):
    """Adopted as a refinement of the same part's model, the injector is re-acquired cold (N_u and L_h
    under another model are biased differently) with the wear rate and temperature slope it had
    learned; a model for a new part starts them from their priors."""
    def worn(tr: Tracker, first: int, n: int) -> None:
        for k in range(first, first + n):
            tr.update(at(measured(17.0, 3.0 + 0.01 * k, 3100 + k)[0], float(k)))

    refined, new = Tracker(sim=sim), Tracker(sim=sim)
    worn(refined, 0, 30)
    learned = list(refined.states[0].x), [row[:] for row in refined.states[0].p]
    assert 0.006 < learned[0][kalman.WEAR] < 0.014       # it learned the part's 0.01 µm per injection
    new.states[0] = TrackerState.from_dict(refined.states[0].to_dict())
    refined.adopt(0, refined.params, refined=True)
    new.adopt(0, new.params)
    worn(refined, 30, 1)
    worn(new, 30, 1)
    for k in (kalman.SLOPE, kalman.WEAR):
        assert refined.states[0].x[k] == learned[0][k] and refined.states[0].p[k][k] == learned[1][k][k]
    assert new.states[0].x[kalman.WEAR] == 0.0 and new.states[0].updates == 1   # a cold start for both
    assert refined.states[0].updates == 1
    worn(refined, 31, 9)
    worn(new, 31, 9)
    assert refined.states[0].p[kalman.LH][kalman.LH] < 0.7 * new.states[0].p[kalman.LH][kalman.LH]


def test_a_state_carried_to_a_refined_model_round_trips_and_is_checked_when_restored():
    """A carried state (not yet re-acquired) is strict JSON and loads; a carried wear rate beyond its
    bound, or a negative variance, does not."""
    from estimator.ident.tracking.tracker_state import carried_over

    carried = carried_over(TrackerState().with_prior(17.5, 3.2))
    carried.x[kalman.WEAR] = 0.004
    blob = json.dumps(carried.to_dict(), allow_nan=False)
    back = TrackerState.from_dict(json.loads(blob))
    assert not back.initialized and back.x[kalman.WEAR] == 0.004 and np.isnan(back.x[kalman.LH])
    assert Tracker().restore({0: back}) == []
    back.x[kalman.WEAR] = 0.5
    assert "wear rate" in Tracker().restore({0: back})[0]
    back.x[kalman.WEAR], back.p[kalman.SLOPE][kalman.SLOPE] = 0.004, -1e-6
    assert "variances" in Tracker().restore({0: back})[0]
