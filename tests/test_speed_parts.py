"""What the online-speed work changed, checked for correctness (the timings live in the benchmarks):
the heartbeat's latency range and stage breakdown, the daemon's stage statistics."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.codec.ingest import Counters
from estimator.codec.records import Codec
from estimator.ident.config import TrackerConfig
from estimator.ident.tracker import Tracker
from estimator.service.latency import STAGES, Stats
from estimator.service.processor import Processor


def test_heartbeat_shows_an_overload_of_seconds_and_the_stages():
    p = Processor(Codec(), Tracker(TrackerConfig()), Counters(), "reset-only")
    stages = {"queue": 4321.5, "assembly": 0.12, "estimation": 2.97, "send": 0.3}
    hb = p.codec.decode(p.status_frame(3, 12_345.67, 10.0, stages))
    assert hb.latency_p99_ms == pytest.approx(12_345.67, abs=0.006)   # was saturated at 655.35 ms
    assert (hb.queue_p99_ms, hb.assembly_p99_ms, hb.estimation_p99_ms, hb.send_p99_ms) == pytest.approx(
        (4321.5, 0.12, 2.97, 0.3), abs=0.006)


def test_stats_p99_per_stage():
    st = Stats()
    for k in range(1000):
        parts = (0.001 * (k == 999), 0.0001, 0.002 + 1e-6 * k, 0.0002)
        st.add(float(k) * 1e-3, sum(parts), parts)
    total, stages = st.p99s_ms()
    assert list(stages) == list(STAGES)
    assert stages["estimation"] == pytest.approx(1e3 * float(np.percentile(0.002 + 1e-6 * np.arange(1000), 99)))
    assert stages["assembly"] == pytest.approx(0.1) and stages["send"] == pytest.approx(0.2)
    assert total > stages["estimation"]
    assert Stats().p99s_ms() == (0.0, dict.fromkeys(STAGES, 0.0))


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


def _cycle_case(sim, mismatch: bool, seed: int):
    from sim_bench.ident_bench import F_OPEN_N, _injection
    from sim_bench.plant import Plant, PlantConfig
    plant = Plant(PlantConfig(mismatch=mismatch, window_s=150e-6 if mismatch else 100e-6))
    return _injection(plant.measure(16.0 + seed, (2.0 + seed) * 1e-6, F_OPEN_N, np.random.default_rng(seed)))


@pytest.mark.parametrize("mismatch, robust, norm", [(False, False, "l2"), (True, True, "l2"), (False, False, "l1")])
def test_compiled_cycle_is_the_python_cycle(sim, mismatch, robust, norm):
    """One warm cycle in one compiled call gives what the Python stencil, vertex and Gauss–Newton fit
    give (to rounding: its sums run in another order), in plain, robust and L1 mode."""
    from estimator.ident import compiled_cycle as cc
    from estimator.ident.cost import CostModel
    from estimator.ident.local_fit import _stencil_cycle, fit_with_jacobian
    from estimator.ident.search import Box
    from estimator.ident.config import IdentConfig
    from estimator.ident.idle_stroke import identify
    from estimator.ident.idle_stroke import effective_window_s
    box = Box(np.array([14.9, 0.5]), np.array([21.1, 20.0]))
    fits = 0
    for seed in (1, 2, 3):
        inj = _cycle_case(sim, mismatch, seed)
        config = IdentConfig(robust="on" if robust else "off", norm=norm)
        est = identify(inj, sim, config)
        window = effective_window_s(config, inj, robust)
        d = est.directions       # a warm start: the cold start's conjugate directions, near its optimum
        sd = np.sqrt(np.diag(d.T @ est.cov_um @ d))
        for shift in ((0.5, -0.5), (-1.0, 0.3)):
            x0, st = est.point.array() + d @ (np.array(shift) * sd), 2.0 * sd
            m_py = CostModel(sim, inj, window, norm, robust)
            m_c = CostModel(sim, inj, window, norm, robust)
            x_py, ok_py, jac_py = _stencil_cycle(m_py, x0, d, st, box)
            cf = cc.run_cycle(m_c, x0, d, st, box)
            np.testing.assert_allclose(cf.x, x_py, rtol=1e-12)
            assert np.array_equal(cf.ok, ok_py)
            if jac_py is None:
                assert cf.code == cc.CYCLE_PARTIAL and np.isnan(cf.jac).all()
                continue
            fits += 1
            assert cf.code == cc.CYCLE_FIT
            np.testing.assert_allclose(cf.jac, jac_py, rtol=1e-7, atol=1e-9 * np.abs(jac_py).max())
            fit = fit_with_jacobian(m_py, x_py, jac_py)
            assert m_c.evaluations == m_py.evaluations == 6 and cf.success
            for name in ("criterion", "paper_cost_vs", "sigma_v", "t_contact_s", "t_open_s"):
                assert getattr(cf, name) == pytest.approx(getattr(fit, name), rel=1e-9), name
            for name in ("jtj", "gn_step", "cov_x", "residual"):
                np.testing.assert_allclose(getattr(cf, name), getattr(fit, name), rtol=1e-7,
                                           atol=1e-9 * np.abs(getattr(fit, name)).max(), err_msg=name)
            v, w = fit.directions
            np.testing.assert_allclose(cf.eigenvalues, w, rtol=1e-9)
            np.testing.assert_allclose(np.abs(cf.directions.T @ v), np.eye(2), atol=1e-9)   # up to sign
    assert fits >= 4


def test_compiled_cycle_hands_the_unusual_cases_to_python(sim):
    """A stencil that leaves the box gives the vertex and the directions that found it, no fit; a
    stencil point with L_h <= 0 (a pre-compressed start) is not simulated by the compiled cycle."""
    from estimator.ident import compiled_cycle as cc
    from estimator.ident.cost import CostModel
    from estimator.ident.local_fit import _stencil_cycle
    from estimator.ident.search import Box
    inj = _cycle_case(sim, False, 1)
    d = np.array([[0.96, -0.28], [0.28, 0.96]])
    box = Box(np.array([14.9, 2.95]), np.array([21.1, 20.0]))
    x0, st = np.array([17.0, 3.0]), np.array([0.03, 0.15])
    cf = cc.run_cycle(CostModel(sim, inj), x0, d, st, box)
    x_py, ok_py, jac_py = _stencil_cycle(CostModel(sim, inj), x0, d, st, box)
    assert cf.code == cc.CYCLE_PARTIAL and jac_py is None and np.isnan(cf.jac).all()
    np.testing.assert_allclose(cf.x, x_py, rtol=1e-12)
    assert np.array_equal(cf.ok, ok_py)
    low = Box(np.array([14.9, -3.0]), np.array([21.1, 20.0]))
    m = CostModel(sim, inj)
    cf = cc.run_cycle(m, np.array([17.0, 0.05]), d, st, low)
    assert cf.code == cc.CYCLE_FALLBACK and m.evaluations == 0


def test_compiled_nuisance_span_is_the_numpy_one():
    """The compiled nuisance columns are the numpy formulas bit for bit; the residual energy in their
    span is the least-squares projection's, with raw columns (normal equations) and with the
    orthonormal basis."""
    from estimator.ident.cost import NUISANCE_THRESHOLDS, model_error_statistic, nuisance_basis, nuisance_columns
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


@pytest.mark.parametrize("robust", [False, True])
def test_compiled_forward_fit_is_the_python_one(sim, robust):
    """local_fit's compiled three-point fit equals its Python twin (at the upper bounds the steps turn
    back); a point whose neighbour needs a pre-compressed start stays in Python."""
    from estimator.ident.cost import CostModel
    from estimator.ident.local_fit import _forward_fit, local_fit
    from estimator.ident.search import Box
    inj = _cycle_case(sim, robust, 2)
    box = Box(np.array([14.9, 0.001]), np.array([18.0, 4.0]))
    for x in (np.array([18.0, 4.0]), np.array([17.97, 3.9])):
        m_c, m_py = CostModel(sim, inj, 100e-6, "l2", robust), CostModel(sim, inj, 100e-6, "l2", robust)
        got, want = local_fit(m_c, x, box), _forward_fit(m_py, x, box)
        assert m_c.evaluations == m_py.evaluations == 3 and got.success and want.success
        for name in ("criterion", "paper_cost_vs", "sigma_v", "t_contact_s", "t_open_s"):
            assert getattr(got, name) == pytest.approx(getattr(want, name), rel=1e-9), name
        for name in ("jtj", "gn_step", "cov_x", "residual"):
            np.testing.assert_allclose(getattr(got, name), getattr(want, name), rtol=1e-7,
                                       atol=1e-9 * np.abs(getattr(want, name)).max(), err_msg=name)
    m = CostModel(sim, inj)
    from estimator.ident import compiled_cycle as cc
    low = Box(np.array([14.9, -3.0]), np.array([21.1, 20.0]))
    assert cc.run_forward_fit(m, np.array([17.0, -0.001]), np.array([2e-3, 2e-3]), low).code == cc.CYCLE_FALLBACK
    fit = local_fit(m, np.array([17.0, -0.001]), low)    # pre-compressed: in Python
    assert m.evaluations == 3 and fit.success and np.isfinite(fit.criterion)


@pytest.mark.parametrize("n", [201, 200])
def test_noise_level_is_the_middle_absolute_difference(n):
    """The one noise estimate both fit paths use: the upper middle of the sorted |first differences|,
    as a white-noise sigma (MAD of a difference of two samples), floored at 1 mV."""
    from estimator.ident.cost import MAD_PER_SIGMA, NOISE_FLOOR_V, noise_sigma_v
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

    from estimator.ident import tracker as tr
    from estimator.ident.idle_stroke import search_box
    from estimator.model.fast_sim import FastSimulator
    config = TrackerConfig()
    s = FastSimulator()
    b1, n1 = tr._box_and_noise(config, s, 28.0)
    b2, _ = tr._box_and_noise(config, s, 60.0)
    assert tr._box_and_noise(config, s, 28.0)[0] is b1                     # kept
    for f_open, box in ((28.0, b1), (60.0, b2)):                            # and what search_box gives
        want = search_box(config.ident, s, f_open)
        assert np.array_equal(box.lo, want.lo) and np.array_equal(box.hi, want.hi)
    assert b2 is not b1                                                     # one per F_open (it moves the feasible L_h)
    assert n1 == tr.process_noise(config, b1)
    for f_open in np.linspace(20.0, 80.0, 40):                              # bounded per simulator
        tr._box_and_noise(config, s, float(f_open))
    assert len(tr._BOXES[s]) <= tr._BOXES_PER_SIMULATOR
    gone = weakref.ref(s)
    del s
    gc.collect()
    assert gone() is None                                                   # not held by the cache


def test_refine_step_rules_in_floats_are_the_numpy_rules():
    """refine's step sizes and Gauss–Newton tests, written in floats for speed, give what the numpy
    expressions they replace give, NaN, inf, zero and negative variances included."""
    from estimator.ident.local_fit import next_steps, _within
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
    from estimator.ident.compiled_cycle import CYCLE_FIT, CycleFit
    return CycleFit(CYCLE_FIT, 6, np.array(x, dtype=float), np.array([True, True]), np.full((2, 3), np.nan), criterion,
                    0.0, np.eye(2), np.array(gn_sigmas, dtype=float), 1.0, np.eye(2), np.zeros(3), np.nan, np.nan, True,
                    np.eye(2), np.ones(2))


@pytest.mark.parametrize("gn_fit_sigmas, cycles_run", [((0.1, 0.2), 1), ((0.1, 0.3), 2)])
def test_a_gauss_newton_point_that_confirms_the_minimum_ends_the_warm_refinement(monkeypatch, gn_fit_sigmas,
                                                                                  cycles_run):
    """The warm cycle's vertex is 0.3 sigma short of its Gauss–Newton minimum (not converged); the fit at
    the Gauss–Newton point costs more than the vertex. If that fit, with its own Jacobian, puts the minimum
    within a quarter sigma of it, the vertex is converged: no second cycle of six simulations (what set
    the p99 of the warm update). Otherwise the second cycle runs as before."""
    from estimator.ident import local_fit as lf
    from estimator.ident.config import IdentConfig
    from estimator.ident.search import Box

    calls = []

    def run_cycle(model, x, d, st, box):
        calls.append(x.copy())
        return _cycle(x + [1.0, 1.0], 10.0, (0.1, 0.3) if len(calls) == 1 else (0.0, 0.0))

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
    from estimator.ident import cost
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

    from estimator.model import direct_call

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


def test_compiled_gauss_newton_loop_is_the_python_loop(sim, monkeypatch):
    """The cold start's Gauss–Newton loop, compiled, takes the Python loop's steps (``compiled=False``)
    to the bit: from a lot-like start, and where a point needs a pre-compressed start (L_h <= 0) and the loop goes on
    in Python, at the first point or after some compiled steps; a small trust region that runs out
    of steps included, and first trust regions widened to the first fit's standard deviations
    (``radius_sd``) in both."""
    from estimator.ident import cold_start
    from estimator.ident import compiled_cycle as cc
    from estimator.ident.config import IdentConfig
    from estimator.ident.cost import CostModel
    from estimator.ident.idle_stroke import search_box
    from sim_bench.ident_bench import F_OPEN_N, _injection
    from sim_bench.plant import Plant, PlantConfig
    from .helpers import record_codes
    codes = record_codes(monkeypatch, cold_start, "run_gauss_newton")
    cfg = IdentConfig()
    cases = [(0.2, (16.5, 3.0), None, False, 0.0), (0.05, (16.5, 1.0), None, False, 0.0),
             (0.3, (16.5, -0.5), None, False, 0.0), (-0.2, (16.2, 2.0), None, True, 0.0),
             (3.0, (17.5, 6.0), (0.002, 0.01), False, 0.0), (3.0, (16.4, 3.6), (0.002, 0.01), True, 4.0),
             (0.3, (16.5, -0.5), (0.002, 0.01), True, 4.0)]
    widened = []
    for k, (lh_um, start, radius, robust, radius_sd) in enumerate(cases):
        plant = Plant(PlantConfig())
        inj = _injection(plant.measure(16.2, lh_um * 1e-6, F_OPEN_N, np.random.default_rng(k)))
        box = search_box(cfg, sim, inj.f_open_n)
        m_c, m_py = CostModel(sim, inj, 100e-6, "l2", robust), CostModel(sim, inj, 100e-6, "l2", robust)
        r = None if radius is None else np.array(radius)
        got, conv = cold_start.gauss_newton_fit(m_c, np.array(start), box, cfg, r, radius_sd=radius_sd)
        want, conv_py = cold_start.gauss_newton_fit(m_py, np.array(start), box, cfg, r, compiled=False,
                                                    radius_sd=radius_sd)
        if radius_sd:   # the widening changes the run: without it, more steps
            m_0 = CostModel(sim, inj, 100e-6, "l2", robust)
            cold_start.gauss_newton_fit(m_0, np.array(start), box, cfg, r, compiled=False)
            widened.append(m_0.evaluations - m_py.evaluations)
        assert m_c.evaluations == m_py.evaluations, k
        assert np.array_equal(got.x, want.x) and got.criterion == want.criterion and conv == conv_py, k
        assert np.array_equal(got.cov_x, want.cov_x) and got.success == want.success
    assert {cc.GN_DONE, cc.GN_FIRST_FIT, cc.GN_STEP_FIT} <= set(codes)
    assert max(widened) > 0, widened


@pytest.mark.parametrize("robust", [False, True])
def test_compiled_point_costs_are_the_cost_models(sim, robust):
    """The ring's compiled costs are the cost model's (to rounding: sums in another order), evaluations
    counted; points with one at L_h <= 0 are left to Python (nothing simulated)."""
    from estimator.ident import compiled_cycle as cc
    from estimator.ident.cost import CostModel
    from estimator.ident.local_fit import cost_fn
    inj = _cycle_case(sim, robust, 1)
    m_c, m_py = CostModel(sim, inj, 100e-6, "l2", robust), CostModel(sim, inj, 100e-6, "l2", robust)
    pts = np.column_stack([np.linspace(16.0, 18.5, 9), np.linspace(0.5, 40.0, 9)])
    got, want = cc.run_point_costs(m_c, pts), cost_fn(m_py)(pts)
    np.testing.assert_allclose(got, want, rtol=1e-10)
    assert m_c.evaluations == m_py.evaluations == 9 and np.all(np.isfinite(got[:5]))
    pts[3, 1] = -0.2
    assert cc.run_point_costs(m_c, pts) is None and m_c.evaluations == 9
