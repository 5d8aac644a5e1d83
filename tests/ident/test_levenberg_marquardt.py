"""The calibration's least-squares solver against scipy's trust-region solver on the same problems."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from estimator.ident.fit.levenberg_marquardt import least_squares_lm


def _problem(seed: int):
    """A tall nonlinear fit: a sum of two damped exponentials (4 unknowns) to 2,000 noisy samples."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 5.0, 2000)
    truth = np.array([2.0, 1.3, 0.7, 0.25])

    def model(x):
        return x[0] * np.exp(-x[1] * t) + x[2] * np.exp(-x[3] * t)

    y = model(truth) + 0.01 * rng.standard_normal(t.size)

    def residual(x):
        return model(x) - y

    def jacobian(x):
        return np.column_stack([np.exp(-x[1] * t), -x[0] * t * np.exp(-x[1] * t),
                                np.exp(-x[3] * t), -x[2] * t * np.exp(-x[3] * t)])

    return residual, jacobian, truth


def test_it_finds_scipys_minimum_inside_the_bounds():
    residual, jacobian, truth = _problem(1)
    lo, hi = np.array([0.0, 0.5, 0.0, 0.0]), np.array([5.0, 3.0, 5.0, 0.5])
    x0 = np.array([1.0, 1.0, 1.0, 0.1])
    ours = least_squares_lm(residual, jacobian, x0, lo, hi, max_nfev=100)
    ref = least_squares(residual, x0, jac=jacobian, bounds=(lo, hi), method="trf", x_scale="jac", xtol=1e-12,
                        ftol=1e-14, gtol=1e-14)
    assert ours.converged
    np.testing.assert_allclose(ours.x, ref.x, rtol=1e-5, atol=1e-7)
    assert abs(ours.cost - ref.cost) <= 1e-9 * ref.cost
    np.testing.assert_allclose(ours.fun, residual(ours.x))
    np.testing.assert_allclose(ours.jac, jacobian(ours.x))
    assert np.all(np.abs(ours.x - truth) < 0.05)


def test_an_active_bound_holds_the_solution_where_scipy_puts_it():
    residual, jacobian, _ = _problem(2)
    lo, hi = np.array([0.0, 0.5, 0.0, 0.0]), np.array([5.0, 3.0, 5.0, 0.2])   # the slow rate 0.25 is out of reach
    x0 = np.array([1.0, 1.0, 1.0, 0.1])
    ours = least_squares_lm(residual, jacobian, x0, lo, hi, max_nfev=200)
    ref = least_squares(residual, x0, jac=jacobian, bounds=(lo, hi), method="trf", x_scale="jac", xtol=1e-12,
                        ftol=1e-14, gtol=1e-14)
    assert ours.x[3] == hi[3]
    np.testing.assert_allclose(ours.x, ref.x, rtol=1e-4, atol=1e-6)
    assert ours.cost <= ref.cost * (1 + 1e-6)


def test_the_budget_of_residual_evaluations_is_kept():
    residual, jacobian, _ = _problem(3)
    calls = []

    def counted(x):
        calls.append(1)
        return residual(x)

    res = least_squares_lm(counted, jacobian, np.array([1.0, 1.0, 1.0, 0.1]), np.zeros(4), np.full(4, 5.0),
                           max_nfev=4)
    assert len(calls) == res.nfev <= 4 and not res.converged
