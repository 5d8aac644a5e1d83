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

from estimator.ident.compiled_cycle import CYCLE_FALLBACK, CYCLE_FIT, CycleFit, run_cycle, run_forward_fit
from estimator.ident.config import IdentConfig
from estimator.ident.coords import UM_PER_M
from estimator.ident.cost import CostModel, noise_sigma_v
from estimator.ident.search import Box, conjugate_directions, conjugate_stencil, conjugate_vertex, line_search

FD_STEP = np.array([2e-3, 2e-3])   # finite-difference steps: N/V, µm


def cost_fn(model: CostModel):
    """The cost model as a function of (B, 2) points in (N/V, µm)."""
    def f(x: np.ndarray) -> np.ndarray:
        return model(x[:, 0], x[:, 1] / UM_PER_M)
    return f


def simulate_at(model: CostModel, pts: np.ndarray):
    """The model's simulation of (B, 2) points in (N/V, µm)."""
    return model.simulate(pts[:, 0], pts[:, 1] / UM_PER_M)


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

    @cached_property
    def sd_x(self) -> np.ndarray:
        """Standard deviations of (N_u, L_h) in (N/V, µm): the square roots of ``cov_x``'s diagonal."""
        return np.sqrt(np.abs(np.diag(self.cov_x)))

    @cached_property
    def directions(self) -> tuple[np.ndarray, np.ndarray]:
        """Conjugate directions (columns) and eigenvalues of ``jtj``, weakest first (computed once)."""
        return conjugate_directions(self.jtj)


def local_fit(model: CostModel, x: np.ndarray, box: Box) -> LocalFit:
    """Simulate x and two forward-difference neighbours in one batch (steps toward the box inside);
    compiled (:func:`compiled_cycle.forward_fit`) unless a point needs a pre-compressed start."""
    cf = run_forward_fit(model, x, FD_STEP, box)
    return from_cycle_fit(cf) if cf.code == CYCLE_FIT else _forward_fit(model, x, box)


def _forward_fit(model: CostModel, x: np.ndarray, box: Box) -> LocalFit:
    """:func:`local_fit` in Python (any L_h: pre-compressed starts included)."""
    steps = np.where(x + FD_STEP <= box.hi, FD_STEP, -FD_STEP)
    pts = np.array([x, x + [steps[0], 0.0], x + [0.0, steps[1]]])
    res = simulate_at(model, pts)
    r = model.residuals(res)
    jac = -(r[1:] - r[0]) / steps[:, None]            # dU_sim/dx, (2, N)
    return _fit_from(model, x, res, r[0], jac, bool(res.success.all()))


def fit_with_jacobian(model: CostModel, x: np.ndarray, jac: np.ndarray) -> LocalFit:
    """Local fit at x with a Jacobian known from elsewhere (the conjugate stencil): one simulation."""
    res = simulate_at(model, x[None, :])
    return _fit_from(model, x, res, model.residuals(res)[0], jac, bool(res.success[0]))


def _fit_from(model: CostModel, x: np.ndarray, res, r0: np.ndarray, jac: np.ndarray, ok: bool) -> LocalFit:
    """Gauss–Newton model from the residual r0 at x (candidate 0 of ``res``) and dU/dx ``jac`` (2, N)."""
    crit = model.from_result(res)
    raw = model.measured - res.voltage_v[0]
    jtj = jac @ jac.T
    ok = ok and bool(np.isfinite(jtj).all())
    sigma = noise_sigma_v(r0) if ok else float("nan")
    det = float(jtj[0, 0] * jtj[1, 1] - jtj[0, 1] * jtj[1, 0]) if ok else 0.0
    if ok and det > 1e-14 * float(jtj[0, 0] * jtj[1, 1]):
        inv = np.array([[jtj[1, 1], -jtj[0, 1]], [-jtj[1, 0], jtj[0, 0]]]) / det
        cov = sigma ** 2 * inv
        step = inv @ (jac @ r0)
    else:
        cov, step = np.full((2, 2), np.inf), np.zeros(2)
    return LocalFit(x.copy(), float(crit[0]), float(model.paper_cost_vs(res)[0]), jtj, step, sigma, cov,
                    raw, float(res.t_contact_s[0]), float(res.t_open_s[0]), ok)


def _stencil_cycle(model: CostModel, x: np.ndarray, d: np.ndarray, st: np.ndarray,
                   box: Box) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The batched cycle's stencil in Python: the vertex, which directions gave it, and the
    Jacobian (None unless the stencil was inside the box, both vertices found and all simulated)."""
    pts, inside = conjugate_stencil(x, d, st, box)
    res = simulate_at(model, pts)
    xv, ok = conjugate_vertex(pts, model.from_result(res), x, d, st, box)
    if not (inside and ok.all() and res.success.all()):
        return xv, ok, None
    # the stencil's central differences along d1, d2 are the Gauss–Newton Jacobian:
    # dU/dx = D (dU/dalpha), with alpha the coordinates along the directions
    r = model.residuals(res)
    jac_a = np.stack([-(r[2] - r[1]) / (2 * st[0]), -(r[4] - r[3]) / (2 * st[1])])
    return xv, ok, d @ jac_a


def from_cycle_fit(cf: CycleFit) -> LocalFit:
    """The LocalFit of a compiled cycle (its conjugate directions already computed)."""
    fit = LocalFit(cf.x.copy(), float(cf.criterion), float(cf.paper_cost_vs), cf.jtj, cf.gn_step, float(cf.sigma_v),
                   cf.cov_x, cf.residual, float(cf.t_contact_s), float(cf.t_open_s), bool(cf.success))
    if cf.success:
        fit.__dict__["directions"] = (cf.directions, cf.eigenvalues)   # the cached_property's slot
    return fit


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
    cycle are evaluated in one batch (:func:`conjugate_stencil`, :func:`conjugate_vertex`); a direction whose parabola is not
    convex or leaves the trust region falls back to the bracketing line search.
    """
    x, j = box.clip(x0.astype(float)), j0
    d, st = directions, steps
    tol = tuple(config.tol)
    converged = False
    cycles = 0
    f = cost_fn(model)
    for cycles in range(1, (max_cycles or config.max_cycles) + 1):
        start = x.copy()
        todo = [0, 1]
        jac = None
        fit = None
        if batched:
            # the common case in one compiled call (compiled_cycle); what it cannot do, Python does
            cf = run_cycle(model, x, d, st, box)
            if cf.code == CYCLE_FALLBACK:
                x, ok, jac = _stencil_cycle(model, x, d, st, box)
            else:
                x, ok = cf.x, cf.ok
                jac = cf.jac if np.isfinite(cf.jac[0, 0]) else None
                if cf.code == CYCLE_FIT:
                    fit = from_cycle_fit(cf)
            todo = [i for i in range(2) if not ok[i]]
            j = None
        for i in todo:
            # the vertex of the first search is the centre of the second, and the vertex of the
            # second is the centre of the local fit: both are evaluated there, not twice
            lr = line_search(f, x, d[:, i], float(st[i]), box, j0=j if i == 0 else None, evaluate_vertex=False)
            x, j = lr.x, None
        if fit is None:
            fit = fit_with_jacobian(model, x, jac) if jac is not None else local_fit(model, x, box)
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
    return fit, converged, cycles


