"""The local Gauss–Newton model of the cost and the conjugate-direction refinement built on it.

A :class:`LocalFit` is the residual, Jacobian, noise level and covariance at one point of the
(N_u N/V, L_h µm) plane; :func:`refine` runs cycles of line searches along the conjugate
directions of that model until the Gauss–Newton step is within a fraction of a standard deviation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from estimator.ident.config import IdentConfig
from estimator.ident.coords import UM_PER_M
from estimator.ident.fit.cost import CostModel
from estimator.ident.fit.fit_kernel import FIT, KernelFit, run_cycle, run_forward_fit
from estimator.ident.fit.search import Box, CostFn, line_search

FD_STEP = np.array([2e-3, 2e-3])   # finite-difference steps: N/V, µm


def cost_fn(model: CostModel) -> CostFn:
    """The cost model as a function of (B, 2) points in (N/V, µm)."""
    def f(x: np.ndarray) -> np.ndarray:
        return model(x[:, 0], x[:, 1] / UM_PER_M)
    return f


@dataclass(frozen=True)
class LocalFit:
    """Gauss–Newton model of the cost at a point: residual, Jacobian, noise and covariance."""

    x: np.ndarray
    criterion: float
    paper_cost_vs: float
    jtj: np.ndarray            # (2, 2) in (N/V, µm), V^2 per unit^2 (sum over samples)
    gn_step: np.ndarray        # Gauss–Newton step in (N/V, µm)
    sigma_v: float
    cov_x: np.ndarray          # covariance in (N/V, µm)
    residual: np.ndarray       # unprojected residual at x (V)
    t_contact_s: float
    t_open_s: float
    success: bool
    directions: tuple[np.ndarray, np.ndarray]   # eigenvectors (columns) and eigenvalues of jtj, weakest first

    @cached_property
    def sd_x(self) -> np.ndarray:
        """Standard deviations of (N_u, L_h) in (N/V, µm): the square roots of ``cov_x``'s diagonal."""
        return np.sqrt(np.abs(np.diag(self.cov_x)))


def local_fit(model: CostModel, x: np.ndarray, box: Box) -> LocalFit:
    """The Gauss–Newton model at x (N/V, µm): x and two forward-difference neighbours (steps toward
    the box's inside) simulated in one batch (:func:`fit_kernel.forward_fit`)."""
    return from_kernel_fit(run_forward_fit(model, x, FD_STEP, box))


def from_kernel_fit(kf: KernelFit) -> LocalFit:
    """The LocalFit of a compiled fit (its conjugate directions already computed)."""
    return LocalFit(kf.x.copy(), float(kf.criterion), float(kf.paper_cost_vs), kf.jtj, kf.gn_step, float(kf.sigma_v),
                    kf.cov_x, kf.residual, float(kf.t_contact_s), float(kf.t_open_s), bool(kf.success),
                    (kf.directions, kf.eigenvalues))


def _within(v: np.ndarray, tol: tuple[float, float], k: float, cov: np.ndarray | None = None) -> bool:
    """Both |components| of ``v`` at most max(tol_i, k sigma_i) (sigma_i from ``cov``'s diagonal;
    just tol_i without ``cov``); False where that bound is NaN, as numpy's comparison is."""
    for i in range(2):
        bound = tol[i]
        if cov is not None:
            bound = _max_nan(k * math.sqrt(abs(float(cov[i, i]))), bound)
        if not float(v[i]) <= bound:
            return False
    return True


def _max_nan(a: float, b: float) -> float:
    """np.maximum of two floats (NaN wins), without its per-call overhead."""
    return a if (a >= b or a != a) else b


def next_steps(sigma_v: float, w: np.ndarray, tol: tuple[float, float]) -> np.ndarray:
    """Step sizes along directions of Gauss–Newton eigenvalues ``w``: two standard deviations
    (noise ``sigma_v``), between 4 min(tol) and 2; the numpy expression
    ``min(max(2 sqrt(max(sigma^2 / max(w, 1e-300), 0)), 4 min(tol)), 2)`` in floats (NaN as numpy)."""
    out = np.empty(2)
    lo = 4 * min(tol)
    for i in range(2):
        sd = math.sqrt(_max_nan(sigma_v ** 2 / _max_nan(float(w[i]), 1e-300), 0.0))
        v = _max_nan(2.0 * sd, lo)
        out[i] = v if (v <= 2.0 or v != v) else 2.0
    return out


def refine(model: CostModel, x0: np.ndarray, directions: np.ndarray, steps: np.ndarray, box: Box,
           config: IdentConfig, max_cycles: int | None = None, j0: float | None = None,
           batched: bool = False) -> tuple[LocalFit, bool, int]:
    """Cycles of line searches along conjugate directions; returns (fit, converged, cycles).

    ``batched``: the directions are already conjugate (warm start), so both line searches of a
    cycle are evaluated in one batch (:func:`fit_kernel.warm_cycle`); a direction whose parabola is
    not convex or leaves the trust region falls back to the bracketing line search.
    """
    x, j = box.clip(x0.astype(float)), j0
    d, st = directions, steps
    tol = (float(config.tol[0]), float(config.tol[1]))
    converged = False
    cycles = 0
    f = cost_fn(model)
    for cycles in range(1, (max_cycles or config.max_cycles) + 1):
        start = x.copy()
        todo = [0, 1]
        fit: LocalFit | None = None
        if batched:
            # stencil, both vertices and the fit at the vertex in one compiled call; a direction whose
            # parabola it could not use is searched below, and the fit made where that search ends
            cycle = run_cycle(model, x, d, st, box)
            x = cycle.x
            if cycle.code == FIT:
                fit = from_kernel_fit(cycle)
            todo = [i for i in range(2) if not cycle.ok[i]]
            j = None
        for i in todo:
            # the vertex of the first search is the centre of the second, and the vertex of the
            # second is the centre of the local fit: both are evaluated there, not twice
            lr = line_search(f, x, d[:, i], float(st[i]), box, j0=j if i == 0 else None, evaluate_vertex=False)
            x, j = lr.x, None
        if fit is None:
            fit = local_fit(model, x, box)
        if not fit.success:
            return fit, False, cycles
        # converged when the last cycle hardly moved, or when the Gauss–Newton model puts the
        # minimum within a quarter standard deviation (or the tolerance) of where we are (2-vectors
        # as floats: the same comparisons as numpy's, NaN included, without its per-call overhead)
        if _within(np.abs(x - start), tol, 0.0) or _within(np.abs(fit.gn_step), tol, 0.25, fit.cov_x):
            converged = True
            break
        d, w = fit.directions
        # next steps: two standard deviations along each direction, at least the tolerance
        st = next_steps(fit.sigma_v, w, tol)
        j = fit.criterion
        # |GN step| <= 4 max(sigma, tol): _within with the tolerances scaled too (times 4 is exact)
        if batched and _within(np.abs(fit.gn_step), (4.0 * tol[0], 4.0 * tol[1]), 4.0, fit.cov_x):
            # near the minimum already: one Gauss–Newton step is cheaper than another cycle
            x_gn = box.clip(x + fit.gn_step)
            fit_gn = local_fit(model, x_gn, box)
            if fit_gn.success and fit_gn.criterion <= fit.criterion:
                fit, x = fit_gn, x_gn
                if _within(np.abs(fit.gn_step), tol, 0.25, fit.cov_x):
                    converged = True
                    break
            elif fit_gn.success and _within(np.abs(fit_gn.gn_step), tol, 0.25, fit_gn.cov_x):
                # the fit at the Gauss–Newton point, with its own Jacobian, puts the minimum within a
                # quarter standard deviation of that point, and the cost here is lower still: here is
                # as close to the minimum (another cycle from here moved 0.01-0.14 sigma, measured)
                converged = True
                break
            j = fit.criterion
    assert fit is not None   # every cycle ends with a fit
    return fit, converged, cycles


