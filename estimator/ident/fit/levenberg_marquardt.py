"""Bounded Levenberg–Marquardt for tall least-squares problems with few unknowns.

The electrical calibration fits about 75 unknowns to about 12,000 residuals. A trust-region solver
that decomposes the Jacobian itself (scipy's ``trf``: an SVD of the 12,000 × 75 matrix, ≈ 60 ms, on
every iteration) spent a third of a calibration there. This one works on the normal equations
``J'J`` (75 × 75, ≈ 3 ms to form), which the calibration's priors keep well conditioned:

- the step solves ``(J'J + lambda diag(J'J)) dx = -J'r`` (Marquardt's scaling: each unknown in the
  units its own column gives it, as ``x_scale="jac"`` does);
- an unknown at a bound whose gradient pushes outwards is held there, the step solved for the others,
  and a step leaving the bounds is projected back onto them;
- ``lambda`` follows the gain ratio (actual over predicted reduction of the cost), Nielsen's rule;
- it stops when the cost falls by less than ``ftol`` of itself, the step is below ``xtol`` of ``x``,
  or ``max_nfev`` residuals have been evaluated.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

LAMBDA_START = 1e-3      # the first damping, relative to J'J's diagonal
LAMBDA_MIN = 1e-12
LAMBDA_MAX = 1e16        # damped this far without a step that lowers the cost: nothing left to gain


@dataclass(frozen=True)
class LeastSquaresResult:
    """The solution: ``x``, ``cost`` = 0.5 ``fun``'fun, the residual ``fun`` and Jacobian ``jac`` at
    ``x``, the residual evaluations ``nfev``, and whether a tolerance (not the budget) stopped it."""

    x: np.ndarray
    cost: float
    fun: np.ndarray
    jac: np.ndarray
    nfev: int
    converged: bool


def least_squares_lm(residual: Callable[[np.ndarray], np.ndarray], jacobian: Callable[[np.ndarray], np.ndarray],
                     x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_nfev: int = 30, xtol: float = 1e-8,
                     ftol: float = 1e-10) -> LeastSquaresResult:
    """Minimise 0.5 ||residual(x)||^2 within ``lo <= x <= hi`` from ``x0`` (clipped into the bounds);
    ``jacobian(x)`` is d residual / dx at an ``x`` whose residual was just evaluated."""
    x = np.clip(np.asarray(x0, dtype=float), lo, hi)
    r = residual(x)
    cost = 0.5 * float(r @ r)
    nfev = 1
    jac = jacobian(x)
    lam, grow = LAMBDA_START, 2.0
    converged = False
    while nfev < max_nfev:
        a = jac.T @ jac
        g = jac.T @ r
        d = np.maximum(np.diag(a), 1e-12 * float(np.max(np.diag(a))) + 1e-300)
        # unknowns held at a bound by a gradient pushing outwards stay there: the step is solved for the rest
        free = ~(((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0)))
        step = np.zeros_like(x)
        try:
            step[free] = np.linalg.solve(a[np.ix_(free, free)] + lam * np.diag(d[free]), -g[free])
        except np.linalg.LinAlgError:
            lam, grow = lam * grow, grow * 2.0
            if lam > LAMBDA_MAX:      # a Jacobian no damping makes solvable (not finite): stop where it is
                break
            continue
        x_new = np.clip(x + step, lo, hi)
        step = x_new - x
        predicted = -float(g @ step + 0.5 * step @ a @ step)
        r_new = residual(x_new)
        nfev += 1
        cost_new = 0.5 * float(r_new @ r_new)
        gain = (cost - cost_new) / predicted if predicted > 0 else -1.0
        if np.isfinite(cost_new) and gain > 0:
            small_step = float(np.linalg.norm(step)) <= xtol * (xtol + float(np.linalg.norm(x)))
            small_fall = cost - cost_new <= ftol * cost
            x, r, cost = x_new, r_new, cost_new
            jac = jacobian(x)
            lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3), LAMBDA_MIN)
            grow = 2.0
            if small_step or small_fall:
                converged = True
                break
        else:
            if float(np.linalg.norm(step)) <= xtol * (xtol + float(np.linalg.norm(x))):
                converged = True      # no step left that lowers the cost: a minimum (or a bound)
                break
            lam, grow = lam * grow, grow * 2.0
    return LeastSquaresResult(x, cost, r, jac, nfev, converged)
