"""The compiled local fits checked against independent oracles: the simulator's own voltages with
numpy differences and projections, numpy parabolas, and scipy's least_squares on the same cost."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from estimator.errors import ParameterError
from estimator.ident.config import IdentConfig
from estimator.ident.fit import fit_kernel
from estimator.ident.fit.cold_start import gauss_newton_fit, unchecked_fit
from estimator.ident.fit.cost import CostModel, noise_sigma_v, nuisance_basis, trapezoid_weights
from estimator.ident.fit.idle_stroke import search_box
from estimator.ident.fit.local_fit import local_fit, refine
from estimator.ident.fit.search import Box
from estimator.ident.measurement import Injection

F_OPEN_N = 28.0 * 1.25
TRUTH = (16.6, 2.4)     # N/V, µm


def _injection(sim, lh_um: float = TRUTH[1], seed: int = 1) -> Injection:
    from sim_bench.benches.ident_bench import _injection as to_injection
    from sim_bench.hardware.plant import Plant, PlantConfig
    plant = Plant(PlantConfig())
    return to_injection(plant.measure(TRUTH[0], lh_um * 1e-6, F_OPEN_N, np.random.default_rng(seed)))


def _residual(model: CostModel, x: np.ndarray) -> np.ndarray:
    """The window's residual at x (N/V, µm) from the simulator's own voltage, projected with numpy."""
    res = model.sim.simulate(model.current, x[0], x[1] * 1e-6, model.injection.f_open_n)
    r = model.measured - res.voltage_v[0, : model.n]
    if model.robust:
        b = nuisance_basis(model.current, model.dt)
        r = r - b @ (b.T @ r)
    return r


def _least_squares_minimum(model: CostModel, x0: np.ndarray) -> np.ndarray:
    """scipy's minimum of the same cost (weighted least squares), from x0."""
    w = np.sqrt(trapezoid_weights(model.n, model.dt))
    out = least_squares(lambda x: w * _residual(model, x), x0, diff_step=1e-6, x_scale=[0.01, 0.1],
                        xtol=1e-12, ftol=1e-14, gtol=1e-14)
    return out.x


@pytest.mark.parametrize("robust", [False, True])
@pytest.mark.parametrize("lh_um", [2.4, -0.3])
def test_forward_fit_is_the_gauss_newton_model_of_the_simulators_voltage(sim, robust, lh_um):
    """Cost, residual, Jacobian, noise level and covariance of a compiled fit are what numpy makes of
    the simulator's voltages at the point and beside it (a pre-compressed start, L_h < 0, included)."""
    inj = _injection(sim, lh_um)
    model = CostModel(sim, inj, 100e-6, "l2", robust)
    box = Box(np.array([14.9, -2.0]), np.array([21.1, 10.0]))
    x = np.array([TRUTH[0] + 0.01, lh_um + 0.05])
    fit = local_fit(model, x, box)
    assert fit.success and model.evaluations == 3
    r = _residual(model, x)
    w = trapezoid_weights(model.n, model.dt)
    assert fit.criterion == pytest.approx(float(np.sum(w * r * r)), rel=1e-10)
    raw = inj.voltage_v[: model.n] - sim.simulate(model.current, x[0], x[1] * 1e-6, F_OPEN_N).voltage_v[0, : model.n]
    np.testing.assert_allclose(fit.residual, raw, rtol=0, atol=1e-12)
    h = np.array([1e-3, 1e-3])
    jac = np.stack([-(_residual(model, x + e) - _residual(model, x - e)) / (2 * e.sum()) for e in np.diag(h)])
    scale = np.abs(jac).max(axis=1)
    jac_fit = np.stack([-(_residual(model, x + e) - r) / e.sum() for e in np.diag(fit_kernel_steps())])
    np.testing.assert_allclose(jac_fit, jac, rtol=0, atol=0.02 * scale.max())
    sigma = noise_sigma_v(r)
    assert fit.sigma_v == pytest.approx(sigma, rel=1e-12)
    jtj = jac_fit @ jac_fit.T
    np.testing.assert_allclose(fit.jtj, jtj, rtol=1e-6)
    np.testing.assert_allclose(fit.cov_x, sigma ** 2 * np.linalg.inv(jtj), rtol=1e-6)
    np.testing.assert_allclose(fit.gn_step, np.linalg.solve(jtj, jac_fit @ r), rtol=1e-6, atol=1e-12)
    d, eig = fit.directions
    want = np.linalg.eigvalsh(jtj)
    np.testing.assert_allclose(eig, want, rtol=1e-9)
    np.testing.assert_allclose(np.abs(d.T @ np.linalg.eigh(jtj)[1]), np.eye(2), atol=1e-9)


def fit_kernel_steps() -> np.ndarray:
    from estimator.ident.fit.local_fit import FD_STEP
    return FD_STEP


@pytest.mark.parametrize("robust", [False, True])
def test_the_searches_end_at_the_least_squares_minimum(sim, robust):
    """The cold start's local fit (Gauss–Newton, the line searches where it stalls) from a nominal, a
    pre-compressed (L_h < 0) and a distant start, and the warm refinement from a start two standard
    deviations off, end within a quarter standard deviation of scipy's least-squares minimum of the
    same cost, at most 0.1 (chi-square units) above its cost."""
    inj = _injection(sim)
    config = IdentConfig()
    box = search_box(config, sim, inj.f_open_n)
    oracle = CostModel(sim, inj, 100e-6, "l2", robust)
    x_ls = _least_squares_minimum(oracle, np.array(TRUTH))
    j_ls = float(oracle(np.array([x_ls[0]]), np.array([x_ls[1] * 1e-6]))[0])

    def check(fit, what):
        assert fit.success, what
        assert np.all(np.abs(fit.x - x_ls) <= 0.25 * fit.sd_x), (what, fit.x, x_ls, fit.sd_x)
        assert (fit.criterion - j_ls) / (fit.sigma_v ** 2 * oracle.dt) <= 0.1, what
    fit, converged = gauss_newton_fit(CostModel(sim, inj, 100e-6, "l2", robust), np.array([16.5, 3.0]), box, config)
    assert converged
    check(fit, "Gauss–Newton")
    for start in ((16.4, -0.5), (17.5, 6.0)):
        fit, converged = unchecked_fit(CostModel(sim, inj, 100e-6, "l2", robust), np.array(start), box, config)
        assert converged
        check(fit, start)
    d, _ = fit.directions
    sd = np.sqrt(np.diag(d.T @ fit.cov_x @ d))
    model = CostModel(sim, inj, 100e-6, "l2", robust)
    warm, converged, cycles = refine(model, x_ls + d @ (np.array([2.0, -1.0]) * sd), d, 2.0 * sd, box, config,
                                     max_cycles=3, batched=True)
    assert converged and cycles <= 3
    check(warm, "warm")


def test_a_warm_cycle_finds_the_vertices_of_numpys_parabolas(sim):
    """A warm cycle's vertex is where the parabolas numpy fits through the cost model's own costs of
    its stencil put it; a stencil that leaves the box still gives both vertices, but no fit."""
    inj = _injection(sim)
    box = Box(np.array([14.9, -2.0]), np.array([21.1, 20.0]))
    near = local_fit(CostModel(sim, inj), np.array([16.597, 2.41]), box)
    d, _ = near.directions
    st = 2.0 * np.sqrt(np.diag(d.T @ near.cov_x @ d))
    x0 = near.x + d @ st / 2
    cut = min(x0[1] - st[0] * abs(d[1, 0]), x0[1] - st[1] * abs(d[1, 1])) + 0.01
    for lo_lh, partial in ((-2.0, False), (cut, True)):
        box = Box(np.array([14.9, lo_lh]), np.array([21.1, 20.0]))
        model = CostModel(sim, inj)
        cycle = fit_kernel.run_cycle(model, x0, d, st, box)
        assert (cycle.code == fit_kernel.PARTIAL) == partial and model.evaluations == (5 if partial else 6)
        assert np.isnan(cycle.jac).all() == partial and cycle.ok.all()
        pts = box.clip(np.array([x0, x0 - st[0] * d[:, 0], x0 + st[0] * d[:, 0], x0 - st[1] * d[:, 1],
                                 x0 + st[1] * d[:, 1]]))
        j = CostModel(sim, inj)(pts[:, 0], pts[:, 1] * 1e-6)
        want = x0.copy()
        for i in range(2):
            rows = [1 + 2 * i, 0, 2 + 2 * i]
            c2, c1, _ = np.polyfit((pts[rows] - x0) @ d[:, i], j[rows], 2)
            assert c2 > 0
            want = want + (-c1 / (2 * c2)) * d[:, i]
        np.testing.assert_allclose(cycle.x, box.clip(want), rtol=0, atol=1e-8 * np.abs(st).max())


@pytest.mark.parametrize("robust", [False, True])
def test_point_costs_are_the_cost_models(sim, robust):
    """The ring's compiled costs are the cost model's, pre-compressed points included, evaluations counted."""
    inj = _injection(sim)
    m_c, m_py = CostModel(sim, inj, 100e-6, "l2", robust), CostModel(sim, inj, 100e-6, "l2", robust)
    pts = np.column_stack([np.linspace(16.0, 18.5, 9), np.r_[np.linspace(0.5, 40.0, 8), -0.2]])
    got = fit_kernel.run_point_costs(m_c, pts)
    want = m_py(pts[:, 0], pts[:, 1] * 1e-6)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert m_c.evaluations == 9 and np.all(np.isfinite(got))
    w = trapezoid_weights(m_py.n, m_py.dt)
    assert got[2] == pytest.approx(float(np.sum(w * _residual(m_py, pts[2]) ** 2)), rel=1e-10)


def test_points_the_simulator_refuses_raise_its_error(sim):
    """A current with a NaN, or an N_u outside the simulator's range, raise the simulator's own error
    from every compiled fit, nothing counted."""
    inj = _injection(sim)
    box = Box(np.array([14.9, -2.0]), np.array([21.1, 10.0]))
    bad = Injection(np.where(np.arange(inj.n) == 40, np.nan, inj.current_a), inj.voltage_v, inj.dt_s,
                    f_open_n=inj.f_open_n)
    model = CostModel(sim, bad)
    with pytest.raises(ParameterError, match="current"):
        local_fit(model, np.array(TRUTH), box)
    with pytest.raises(ParameterError, match="current"):
        fit_kernel.run_point_costs(model, np.array([TRUTH]))
    model = CostModel(sim, inj)
    lo, hi = sim.nu_range
    wide = Box(np.array([lo - 5.0, -2.0]), np.array([hi + 5.0, 10.0]))
    with pytest.raises(ParameterError):
        fit_kernel.run_cycle(model, np.array([hi + 1.0, 2.0]), np.eye(2), np.array([0.1, 0.1]), wide)
    assert model.evaluations == 0
