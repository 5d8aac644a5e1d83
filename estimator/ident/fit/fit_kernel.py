"""The local fits of the (N_u, L_h) search, compiled (numba): one call per fit.

Every fit the searches make runs here, on a :class:`~estimator.ident.fit.cost.Problem` (one cost
window as compiled code reads it), and returns a :class:`KernelFit` with named fields:

- :func:`forward_fit`: a point and its two forward-difference neighbours in one batch, the
  Gauss–Newton model there (residual, Jacobian, noise level, covariance, step);
- :func:`warm_cycle`: one warm refinement cycle: the conjugate stencil (five candidates), both
  parabolic vertices, the stencil's central-difference Jacobian and the Gauss–Newton model at the
  vertex (six simulations);
- :func:`gauss_newton`: the cold start's trust-region Gauss–Newton loop, each step a forward fit;
- :func:`point_costs`: the costs of a batch of points (the cold start's ring probe).

The decisions around them (bracketing line searches where a parabola is not convex, convergence
of the refinement, the ring, the global search) are Python, in :mod:`~estimator.ident.fit.local_fit`
and :mod:`~estimator.ident.fit.cold_start`; nothing here has a Python twin. Candidates with L_h <= 0
start pre-compressed (:func:`kernel.run_batch`). Points the simulator refuses (a non-finite
current, an N_u outside its range) give ``NOT_SIMULABLE`` and the wrappers raise the simulator's
own :class:`~estimator.errors.ParameterError`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from estimator._compiled import njit
from estimator._compiled.direct_call import DirectCall, c_float
from estimator.errors import ParameterError
from estimator.ident.coords import UM_PER_M
from estimator.ident.fit.cost import CostModel, Problem, costs_of, noise_sigma, residuals_into
from estimator.ident.fit.search import TRUST_STEPS, Box, parabola_vertex
from estimator.model import kernel

FIT, PARTIAL, NOT_SIMULABLE = 0, 1, 2
"""Outcomes: the fit is done; a warm cycle found its vertex (``ok`` says along which directions)
but not the fit there (a direction's parabola was not usable, the stencil left the box or a
simulation failed); the points could not be simulated (nothing was)."""


class KernelFit(NamedTuple):
    """A compiled fit (arrays owned by the caller afterwards); NaN fields where ``code`` is not FIT."""

    code: int
    evaluations: int
    x: np.ndarray          # (2,) the point in (N/V, µm)
    ok: np.ndarray         # (2,) bool: a warm cycle's parabola along that direction gave the vertex
    jac: np.ndarray        # (2, N) dU/dx (V per N/V, V per µm); NaN if not known
    criterion: float       # the cost at x (V^2 s or V s)
    paper_cost_vs: float   # eq. 28's L1 cost at x (V s)
    jtj: np.ndarray        # (2, 2)
    gn_step: np.ndarray    # (2,) Gauss–Newton step in (N/V, µm)
    sigma_v: float         # noise level of the residual (V)
    cov_x: np.ndarray      # (2, 2) in (N/V, µm), inf where singular
    residual: np.ndarray   # (N,) unprojected U_m - U_sim at x (V)
    t_contact_s: float
    t_open_s: float
    success: bool
    directions: np.ndarray  # (2, 2) eigenvectors of jtj (columns), weakest first
    eigenvalues: np.ndarray  # (2,) clipped at 0


class GaussNewtonRules(NamedTuple):
    """The cold start's trust-region rules (see :func:`cold_start.gauss_newton_fit`)."""

    radius_sd: float        # first radius at least this many of the first fit's standard deviations
    min_sd: np.ndarray      # (2,) each standard deviation at least this (N/V, µm)
    tol: np.ndarray         # (2,) tolerances (N/V, µm)
    max_steps: int
    converged_sd: float     # converged: the step within this many standard deviations
    close_sd: float         # ... or within this many, and taking it did not lower the cost
    shrink: float           # a refused step shrinks the radius to this fraction of its length


class GaussNewtonRun(NamedTuple):
    """What :func:`gauss_newton` returns: the fit at the last point taken."""

    code: int               # FIT or NOT_SIMULABLE
    converged: bool
    steps: int
    evaluations: int        # simulations, all steps
    radius: np.ndarray      # (2,) the trust region at the end (N/V, µm)
    fit: KernelFit


@njit(cache=True, nogil=True)
def _simulable(p: Problem, pts: np.ndarray) -> bool:
    """Whether the simulator takes the points (B, 2) in (N/V, µm) (:func:`kernel.check_inputs`)."""
    code, _ = kernel.check_inputs(p.current, pts[:, 0].copy(), pts[:, 1].copy(), np.full(pts.shape[0], p.f_open_n),
                                  p.nu_lo, p.nu_hi)
    return code == kernel.INPUTS_OK


@njit(cache=True, nogil=True)
def _simulate(p: Problem, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Voltages (B, N) in V, success, contact and opening times (s) of candidates at ``pts`` (B, 2)."""
    nb = pts.shape[0]
    nu = np.empty(nb)
    lh = np.empty(nb)
    for b in range(nb):
        nu[b] = pts[b, 0]
        lh[b] = pts[b, 1] / UM_PER_M
    u, _, _, _, tc, to, _, success = kernel.run_table(p.model, p.automaton, p.table, nu, lh,
                                                      np.full(nb, p.f_open_n), p.current, p.h_us)
    return u, success, tc, to


@njit(cache=True, nogil=True)
def _residuals(p: Problem, u: np.ndarray) -> np.ndarray:
    """The (projected) residuals (B, N) of simulated voltages ``u`` (B, N)."""
    r = np.empty(u.shape)
    residuals_into(p.measured, u, p.basis, p.robust, r)
    return r


@njit(cache=True, nogil=True)
def _no_fit(code: int, evaluations: int, x: np.ndarray, ok: np.ndarray, jac: np.ndarray) -> KernelFit:
    """The :class:`KernelFit` of a call that stopped before the fit (NaN fields)."""
    n = jac.shape[1]
    nan22 = np.full((2, 2), np.nan)
    return KernelFit(code, evaluations, x, ok, jac, np.nan, np.nan, nan22, np.full(2, np.nan), np.nan, nan22.copy(),
                     np.full(n, np.nan), np.nan, np.nan, False, nan22.copy(), np.full(2, np.nan))


@njit(cache=True, nogil=True)
def _fit_at(p: Problem, evaluations: int, x: np.ndarray, ok: np.ndarray, jac: np.ndarray, u: np.ndarray, r0: np.ndarray, tc: float, to: float,
            u_ok: bool, success: bool) -> KernelFit:
    """The Gauss–Newton model at ``x`` from its simulated voltage ``u`` (V), its (projected) residual
    ``r0`` and ``jac`` = dU/dx (2, N); ``u_ok``: the point's own simulation succeeded, ``success``:
    every simulation behind the fit did."""
    n = u.shape[0]
    ok1 = np.empty(1, dtype=np.bool_)
    ok1[0] = u_ok
    crit = costs_of(r0.reshape((1, n)), p.weights, p.l1, ok1)[0]
    raw = np.empty(n)
    paper = 0.0
    for k in range(n):
        raw[k] = p.measured[k] - u[k]
        paper += abs(raw[k]) * p.weights[k]
    jtj = np.empty((2, 2))
    jr = np.zeros(2)
    for a in range(2):
        for b in range(2):
            s = 0.0
            for k in range(n):
                s += jac[a, k] * jac[b, k]
            jtj[a, b] = s
        for k in range(n):
            jr[a] += jac[a, k] * r0[k]
    fine = success and np.all(np.isfinite(jtj))
    sigma = noise_sigma(r0) if fine else np.nan
    det = jtj[0, 0] * jtj[1, 1] - jtj[0, 1] * jtj[1, 0] if fine else 0.0
    cov = np.full((2, 2), np.inf)
    step = np.zeros(2)
    if fine and det > 1e-14 * jtj[0, 0] * jtj[1, 1]:
        inv = np.empty((2, 2))
        inv[0, 0], inv[0, 1] = jtj[1, 1] / det, -jtj[0, 1] / det
        inv[1, 0], inv[1, 1] = -jtj[1, 0] / det, jtj[0, 0] / det
        for a in range(2):
            for b in range(2):
                cov[a, b] = sigma ** 2 * inv[a, b]
            step[a] = inv[a, 0] * jr[0] + inv[a, 1] * jr[1]
    dirs = np.full((2, 2), np.nan)
    eig = np.full(2, np.nan)
    if fine:
        w, v = np.linalg.eigh(0.5 * (jtj + jtj.T))
        dirs = np.ascontiguousarray(v)
        eig = np.maximum(w, 0.0)
    return KernelFit(FIT, evaluations, x, ok, jac, crit, paper, jtj, step, sigma, cov, raw, tc, to, bool(fine), dirs, eig)


@njit(cache=True, nogil=True)
def forward_fit(p: Problem, x: np.ndarray, fd: np.ndarray, hi: np.ndarray) -> KernelFit:
    """The Gauss–Newton model at ``x`` (N/V, µm) from x and its two forward-difference neighbours
    (steps ``fd``, turned back where they would pass ``hi``), simulated in one batch."""
    n = p.current.shape[0]
    steps = np.empty(2)
    for i in range(2):
        steps[i] = fd[i] if x[i] + fd[i] <= hi[i] else -fd[i]
    pts = np.empty((3, 2))
    for b in range(3):
        pts[b, 0] = x[0]
        pts[b, 1] = x[1]
    pts[1, 0] += steps[0]
    pts[2, 1] += steps[1]
    ok = np.ones(2, dtype=np.bool_)
    if not _simulable(p, pts):
        return _no_fit(NOT_SIMULABLE, 0, x.copy(), ok, np.full((2, n), np.nan))
    u, success, tc, to = _simulate(p, pts)
    r = _residuals(p, u)
    jac = np.empty((2, n))
    for k in range(n):
        jac[0, k] = -(r[1, k] - r[0, k]) / steps[0]
        jac[1, k] = -(r[2, k] - r[0, k]) / steps[1]
    return _fit_at(p, 3, x.copy(), ok, jac, u[0], r[0], tc[0], to[0], success[0],
                   success[0] and success[1] and success[2])


@njit(cache=True, nogil=True)
def warm_cycle(p: Problem, x0: np.ndarray, d: np.ndarray, st: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> KernelFit:
    """One warm refinement cycle from ``x0`` along the (conjugate) columns of ``d`` with steps ``st``
    (N/V, µm) in the box ``lo``, ``hi``: the stencil {x0, x0 -/+ st_i d_i} in one batch, the parabola's
    vertex along each direction (within :data:`TRUST_STEPS` steps), and where both were found inside
    the box the Gauss–Newton model at the vertex with the stencil's central differences as Jacobian."""
    n = p.current.shape[0]
    nanjac = np.full((2, n), np.nan)
    cand = np.empty((5, 2))
    pts = np.empty((5, 2))
    for i in range(2):
        cand[0, i] = x0[i]
        cand[1, i] = x0[i] - st[0] * d[i, 0]
        cand[2, i] = x0[i] + st[0] * d[i, 0]
        cand[3, i] = x0[i] - st[1] * d[i, 1]
        cand[4, i] = x0[i] + st[1] * d[i, 1]
    inside = True
    for b in range(5):
        for i in range(2):
            v = min(max(cand[b, i], lo[i]), hi[i])
            pts[b, i] = v
            if v != cand[b, i]:
                inside = False
    if not _simulable(p, pts):
        return _no_fit(NOT_SIMULABLE, 0, x0.copy(), np.zeros(2, dtype=np.bool_), nanjac)
    u, success, _, _ = _simulate(p, pts)
    r = _residuals(p, u)
    j = costs_of(r, p.weights, p.l1, success)
    x = x0.copy()
    ok = np.zeros(2, dtype=np.bool_)
    for i in range(2):
        a = np.empty(3)
        for q, b in enumerate((1 + 2 * i, 0, 2 + 2 * i)):
            a[q] = (pts[b, 0] - x0[0]) * d[0, i] + (pts[b, 1] - x0[1]) * d[1, i]
        vx, _ = parabola_vertex(a[0], a[1], a[2], j[1 + 2 * i], j[0], j[2 + 2 * i])
        if np.isfinite(vx) and abs(vx) <= TRUST_STEPS * st[i] and a[0] < a[1] < a[2]:
            x[0] += vx * d[0, i]
            x[1] += vx * d[1, i]
            ok[i] = True
    for i in range(2):
        x[i] = min(max(x[i], lo[i]), hi[i])
    if not (inside and ok[0] and ok[1] and success.all()):
        return _no_fit(PARTIAL, 5, x, ok, nanjac)
    # central differences along d1, d2 are the Jacobian: dU/dx = D dU/dalpha
    jac = np.empty((2, n))
    for k in range(n):
        ja0 = -(r[2, k] - r[1, k]) / (2 * st[0])
        ja1 = -(r[4, k] - r[3, k]) / (2 * st[1])
        jac[0, k] = d[0, 0] * ja0 + d[0, 1] * ja1
        jac[1, k] = d[1, 0] * ja0 + d[1, 1] * ja1
    xv = np.empty((1, 2))
    xv[0, 0] = x[0]
    xv[0, 1] = x[1]
    uv, sv, tcv, tov = _simulate(p, xv)
    rv = _residuals(p, uv)
    return _fit_at(p, 6, x, ok, jac, uv[0], rv[0], tcv[0], tov[0], sv[0], sv[0])


@njit(cache=True, nogil=True)
def _max_nan(a: float, b: float) -> float:
    """np.maximum of two floats (NaN wins)."""
    return a if (a >= b or a != a) else b


@njit(cache=True, nogil=True)
def widened_radius(rad: np.ndarray, cov: np.ndarray, k: float, min_sd: np.ndarray) -> np.ndarray:
    """A copy of the trust region ``rad`` (N/V, µm), each radius raised to ``k`` standard deviations of
    ``cov`` (each at least ``min_sd``) where that is larger and finite (``k <= 0``: unchanged)."""
    out = rad.copy()
    if k > 0.0:
        for i in range(2):
            r = k * _max_nan(np.sqrt(abs(cov[i, i])), min_sd[i])
            if r > out[i] and r < np.inf:
                out[i] = r
    result: np.ndarray = out
    return result


@njit(cache=True, nogil=True)
def gauss_newton(p: Problem, x: np.ndarray, fd: np.ndarray, lo: np.ndarray, hi: np.ndarray, rad: np.ndarray, rules: GaussNewtonRules) -> GaussNewtonRun:
    """Trust-region Gauss–Newton steps from ``x`` (inside the box ``lo``, ``hi``; N/V, µm), each step a
    :func:`forward_fit` (steps ``fd``); first radius ``rad``, widened to ``rules.radius_sd`` of the first
    fit's standard deviations (:func:`widened_radius`). A step that lowers the cost is taken and the
    radius doubles; one that does not shrinks the radius to ``rules.shrink`` times that step.
    Converged when the step is within ``rules.converged_sd`` standard deviations (or the tolerance),
    or within ``rules.close_sd`` and taking it did not lower the cost; not converged after
    ``rules.max_steps`` steps, when a step no longer moves the point, or when a simulation fails."""
    tol = rules.tol
    fit = forward_fit(p, x, fd, hi)
    evaluations = fit.evaluations
    if fit.code != FIT:
        return GaussNewtonRun(NOT_SIMULABLE, False, 0, evaluations, rad, fit)
    rad = widened_radius(rad, fit.cov_x, rules.radius_sd, rules.min_sd)
    for k in range(rules.max_steps):
        if not fit.success:
            return GaussNewtonRun(FIT, False, k, evaluations, rad, fit)
        step, cov = fit.gn_step, fit.cov_x
        sd0, sd1 = np.sqrt(abs(cov[0, 0])), np.sqrt(abs(cov[1, 1]))
        if (abs(step[0]) <= _max_nan(tol[0], rules.converged_sd * sd0)
                and abs(step[1]) <= _max_nan(tol[1], rules.converged_sd * sd1)):
            return GaussNewtonRun(FIT, True, k, evaluations, rad, fit)
        q0 = rad[0] / _max_nan(abs(step[0]), 1e-300)
        q1 = rad[1] / _max_nan(abs(step[1]), 1e-300)
        q = np.nan if (q0 != q0 or q1 != q1) else min(q0, q1)
        scale = q if q < 1.0 else 1.0     # a NaN ratio takes the whole step
        x_new = np.empty(2)
        moved = np.empty(2)
        for i in range(2):
            x_new[i] = min(max(fit.x[i] + scale * step[i], lo[i]), hi[i])
            moved[i] = abs(x_new[i] - fit.x[i])
        if moved[0] <= tol[0] and moved[1] <= tol[1]:
            return GaussNewtonRun(FIT, False, k, evaluations, rad, fit)
        fit_new = forward_fit(p, x_new, fd, hi)
        evaluations += fit_new.evaluations
        if fit_new.code != FIT:
            return GaussNewtonRun(NOT_SIMULABLE, False, k, evaluations, rad, fit_new)
        if fit_new.success and fit_new.criterion < fit.criterion:
            fit = fit_new
            rad = 2.0 * rad
        elif (scale == 1.0 and abs(step[0]) <= _max_nan(tol[0], rules.close_sd * sd0)
              and abs(step[1]) <= _max_nan(tol[1], rules.close_sd * sd1)):
            return GaussNewtonRun(FIT, True, k, evaluations, rad, fit)
        else:
            for i in range(2):
                rad[i] = rules.shrink * moved[i] + tol[i]
    return GaussNewtonRun(FIT, False, rules.max_steps, evaluations, rad, fit)


@njit(cache=True, nogil=True)
def point_costs(p: Problem, pts: np.ndarray) -> tuple[bool, np.ndarray]:
    """The costs of the points (B, 2) in (N/V, µm), +inf where a simulation failed; and whether they
    could be simulated (False: nothing was)."""
    nb = pts.shape[0]
    if not _simulable(p, pts):
        return False, np.full(nb, np.nan)
    u, success, _, _ = _simulate(p, pts)
    return True, costs_of(_residuals(p, u), p.weights, p.l1, success)


# ---- the Python side: one direct call each (the Problem's types never change) ---------------------
_forward_fit = DirectCall(forward_fit)
_warm_cycle = DirectCall(warm_cycle)
_gauss_newton = DirectCall(gauss_newton)
_point_costs = DirectCall(point_costs)


def _refuse(model: CostModel, x: np.ndarray) -> ParameterError:
    """The simulator's own error for a fit it could not simulate around ``x`` (N/V, µm)."""
    try:
        model.sim.simulate(model.current, float(x[0]), float(x[1]) / UM_PER_M, model.injection.f_open_n)
    except ParameterError as err:
        return err
    return ParameterError(f"the fit around N_u = {x[0]:.4g} N/V, L_h = {x[1]:.4g} µm leaves the simulator's "
                          f"N_u range {model.sim.nu_range}")


def run_forward_fit(model: CostModel, x: np.ndarray, fd: np.ndarray, box: Box) -> KernelFit:
    """:func:`forward_fit` on a cost model (its evaluations counted)."""
    out: KernelFit = _forward_fit(model.problem, c_float(x), c_float(fd), c_float(box.hi))
    if out.code == NOT_SIMULABLE:
        raise _refuse(model, x)
    model.evaluations += out.evaluations
    return out


def run_cycle(model: CostModel, x0: np.ndarray, d: np.ndarray, st: np.ndarray, box: Box) -> KernelFit:
    """:func:`warm_cycle` on a cost model (its evaluations counted) from ``x0`` along ``d``, ``st``."""
    out: KernelFit = _warm_cycle(model.problem, c_float(x0), c_float(d), c_float(st), c_float(box.lo),
                                 c_float(box.hi))
    if out.code == NOT_SIMULABLE:
        raise _refuse(model, x0)
    model.evaluations += out.evaluations
    return out


def run_gauss_newton(model: CostModel, x: np.ndarray, fd: np.ndarray, box: Box, radius: np.ndarray,
                     rules: GaussNewtonRules) -> GaussNewtonRun:
    """:func:`gauss_newton` on a cost model (its evaluations counted) from ``x`` (inside the box)."""
    run: GaussNewtonRun = _gauss_newton(model.problem, c_float(x), c_float(fd), c_float(box.lo), c_float(box.hi),
                                        c_float(radius), rules)
    if run.code == NOT_SIMULABLE:
        raise _refuse(model, run.fit.x)
    model.evaluations += run.evaluations
    return run


def run_point_costs(model: CostModel, pts: np.ndarray) -> np.ndarray:
    """:func:`point_costs` on a cost model (its evaluations counted)."""
    simulated, j = _point_costs(model.problem, c_float(pts))
    if not simulated:
        raise _refuse(model, pts[0])
    model.evaluations += int(j.shape[0])
    result: np.ndarray = j
    return result
