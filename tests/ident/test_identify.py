"""Idle-stroke detection (eq. 28) on simulated traces: accuracy, model-error handling, bounds, bad data."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.ident.config import IdentConfig
from estimator.ident.fit.idle_stroke import identify
from estimator.ident.measurement import Injection

from ..helpers import measured


@pytest.mark.parametrize("nu,lh_um,seed", [(16.39, 0.6, 1), (18.5, 7.5, 2), (15.6, -1.2, 3), (20.4, 3.0, 4),
                                           (17.0, -0.4, 5)])
def test_recovers_known_parameters(sim, nu, lh_um, seed):
    inj, truth = measured(nu, lh_um, seed)
    est = identify(inj, sim)
    assert est.status == "ok" and not est.robust
    # within 4 reported standard deviations, and the deviations themselves are small
    assert abs(est.lh_m * 1e6 - lh_um) <= 4 * est.sigma_lh_m * 1e6 + 0.01
    assert abs(est.nu_n_per_v - nu) <= 4 * est.sigma_nu + 1e-3
    assert est.sigma_lh_m < 0.2e-6 and est.sigma_nu / nu < 0.001
    assert abs(est.t_open_s - truth.t_open_s) < 2e-6
    assert abs(est.stroke_m - truth.stroke_m) < 0.3e-6


def test_reported_sigma_is_consistent_with_the_scatter(sim):
    errs, sig = [], []
    for seed in range(12):
        inj, _ = measured(17.5, 4.0, 100 + seed)
        est = identify(inj, sim)
        errs.append(est.lh_m * 1e6 - 4.0)
        sig.append(est.sigma_lh_m * 1e6)
    ratio = np.sqrt(np.mean(np.square(errs))) / np.mean(sig)
    assert 0.4 < ratio < 2.0


def test_sigma_covers_the_measured_currents_noise(sim, monkeypatch):
    """The simulation is driven by the measured current: at 0.02 A of current noise the N_u errors were
    1.8 times their voltage-noise-only sigma. With the current's noise in sigma they are covered."""
    from estimator.ident.fit import idle_stroke
    from sim_bench.hardware.plant import AdcConfig, Plant, PlantConfig

    def z_rms() -> float:
        plant = Plant(PlantConfig(window_s=150e-6, adc=AdcConfig(current_noise_a=0.02)))
        rng = np.random.default_rng(3)
        z = []
        for _ in range(60):
            nu, lh = float(rng.uniform(15.0, 21.0)), float(rng.uniform(0.0, 9.0)) * 1e-6
            m = plant.measure(nu, lh, 28.0, rng)
            est = identify(Injection(m.current_a, m.voltage_v, m.dt_s, 28.0), sim)
            z.append((est.nu_n_per_v - nu) / est.sigma_nu)
        return float(np.sqrt(np.mean(np.square(z))))

    assert 0.7 < z_rms() < 1.3
    sensitivities = idle_stroke.sensitivities
    monkeypatch.setattr(idle_stroke, "sensitivities", lambda *a: (sensitivities(*a)[0], None))   # the current's noise left out
    assert z_rms() > 1.5


@pytest.mark.parametrize("nu,lh_um,seed", [(16.39, 2.5, 11), (18.0, 8.5, 12), (16.0, -0.5, 13)])
def test_model_error_detected_and_absorbed(sim, nu, lh_um, seed):
    inj, _ = measured(nu, lh_um, seed, mismatch=True)
    plain = identify(inj, sim, IdentConfig(robust="off"))
    est = identify(inj, sim)
    assert est.robust and est.model_error_stat > 40
    assert abs(est.lh_m * 1e6 - lh_um) <= 0.5
    # the plain model is pulled away by the hysteresis it does not have
    assert abs(plain.lh_m * 1e6 - lh_um) > abs(est.lh_m * 1e6 - lh_um)


def test_no_false_model_error_on_matched_plant(sim):
    flags = [identify(measured(17.0, 3.0, 200 + s)[0], sim).robust for s in range(6)]
    assert not any(flags)


def test_bounds_are_respected(sim):
    inj, _ = measured(16.0, 3.0, 21)
    est = identify(inj, sim, IdentConfig(nu_bounds_n_per_v=(17.0, 21.0)))
    assert est.status == "at_bound" and est.nu_n_per_v == pytest.approx(17.0)
    est = identify(inj, sim, IdentConfig(lh_bounds_um=(4.0, 10.0)))
    assert est.status == "at_bound" and est.lh_m == pytest.approx(4e-6)


def test_infeasible_region_is_not_crashed_into(sim):
    # true L_h = -2.3 µm is feasible at 28 N; a low lower bound reaches into the infeasible region
    inj, _ = measured(16.5, -2.3, 22)
    est = identify(inj, sim, IdentConfig(lh_bounds_um=(-5.0, 10.0)))
    assert est.status in ("ok", "at_bound")
    assert est.lh_m > -2.64e-6 and abs(est.lh_m * 1e6 + 2.3) < 0.3


def _good():
    inj, _ = measured(17.0, 3.0, 30)
    return inj


@pytest.mark.parametrize("mutate,reason", [
    (lambda i: Injection(np.where(np.arange(i.n) == 50, np.nan, i.current_a), i.voltage_v, i.dt_s), "NaN"),
    (lambda i: Injection(i.current_a[:40], i.voltage_v[:40], i.dt_s), "too short"),
    (lambda i: Injection(np.zeros(i.n), i.voltage_v, i.dt_s), "flat current"),
    (lambda i: Injection(i.current_a, i.voltage_v * 100, i.dt_s), "out of range"),
    (lambda i: Injection(i.current_a, i.voltage_v[:-3], i.dt_s), "differ in length"),
    (lambda i: Injection(i.current_a, i.voltage_v, 1e-6), "does not match"),
    (lambda i: Injection(i.current_a, i.voltage_v, i.dt_s, f_open_n=float("nan")), "preload"),
])
def test_bad_traces_rejected_with_reason(sim, mutate, reason):
    est = identify(mutate(_good()), sim)
    assert est.status == "rejected" and reason in est.message


def test_wrong_sampling_rejected_on_construction():
    t = np.arange(300) * 0.5e-6
    t[100] += 0.2e-6
    with pytest.raises(ValueError, match="wrong sampling"):
        Injection.from_samples(t, np.ones(300), np.ones(300))


def test_the_sample_period_median_is_numpys_to_the_bit():
    from estimator.ident.measurement import median

    rng = np.random.default_rng(5)
    for n in [*list(range(1, 12)), 200, 201, 1999]:
        for scale in (5e-7, 1.0, 3e4):
            x = rng.normal(size=n) * scale
            x[rng.random(n) < 0.3] = x[0]   # ties
            assert median(x) == float(np.median(x)), (n, scale)
    steps = np.diff(np.arange(201) * 5e-7)
    assert median(steps) == float(np.median(steps))


@pytest.mark.parametrize("window_s", [100e-6, 150e-6])
def test_the_plain_cost_shares_the_robust_costs_nuisance_basis_only_over_the_same_samples(sim, window_s):
    from estimator.ident.fit.cost import CostModel, nuisance_basis

    inj, _ = measured(17.2, 2.5, 41, window_s=window_s)
    rob = CostModel(sim, inj, window_s, "l2", True)
    plain = CostModel(sim, inj, 100e-6, "l2", False)
    plain.share_basis(rob)
    np.testing.assert_array_equal(plain.basis, nuisance_basis(plain.current, plain.dt))
    assert (plain.basis is rob.basis) == (window_s == 100e-6)   # one QR where the windows are the same
    other, _ = measured(17.2, 2.5, 42)
    alien = CostModel(sim, other, 100e-6, "l2", False)
    alien.share_basis(rob)   # another injection: its own basis
    np.testing.assert_array_equal(alien.basis, nuisance_basis(alien.current, alien.dt))
    assert alien.basis is not rob.basis


def test_other_sample_period_with_matching_simulator():
    from estimator.model.fast_sim import FastSimulator

    inj, _ = measured(17.0, 3.0, 31, window_s=150e-6)
    dec = Injection(inj.current_a[::2], inj.voltage_v[::2], 1e-6)   # a decimated (1 µs) bus
    est = identify(dec, FastSimulator(dt_s=1e-6))
    assert est.status == "ok" and abs(est.lh_m * 1e6 - 3.0) < 0.3


def test_l1_norm_option(sim):
    inj, _ = measured(17.0, 3.0, 32)
    est = identify(inj, sim, IdentConfig(norm="l1", robust="off"))
    assert est.status == "ok" and abs(est.lh_m * 1e6 - 3.0) < 0.3


@pytest.mark.parametrize("mismatch,window_s", [(False, 100e-6), (True, 150e-6)])
def test_the_plain_and_robust_searches_share_their_grids_without_changing_either(sim, mismatch, window_s):
    """An automatic cold start simulates each grid both costs ask for once (over the longer
    window when the robust one reaches further); each search ends where it ends alone."""
    from estimator.ident.fit.cold_start import SharedGrid, cold_fit
    from estimator.ident.fit.idle_stroke import effective_window_s, search_box

    inj, _ = measured(17.6, 3.3, 21, mismatch=mismatch, window_s=window_s)
    config = IdentConfig(cold_start="global")   # the global search (what a local-first start falls back to)
    box = search_box(config, sim, inj.f_open_n)

    def model(robust: bool):
        from estimator.ident.fit.cost import CostModel
        return CostModel(sim, inj, effective_window_s(config, inj, robust), config.norm, robust)

    alone = [model(r) for r in (False, True)]
    fits_alone = [cold_fit(m, box, config) for m in alone]
    together = [model(r) for r in (False, True)]
    shared = SharedGrid(together)
    fits_together = [cold_fit(m, box, config, shared) for m in together]
    assert together[0].n < together[1].n if window_s > 100e-6 else together[0].n == together[1].n
    for (fa, ca), (ft, ct) in zip(fits_alone, fits_together):
        np.testing.assert_array_equal(fa.x, ft.x)
        assert (fa.criterion, ca) == (ft.criterion, ct)
    spent_alone = sum(m.evaluations for m in alone)
    spent_together = sum(m.evaluations for m in together)
    assert spent_together <= spent_alone - 13 * 25      # at least the first grid is simulated once
    est = identify(inj, sim, config)      # the automatic cold start shares them the same way
    assert est.evaluations < spent_alone - 13 * 25
    assert (est.nu_n_per_v, est.lh_m * 1e6) in [tuple(f.x) for f, _ in fits_together]


def _full_grid_profile_start(f, box, config):
    """The profile search with every row of every zoom column simulated (the reference)."""
    from estimator.ident.fit.cold_start import _column_minima
    nu = np.linspace(box.lo[0], box.hi[0], config.grid[0])
    lh = np.linspace(box.lo[1], box.hi[1], config.grid[1])
    for zoom in range(config.zooms + 1):
        pts = np.stack(np.meshgrid(nu, lh, indexing="ij"), axis=-1).reshape(-1, 2)
        prof, lh_best = _column_minima(f(pts).reshape(nu.size, lh.size), lh)
        i = int(np.argmin(prof))
        if zoom < config.zooms:
            nu = np.linspace(nu[max(i - 1, 0)], nu[min(i + 1, nu.size - 1)], config.zoom_points)
    return box.clip(np.array([nu[i], lh_best[i]]))


@pytest.mark.parametrize("nu_true,lh_true,slope", [(17.3, 4.1, -20.0), (15.2, -1.4, -20.0), (20.8, 9.6, 3.0),
                                                   (18.0, 0.2, 40.0)])
def test_zoom_columns_simulate_a_window_of_rows_and_find_the_full_grids_start(nu_true, lh_true, slope):
    """A zoom column simulates only the rows near its neighbours' minima (widened where
    its minimum lands on the window's edge) and the start point is the full grid's, bit for bit,
    for a narrow sloping valley like eq. 28's (slope in µm per N/V)."""
    from estimator.ident.fit.cold_start import profile_start
    from estimator.ident.fit.search import Box

    evaluated = []

    def f(x):
        evaluated.append(len(x))
        valley = lh_true + slope * (x[:, 0] - nu_true)
        return (x[:, 1] - valley) ** 2 + 30.0 * (x[:, 0] - nu_true) ** 2

    config = IdentConfig()
    box = Box(np.array([14.9, -2.0]), np.array([21.1, 10.0]))
    x = profile_start(f, box, config)[0]
    windowed = sum(evaluated)
    np.testing.assert_array_equal(x, _full_grid_profile_start(f, box, config))
    full = 13 * 25 + 2 * 9 * 25
    assert windowed < full - 2 * 9 * 12       # the zooms simulated fewer than half their rows


def test_window_widens_until_the_column_minimum_is_inside():
    """A window that misses a column's minimum grows towards it until the minimum and both its
    neighbours are simulated: the same column minima as the whole column."""
    from estimator.ident.fit.cold_start import _column_minima, _window_profile

    nu = np.array([15.0, 16.0, 17.0])
    lh = np.linspace(-2.0, 10.0, 25)
    target = np.array([-1.9, 4.3, 9.9])

    def f(x):
        return (x[:, 1] - target[np.searchsorted(nu, x[:, 0])]) ** 2

    full = f(np.stack(np.meshgrid(nu, lh, indexing="ij"), axis=-1).reshape(-1, 2)).reshape(3, 25)
    got = _window_profile(f, nu, lh, np.array([12, 0, 3]), np.array([14, 2, 5]), 2)
    want = _column_minima(full, lh)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)


def test_a_single_bad_sample_anywhere_rejects_the_trace():
    """One NaN or infinite sample, in either signal, at either end, names the problem."""
    t = np.arange(201) * 0.5e-6
    cur = 10.0 * np.sin(np.pi * t / 100e-6)
    volt = 100.0 * (1 - np.cos(np.pi * t / 100e-6))
    assert Injection(cur, volt, 0.5e-6).problem() is None
    for signal, k, v in ((0, 0, np.nan), (0, 200, np.inf), (1, 200, np.nan), (1, 0, -np.inf), (1, 100, np.nan)):
        i, u = cur.copy(), volt.copy()
        (i if signal == 0 else u)[k] = v
        assert Injection(i, u, 0.5e-6).problem() == "NaN or infinite samples"
    assert Injection(cur.astype(np.float32), volt, 0.5e-6).problem() is None     # any float dtype


@pytest.mark.parametrize("nu,lh_um,seed", [(16.0, 1.5, 41), (19.5, 7.0, 42), (17.5, 3.5, 43), (20.6, -0.5, 44),
                                           (15.4, 8.0, 45)])
def test_local_first_cold_start_finds_the_global_searchs_estimate_with_a_fifth_of_the_simulations(sim, nu, lh_um, seed):
    """The default cold start refines from the start point and keeps the fit after checking
    it; on a matched plant that is the global search's estimate (within a fifth of a standard
    deviation: both stop within the convergence tolerance) at a fifth of the simulations or less."""
    inj, _ = measured(nu, lh_um, seed)
    est = identify(inj, sim)
    ref = identify(inj, sim, IdentConfig(cold_start="global"))
    assert est.status == ref.status == "ok" and est.robust == ref.robust
    assert abs(est.nu_n_per_v - ref.nu_n_per_v) <= 0.2 * ref.sigma_nu
    assert abs(est.lh_m - ref.lh_m) <= 0.2 * ref.sigma_lh_m
    assert est.evaluations * 5 <= ref.evaluations


def test_a_local_fit_that_does_not_explain_the_trace_falls_back_to_the_global_search(sim):
    """A hysteresis plant at low noise leaves a residual the robust cost does not absorb: the local
    fit fails the check and the estimate is the global search's, bit for bit, its simulations
    counted on top."""
    from sim_bench.hardware.plant import AdcConfig
    inj, _ = measured(15.3, 4.3, 31, mismatch=True, adc=AdcConfig(voltage_noise_v=0.05))
    est = identify(inj, sim)
    ref = identify(inj, sim, IdentConfig(cold_start="global"))
    assert (est.nu_n_per_v, est.lh_m, est.status, est.robust) == (ref.nu_n_per_v, ref.lh_m, ref.status, ref.robust)
    assert est.evaluations > ref.evaluations


def test_the_check_passes_the_minimum_and_fails_a_point_off_the_valley(sim):
    """excess_residual_z: noise-sized at the minimum of a correct model, far above the acceptance
    limit 0.05 N/V off the valley (where a local fit in another valley would stop)."""
    from estimator.ident.fit.cold_start import excess_residual_z
    from estimator.ident.fit.cost import CostModel
    from estimator.ident.fit.idle_stroke import search_box
    from estimator.ident.fit.local_fit import local_fit
    cfg = IdentConfig()
    inj, _ = measured(17.0, 3.0, 46)
    est = identify(inj, sim, IdentConfig(cold_start="global"))
    model = CostModel(sim, inj, cfg.window_s, cfg.norm, False)
    box = search_box(cfg, sim, inj.f_open_n)
    at_min = excess_residual_z(model, local_fit(model, np.array([est.nu_n_per_v, est.lh_m * 1e6]), box))
    off = excess_residual_z(model, local_fit(model, np.array([est.nu_n_per_v + 0.05, est.lh_m * 1e6]), box))
    assert abs(at_min) < 4 < cfg.local_accept_z < off


@pytest.mark.parametrize("kw", [{"cold_start": "fast"}, {"start_point": (18.0,)}, {"start_point": (float("nan"), 4.0)},
                                {"local_accept_z": 0.0}])
def test_cold_start_settings_are_checked(kw):
    with pytest.raises(ValueError):
        IdentConfig(**kw)


def test_the_published_fit_is_ringed_and_the_other_only_where_the_choice_is_close(sim, monkeypatch):
    """The automatic cold start rings (16 probes) the fit it publishes; the other fit only enters the
    model-error statistic and is ringed too only where that statistic lies within FLIP_MARGIN of the
    threshold. Either way the published estimate is the same."""
    from estimator.ident.fit import cold_start
    from estimator.ident.fit.idle_stroke import FLIP_MARGIN
    rings: list[bool] = []
    real = cold_start.probe_ring
    monkeypatch.setattr(cold_start, "probe_ring", lambda m, f, b: rings.append(m.robust) or real(m, f, b))
    cfg = IdentConfig()
    inj, _ = measured(17.0, 3.0, 47)
    est = identify(inj, sim)
    assert not est.robust and est.model_error_stat < cfg.model_error_threshold - FLIP_MARGIN and rings == [False]
    rings.clear()
    close = identify(inj, sim, IdentConfig(model_error_threshold=abs(est.model_error_stat) + 4))
    assert sorted(rings) == [False, True] and not close.robust
    assert (close.nu_n_per_v, close.lh_m, close.model_error_stat) == (est.nu_n_per_v, est.lh_m, est.model_error_stat)
    rings.clear()
    mis, _ = measured(16.0, 4.0, 48, mismatch=True)
    est_m = identify(mis, sim)
    assert est_m.robust and est_m.model_error_stat > cfg.model_error_threshold + FLIP_MARGIN and rings == [True]
    assert est_m.evaluations < 100    # the local fits, not the global search


def test_columns_no_simulation_explains_are_never_the_minimum():
    """Columns whose every point failed (NaN cost, as at a learned model's widened N_u range where no
    start is feasible) are never taken for the profile's minimum, nor does a zoom beside them cast a
    NaN to a row: the start is the valley's."""
    import warnings

    from estimator.ident.fit.cold_start import profile_start
    from estimator.ident.fit.search import Box

    config = IdentConfig()
    box = Box(np.array([14.9, -2.0]), np.array([23.2, 10.0]))
    edge = np.linspace(14.9, 23.2, config.grid[0])[6]        # the grid column right of the minimum fails

    def f(x):
        cost = (x[:, 1] - 4.0 - 2.0 * (x[:, 0] - 18.0)) ** 2 + 30.0 * (x[:, 0] - 18.0) ** 2
        # infeasible below the valley where N_u < 17.5: each such column's lowest point has a failed one beside it
        cost = np.where((x[:, 0] < 17.5) & (x[:, 1] < 3.7 + 2.0 * (x[:, 0] - 18.0)), np.inf, cost)
        return np.where(x[:, 0] >= edge - 1e-9, np.nan, cost)

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        x = profile_start(f, box, config)[0]
    assert abs(x[0] - 18.0) < 0.1 and abs(x[1] - 4.0) < 0.3
