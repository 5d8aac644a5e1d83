"""The simulator's and the identification's compiled paths checked for correctness (their timings live
in the benchmarks): shared free runs, shared matrices, input checks, small caches, step rules in
floats, direct calls."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.ident.config import TrackerConfig


@pytest.mark.parametrize("f_open_n", [35.0, 0.0])
@pytest.mark.parametrize("samples", [201, 981])
def test_grid_voltages_equal_simulate_bit_for_bit(sim, f_open_n, samples):
    """A grid column's shared free run changes nothing: every point's voltage and success are the
    ones its own simulation gives (pre-compressed rows, no-contact rows, failures and a valve that
    opens at once with F_open = 0 included)."""
    from estimator.model.drive import StandardDrive
    rng = np.random.default_rng(samples)
    cur = StandardDrive().samples((samples - 1) * sim.dt_s, sim.dt_s)
    cur = cur * (1.0 + rng.normal(0.0, 0.01, cur.size))
    nu, lh = np.meshgrid(np.linspace(14.9, 21.1, 7), np.r_[np.linspace(-2e-6, 10e-6, 13), 40e-6], indexing="ij")
    nu = np.r_[nu.ravel(), rng.uniform(15.0, 21.0, 20)]
    lh = np.r_[lh.ravel(), rng.uniform(-2e-6, 12e-6, 20)]
    res = sim.simulate(cur, nu, lh, f_open_n)
    u, ok = sim.grid_voltages(cur, nu, lh, f_open_n)
    assert np.array_equal(ok, res.success)
    assert np.array_equal(u, np.where(res.success[:, None], res.voltage_v, np.nan), equal_nan=True)
    assert ok.sum() > nu.size // 2


@pytest.mark.parametrize("exact", [False, True])
def test_candidates_that_share_an_n_u_share_matrices_and_nothing_else(sim, exact):
    """The kernel keeps a candidate's transition rows and continuous matrices for the next candidate
    with the same N_u (a grid column); each candidate's trajectory is still the one it has alone, bit
    for bit: pre-compressed, contact, opening and no-contact rows, in runs of equal N_u."""
    from estimator.model.drive import StandardDrive
    cur = np.zeros(981)
    cur[:201] = StandardDrive().samples(100e-6, sim.dt_s)
    nu = np.repeat([15.3, 17.0, 17.0 + 1e-9, 20.4], 5)
    lh = np.tile([-1.5e-6, -0.2e-6, 2e-6, 6e-6, 40e-6], 4)
    res = sim.simulate(cur, nu, lh, 28.0, exact=exact)
    for b in range(nu.size):
        one = sim.simulate(cur, nu[b], lh[b], 28.0, exact=exact)
        for got, want in ((res.voltage_v[b], one.voltage_v[0]), (res.s3_m[b], one.s3_m[0]), (res.s4_m[b], one.s4_m[0]),
                          (res.mode[b], one.mode[0]), (res.t_contact_s[b], one.t_contact_s[0]),
                          (res.t_open_s[b], one.t_open_s[0]), (res.status[b], one.status[0])):
            assert np.array_equal(got, want, equal_nan=True), b
    assert np.isfinite(res.t_open_s).sum() >= 8 and np.isnan(res.t_contact_s).sum() >= 3


def test_grid_voltages_check_their_inputs(sim):
    from estimator.errors import ParameterError
    cur = np.linspace(0.0, 10.0, 50)
    with pytest.raises(ParameterError):
        sim.grid_voltages(cur, np.full(4, 40.0), np.full(4, 3e-6), 35.0)     # N_u outside the range
    with pytest.raises(ParameterError):
        sim.grid_voltages(np.r_[cur, np.nan], np.full(4, 17.0), np.full(4, 3e-6), 35.0)
    with pytest.raises(ParameterError):
        sim.grid_voltages(cur, np.full(4, 17.0), np.full(3, 3e-6), 35.0)


def test_compiled_nuisance_span_is_the_numpy_one():
    """The compiled nuisance columns are the numpy formulas bit for bit; the residual energy in their
    span is the least-squares projection's, with raw columns (normal equations) and with the
    orthonormal basis."""
    from estimator.ident.fit.cost import NUISANCE_THRESHOLDS, model_error_statistic, nuisance_basis, nuisance_columns
    from estimator.model.drive import StandardDrive
    rng = np.random.default_rng(3)
    dt = 0.5e-6
    cur = StandardDrive().samples(100e-6, dt) + rng.normal(0.0, 0.02, 201)
    q = np.r_[0.0, np.cumsum((cur[1:] + cur[:-1]) * (0.5 * dt))]
    want = np.empty((201, 6))
    want[:, 0] = cur / np.abs(cur).max()
    want[:, 1] = q / q[-1]
    for k, r in enumerate(NUISANCE_THRESHOLDS):
        want[:, 2 + k] = np.maximum(want[:, 1] - r, 0.0)
    cols = nuisance_columns(cur, dt)
    assert np.array_equal(cols, want)
    res = rng.normal(0.0, 0.1, 201) + 0.3 * cols[:, 3]
    coef, *_ = np.linalg.lstsq(cols, res, rcond=None)
    energy = float(np.sum((cols @ coef) ** 2))
    assert model_error_statistic(res, cols, 0.1) == pytest.approx(energy / 0.01, rel=1e-9)
    assert model_error_statistic(res, nuisance_basis(cur, dt), 0.1) == pytest.approx(energy / 0.01, rel=1e-9)
    assert model_error_statistic(res, np.empty((201, 0)), 0.1) == 0.0


@pytest.mark.parametrize("n", [201, 200])
def test_noise_level_is_the_middle_absolute_difference(n):
    """The one noise estimate both fit paths use: the upper middle of the sorted |first differences|,
    as a white-noise sigma (MAD of a difference of two samples), floored at 1 mV."""
    from estimator.ident.fit.cost import MAD_PER_SIGMA, NOISE_FLOOR_V, noise_sigma_v
    rng = np.random.default_rng(n)
    r = rng.normal(0.0, 0.1, n) + np.linspace(0.0, 3.0, n)     # a smooth trend differencing removes
    d = np.sort(np.abs(np.diff(r)))
    assert noise_sigma_v(r) == d[d.size // 2] / MAD_PER_SIGMA / np.sqrt(2.0)
    e = np.sort(np.abs(np.diff(r[::2])))                        # a strided view is read right
    assert noise_sigma_v(r[::2]) == e[e.size // 2] / MAD_PER_SIGMA / np.sqrt(2.0)
    assert noise_sigma_v(np.zeros(n)) == NOISE_FLOOR_V


def test_valve_prediction_checks_its_inputs_in_the_same_call(sim):
    from estimator.errors import ParameterError
    from estimator.model.drive import StandardDrive
    cur = np.zeros(981)
    cur[:201] = StandardDrive().samples(100e-6)
    assert np.isfinite(sim.valve_prediction(cur, 17.0, 3e-6, 28.0)).all()
    for args, text in (((30.0, 3e-6, 28.0), "outside"), ((17.0, 3e-6, -1.0), "F_open"),
                       ((17.0, float("inf"), 28.0), "finite")):
        with pytest.raises(ParameterError, match=text):
            sim.valve_prediction(cur, *args)
    bad = cur.copy()
    bad[500] = np.nan
    with pytest.raises(ParameterError, match="finite"):
        sim.valve_prediction(bad, 17.0, 3e-6, 28.0)


def test_the_simulators_small_caches_stay_bounded(sim):
    from estimator.model.fast_sim import PLATEAU_WINDOW_S
    cur = np.zeros(1200)
    for n in range(985, 1185):            # 200 trace lengths
        sim.valve_prediction(cur[:n], 17.0, 3e-6, 28.0, PLATEAU_WINDOW_S)
        sim.simulate(cur[:n // 4], 17.0, 3e-6)
    assert len(sim._plateau) <= 64 and len(sim._t_cache) <= 64


def test_search_box_and_noise_kept_per_simulator_weakly():
    import gc
    import weakref

    from estimator.ident.fit.idle_stroke import search_box
    from estimator.ident.tracking import recursive as tr
    from estimator.model.fast_sim import FastSimulator
    config = TrackerConfig()
    s = FastSimulator()
    b1, n1 = tr.box_and_noise(config, s, 28.0)
    b2, _ = tr.box_and_noise(config, s, 60.0)
    assert tr.box_and_noise(config, s, 28.0)[0] is b1                     # kept
    for f_open, box in ((28.0, b1), (60.0, b2)):                            # and what search_box gives
        want = search_box(config.ident, s, f_open)
        assert np.array_equal(box.lo, want.lo) and np.array_equal(box.hi, want.hi)
    assert b2 is not b1                                                     # one per F_open (it moves the feasible L_h)
    assert n1 == tr.process_noise(config, b1)
    for f_open in np.linspace(20.0, 80.0, 40):                              # bounded per simulator
        tr.box_and_noise(config, s, float(f_open))
    assert len(tr._BOXES[s]) <= tr._BOXES_PER_SIMULATOR
    gone = weakref.ref(s)
    del s
    gc.collect()
    assert gone() is None                                                   # not held by the cache


def test_refine_step_rules_in_floats_are_the_numpy_rules():
    """refine's step sizes and Gauss–Newton tests, written in floats for speed, give what the numpy
    expressions they replace give, NaN, inf, zero and negative variances included."""
    from estimator.ident.fit.local_fit import _within, next_steps
    rng = np.random.default_rng(0)
    tol = (2e-4, 2e-3)
    for _ in range(5000):
        w = rng.choice([rng.uniform(-1, 10), 0.0, 1e-320, np.nan, np.inf, 1e-12, 1e6], 2)
        sv = float(rng.choice([rng.uniform(0, 0.1), np.nan, 0.0, 1e3]))
        want = np.minimum(np.maximum(2.0 * np.sqrt(np.maximum(sv ** 2 / np.maximum(w, 1e-300), 0.0)), 4 * min(tol)), 2.0)
        assert np.array_equal(next_steps(sv, w, tol), want, equal_nan=True)
        cov = np.diag(rng.choice([rng.uniform(0, 1e-3), np.nan, np.inf, 0.0, -1e-6], 2))
        g = np.abs(rng.choice([rng.uniform(-0.01, 0.01), np.nan, 0.0], 2))
        sx = np.sqrt(np.abs(np.diag(cov)))
        # refine's near-minimum test: 4 max(sigma, tol) as _within with the tolerances scaled
        assert _within(g, (4.0 * tol[0], 4.0 * tol[1]), 4.0, cov) == bool(np.all(g <= 4.0 * np.maximum(sx, tol)))
        assert _within(g, tol, 0.25, cov) == bool(np.all(g <= np.maximum(tol, 0.25 * sx)))


def _cycle(x: np.ndarray, criterion: float, gn_sigmas: tuple[float, float]):
    """A compiled cycle's outcome at ``x`` with unit variances and a Gauss–Newton step of ``gn_sigmas``."""
    from estimator.ident.fit.fit_kernel import FIT, KernelFit
    return KernelFit(FIT, 6, np.array(x, dtype=float), np.array([True, True]), np.full((2, 3), np.nan), criterion,
                    0.0, np.eye(2), np.array(gn_sigmas, dtype=float), 1.0, np.eye(2), np.zeros(3), np.nan, np.nan, True,
                    np.eye(2), np.ones(2))


@pytest.mark.parametrize("gn_fit_sigmas, cycles_run", [((0.1, 0.2), 1), ((0.1, 0.3), 2)])
def test_a_gauss_newton_point_that_confirms_the_minimum_ends_the_warm_refinement(monkeypatch, gn_fit_sigmas,
                                                                                  cycles_run):
    """The warm cycle's vertex is 0.3 sigma short of its Gauss–Newton minimum (not converged); the fit at
    the Gauss–Newton point costs more than the vertex. If that fit, with its own Jacobian, puts the minimum
    within a quarter sigma of it, the vertex is converged: no second cycle of six simulations (what set
    the p99 of the warm update). Otherwise the second cycle runs as before."""
    from estimator.ident.config import IdentConfig
    from estimator.ident.fit import local_fit as lf
    from estimator.ident.fit.search import Box

    calls = []

    def run_cycle(model, x, d, st, box):
        calls.append(x.copy())
        return _cycle(x + 1.0, 10.0, (0.1, 0.3) if len(calls) == 1 else (0.0, 0.0))

    def forward_fit(model, x, steps, box):
        return _cycle(x, 10.5, gn_fit_sigmas)            # dearer than the vertex: not taken

    class Model:
        evaluations = 0
    monkeypatch.setattr(lf, "run_cycle", run_cycle)
    monkeypatch.setattr(lf, "run_forward_fit", forward_fit)
    box = Box(np.array([0.0, 0.0]), np.array([100.0, 100.0]))
    fit, converged, cycles = lf.refine(Model(), np.array([50.0, 50.0]), np.eye(2), np.ones(2), box, IdentConfig(),
                                       max_cycles=3, batched=True)
    assert converged and cycles == cycles_run and len(calls) == cycles_run
    assert np.array_equal(fit.x, [51.0, 51.0] if cycles_run == 1 else [52.0, 52.0])   # the vertex, not the GN point


def test_the_warm_model_error_test_is_the_statistic_against_the_raw_columns_to_the_bit():
    """cost.plain_model_error (six columns summed in registers) equals model_error_statistic against
    nuisance_columns bit for bit: simulated windows of several lengths and noise levels, a current whose
    first column has unit norm (the orthonormal branch), and another number of thresholds (the general path)."""
    from estimator.ident.fit import cost
    from estimator.model.drive import StandardDrive
    rng = np.random.default_rng(3)
    base = StandardDrive().samples(150e-6)
    for _ in range(200):
        n = int(rng.integers(20, base.size))
        cur = base[:n] * rng.uniform(0.5, 2.0) + rng.normal(0.0, 0.05, n)
        r = rng.normal(0.0, rng.uniform(1e-3, 1.0), n)
        sigma = float(rng.uniform(1e-3, 0.1))
        want = cost.model_error_statistic(r, cost.nuisance_columns(cur, 0.5e-6), sigma)
        assert cost.plain_model_error(r, cur, 0.5e-6, sigma) == want
    spike = np.zeros(50)
    spike[10] = 3.0                                  # column 0 is a unit vector
    r = rng.normal(0.0, 0.01, 50)
    assert cost.plain_model_error(r, spike, 0.5e-6, 0.01) == cost.model_error_statistic(
        r, cost.nuisance_columns(spike, 0.5e-6), 0.01)
    three = np.array([0.1, 0.3, 0.6])
    cur, r = base[:200], rng.normal(0.0, 0.01, 200)
    assert cost._plain_model_error(r, cur, 0.5e-6, three, 0.01) == cost._span_energy(
        r, cost._nuisance_columns(cur, 0.5e-6, three)) / 0.01 ** 2


def test_direct_call_runs_the_dispatchers_overload_and_refuses_other_types():
    """DirectCall: the first call through the dispatcher, later ones straight to that overload (the
    same results); with type checks on (as in the whole suite), another dtype or layout is refused."""
    from numba import njit

    from estimator._compiled import direct_call

    @njit
    def weighted_sum(x, w, scale):
        s = 0.0
        for k in range(x.shape[0]):
            s += x[k] * w[k]
        return s * scale

    call = direct_call.DirectCall(weighted_sum)
    x, w = np.arange(5.0), np.linspace(0.5, 1.5, 5)
    assert call(x, w, 2.0) == weighted_sum(x, w, 2.0)
    assert call(x + 1.0, w, 3.0) == weighted_sum(x + 1.0, w, 3.0)   # the direct path
    assert direct_call._verify, "tests/conftest.py turns the type checks on"
    with pytest.raises(TypeError, match="argument"):
        call(x.astype(np.float32), w, 2.0)
    with pytest.raises(TypeError, match="argument"):
        call(np.arange(10.0)[::2], w, 2.0)          # not contiguous
    assert len(weighted_sum.overloads) == 1         # refused before anything was compiled for them


def test_direct_calls_work_with_numbas_jit_switched_off():
    """NUMBA_DISABLE_JIT=1 (how one debugs the kernel in Python) makes every @njit function a plain
    Python function: the DirectCalls on the warm path then call it as it is. The valve prediction,
    run that way in a fresh process, gives the compiled numbers (to the rounding of fused multiply-adds)."""
    import json
    import os
    import subprocess
    import sys

    from estimator.model.drive import StandardDrive
    from estimator.model.fast_sim import FastSimulator

    code = ("import json; from estimator.model.fast_sim import FastSimulator; "
            "from estimator.model.drive import StandardDrive; "
            "print(json.dumps(FastSimulator().valve_prediction(StandardDrive().samples(490e-6), 17.0, 4e-6, 28.0)))")
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    python_run = json.loads(out.stdout)
    compiled = FastSimulator().valve_prediction(StandardDrive().samples(490e-6), 17.0, 4e-6, 28.0)
    assert all(np.isfinite(compiled))
    np.testing.assert_allclose(python_run, compiled, rtol=1e-9)
