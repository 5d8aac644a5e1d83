"""One warm refinement cycle in one compiled call (numba): stencil, vertex, Gauss–Newton fit.

:func:`estimator.ident.local_fit.refine` with ``batched=True`` runs, per cycle, the conjugate
stencil (five candidates), both parabolic vertices, the stencil's central-difference Jacobian, one
simulation at the vertex and the Gauss–Newton model there. In Python those were two kernel calls
and some forty small numpy operations around them (≈ 0.25 ms per warm update, more than the kernel
itself). :func:`warm_cycle` does the same arithmetic in one call; it is the compiled twin of
:func:`search.conjugate_stencil`, :func:`search.conjugate_vertex` (whose parabola,
:func:`search.parabola_vertex`, it calls), :meth:`cost.CostModel.cost_of`
and :func:`local_fit._fit_from` (the noise level is :func:`cost.noise_sigma` itself), and
``tests/test_speed_parts.py`` holds the two to the same results (to rounding: sums are taken in
another order than numpy's).
:func:`forward_fit` is the same for :func:`local_fit.local_fit` (x and two forward differences).

Only the common case is compiled: every point inside the box with L_h > 0, both parabolas convex
and within the trust region, every simulation successful. Anything else returns ``CYCLE_PARTIAL``
or ``CYCLE_FALLBACK`` and the caller continues in Python from there.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from estimator.ident.coords import UM_PER_M
from estimator.ident.cost import CostModel, noise_sigma
from estimator.ident.search import TRUST_STEPS, Box, parabola_vertex
from estimator.model import kernel
from estimator.model.direct_call import DirectCall, c_float

CYCLE_FIT, CYCLE_PARTIAL, CYCLE_FALLBACK = 0, 1, 2
"""Outcomes: the fit at the vertex is done; the vertex is known but a direction or the fit needs
Python (``ok`` says which direction); nothing usable (the stencil could not be simulated here)."""

_NO_BASIS = np.empty((0, 0))


class CycleFit(NamedTuple):
    """What :func:`warm_cycle` returns (arrays owned by the caller afterwards)."""

    code: int
    evaluations: int
    x: np.ndarray          # (2,) the vertex in (N/V, µm)
    ok: np.ndarray         # (2,) bool: the direction's parabola gave the vertex
    jac: np.ndarray        # (2, N) dU/dx at the stencil (V per N/V, V per µm); NaN if not known
    criterion: float       # the fit's cost at x (V^2 s or V s)
    paper_cost_vs: float   # eq. 28's L1 cost at x (V s)
    jtj: np.ndarray        # (2, 2)
    gn_step: np.ndarray    # (2,)
    sigma_v: float
    cov_x: np.ndarray      # (2, 2), inf where singular
    residual: np.ndarray   # (N,) unprojected U_m - U_sim at x (V)
    t_contact_s: float
    t_open_s: float
    success: bool
    directions: np.ndarray  # (2, 2) eigenvectors of jtj (columns), weakest first
    eigenvalues: np.ndarray  # (2,) clipped at 0


@njit(cache=True, nogil=True)
def _residuals(measured, u, basis, project, out):
    """out = measured - u (rows), projected off ``basis`` (N, K) if ``project``."""
    nb, n = out.shape
    for b in range(nb):
        for k in range(n):
            out[b, k] = measured[k] - u[b, k]
    if project:
        nk = basis.shape[1]
        c = np.empty(nk)
        for b in range(nb):
            for q in range(nk):
                s = 0.0
                for k in range(n):
                    s += out[b, k] * basis[k, q]
                c[q] = s
            for k in range(n):
                s = 0.0
                for q in range(nk):
                    s += c[q] * basis[k, q]
                out[b, k] -= s


@njit(cache=True, nogil=True)
def _costs(r, weights, l1, success):
    """Weighted L2 (or L1) cost per row of the residuals; +inf where not successful or not finite."""
    nb, n = r.shape
    j = np.empty(nb)
    for b in range(nb):
        s = 0.0
        for k in range(n):
            v = r[b, k]
            s += (abs(v) if l1 else v * v) * weights[k]
        j[b] = s if (success[b] and np.isfinite(s)) else np.inf
    return j


@njit(cache=True, nogil=True)
def _simulate(sim_model, aut, src, h, pts, fo, cur):
    """Voltages (B, N) and success of candidates at ``pts`` (B, 2) in (N/V, µm), all with L_h > 0."""
    nb = pts.shape[0]
    nu = np.empty(nb)
    lh = np.empty(nb)
    for b in range(nb):
        nu[b] = pts[b, 0]
        lh[b] = pts[b, 1] / UM_PER_M
    u, _, _, _, tc, to, _, success = kernel.run_from_rest(sim_model, aut, src, nu, lh, np.full(nb, fo), cur, h)
    return u, success, tc, to


@njit(cache=True, nogil=True)
def _simulable(pts, fo, cur, nu_lo, nu_hi):
    """Whether the compiled path can simulate the points (B, 2) in (N/V, µm): :func:`kernel.check_inputs`
    passes and no point needs a pre-compressed start (L_h <= 0)."""
    code, n_neg = kernel.check_inputs(cur, pts[:, 0].copy(), pts[:, 1].copy(), np.full(pts.shape[0], fo),
                                      nu_lo, nu_hi)
    return code == kernel.INPUTS_OK and n_neg == 0


@njit(cache=True, nogil=True)
def _no_fit(code, evaluations, x, ok, jac):
    """The :class:`CycleFit` tuple of a cycle that stopped before the fit (NaN fields)."""
    n = jac.shape[1]
    nan22 = np.full((2, 2), np.nan)
    return (code, evaluations, x, ok, jac, np.nan, np.nan, nan22, np.full(2, np.nan), np.nan, nan22.copy(),
            np.full(n, np.nan), np.nan, np.nan, False, nan22.copy(), np.full(2, np.nan))


@njit(cache=True, nogil=True)
def warm_cycle(sim_model, aut, src, h, nu_lo, nu_hi, cur, fo, measured, weights, basis, project, l1,
               x0, d, st, lo, hi):
    """One batched refinement cycle from ``x0`` along the columns of ``d`` with ``st`` (N/V, µm).

    ``sim_model, aut, src, h`` are the fast simulator's compiled model, automaton, transition
    table and sample period (µs); ``nu_lo, nu_hi`` its N_u range (N/V); ``cur`` the cost window's
    current (A), ``fo`` F_open (N), ``measured`` the window's voltage (V), ``weights`` the
    quadrature weights (s), ``basis`` the nuisance basis (N, K) used when ``project``; ``l1`` the
    paper's L1 cost instead of least squares; ``lo, hi`` the search box. Returns the fields of
    :class:`CycleFit` as a tuple.
    """
    n = cur.shape[0]
    nanjac = np.full((2, n), np.nan)
    # the stencil {x0, x0 -/+ s1 d1, x0 -/+ s2 d2}, moved into the box
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
    if not _simulable(pts, fo, cur, nu_lo, nu_hi):
        return _no_fit(CYCLE_FALLBACK, 0, x0.copy(), np.zeros(2, dtype=np.bool_), nanjac)
    u, success, _, _ = _simulate(sim_model, aut, src, h, pts, fo, cur)
    r = np.empty((5, n))
    _residuals(measured, u, basis, project, r)
    j = _costs(r, weights, l1, success)
    # both vertices from the one batch (conjugate directions)
    x = x0.copy()
    ok = np.zeros(2, dtype=np.bool_)
    for i in range(2):
        a = np.empty(3)
        for q, p in enumerate((1 + 2 * i, 0, 2 + 2 * i)):
            a[q] = (pts[p, 0] - x0[0]) * d[0, i] + (pts[p, 1] - x0[1]) * d[1, i]
        vx, _ = parabola_vertex(a[0], a[1], a[2], j[1 + 2 * i], j[0], j[2 + 2 * i])
        if np.isfinite(vx) and abs(vx) <= TRUST_STEPS * st[i] and a[0] < a[1] < a[2]:
            x[0] += vx * d[0, i]
            x[1] += vx * d[1, i]
            ok[i] = True
    for i in range(2):
        x[i] = min(max(x[i], lo[i]), hi[i])
    all_ok = success[0] and success[1] and success[2] and success[3] and success[4]
    if not (inside and ok[0] and ok[1] and all_ok):
        return _no_fit(CYCLE_PARTIAL, 5, x, ok, nanjac)
    # the stencil's central differences along d1, d2 are the Gauss–Newton Jacobian: dU/dx = D dU/dalpha
    jac = np.empty((2, n))
    for k in range(n):
        ja0 = -(r[2, k] - r[1, k]) / (2 * st[0])
        ja1 = -(r[4, k] - r[3, k]) / (2 * st[1])
        jac[0, k] = d[0, 0] * ja0 + d[0, 1] * ja1
        jac[1, k] = d[1, 0] * ja0 + d[1, 1] * ja1
    if not x[1] > 0.0:      # a pre-compressed start at the vertex: the fit is made in Python
        return _no_fit(CYCLE_PARTIAL, 5, x, ok, jac)
    # the local fit at the vertex with that Jacobian (local_fit._fit_from)
    xv = np.empty((1, 2))
    xv[0, 0] = x[0]
    xv[0, 1] = x[1]
    uv, sv, tcv, tov = _simulate(sim_model, aut, src, h, xv, fo, cur)
    rv = np.empty((1, n))
    _residuals(measured, uv, basis, project, rv)
    crit, paper, jtj, step, sigma, cov, raw, fine, dirs, eig = _gauss_newton(measured, weights, l1, uv[0], rv[0],
                                                                             sv[0], sv[0], jac)
    return (CYCLE_FIT, 6, x, ok, jac, crit, paper, jtj, step, sigma, cov, raw, tcv[0], tov[0], fine, dirs, eig)


@njit(cache=True, nogil=True)
def _gauss_newton(measured, weights, l1, u, r0, u_ok, success, jac):
    """local_fit._fit_from: the Gauss–Newton model at a point from its simulated voltage ``u`` (V), its
    (projected) residual ``r0`` and ``jac`` = dU/dx (2, N); ``u_ok``: the point's own simulation
    succeeded, ``success``: every simulation behind the fit did. Returns (criterion, paper cost, jtj,
    step, sigma, covariance, unprojected residual, success, directions, eigenvalues)."""
    n = u.shape[0]
    ok1 = np.empty(1, dtype=np.bool_)
    ok1[0] = u_ok
    crit = _costs(r0.reshape((1, n)), weights, l1, ok1)[0]
    raw = np.empty(n)
    paper = 0.0
    for k in range(n):
        raw[k] = measured[k] - u[k]
        paper += abs(raw[k]) * weights[k]
    jtj = np.empty((2, 2))
    jr = np.zeros(2)
    for p in range(2):
        for q in range(2):
            s = 0.0
            for k in range(n):
                s += jac[p, k] * jac[q, k]
            jtj[p, q] = s
        for k in range(n):
            jr[p] += jac[p, k] * r0[k]
    fine = success and np.all(np.isfinite(jtj))
    sigma = noise_sigma(r0) if fine else np.nan
    det = jtj[0, 0] * jtj[1, 1] - jtj[0, 1] * jtj[1, 0] if fine else 0.0
    cov = np.full((2, 2), np.inf)
    step = np.zeros(2)
    if fine and det > 1e-14 * jtj[0, 0] * jtj[1, 1]:
        inv = np.empty((2, 2))
        inv[0, 0], inv[0, 1] = jtj[1, 1] / det, -jtj[0, 1] / det
        inv[1, 0], inv[1, 1] = -jtj[1, 0] / det, jtj[0, 0] / det
        for p in range(2):
            for q in range(2):
                cov[p, q] = sigma ** 2 * inv[p, q]
            step[p] = inv[p, 0] * jr[0] + inv[p, 1] * jr[1]
    dirs = np.full((2, 2), np.nan)
    eig = np.full(2, np.nan)
    if fine:
        w, v = np.linalg.eigh(0.5 * (jtj + jtj.T))
        dirs = np.ascontiguousarray(v)
        eig = np.maximum(w, 0.0)
    return crit, paper, jtj, step, sigma, cov, raw, fine, dirs, eig


@njit(cache=True, nogil=True)
def forward_fit(sim_model, aut, src, h, nu_lo, nu_hi, cur, fo, measured, weights, basis, project, l1, x, fd,
                hi):
    """local_fit.local_fit compiled: x and its two forward-difference neighbours (steps ``fd`` in
    (N/V, µm), turned back where they would leave the box below ``hi``) in one batch, the Gauss–Newton
    model at x. Returns the fields of :class:`CycleFit` (``CYCLE_FALLBACK``: a point not simulable here)."""
    n = cur.shape[0]
    steps = np.empty(2)
    for i in range(2):
        steps[i] = fd[i] if x[i] + fd[i] <= hi[i] else -fd[i]
    pts = np.empty((3, 2))
    for b in range(3):
        pts[b, 0] = x[0]
        pts[b, 1] = x[1]
    pts[1, 0] += steps[0]
    pts[2, 1] += steps[1]
    if not _simulable(pts, fo, cur, nu_lo, nu_hi):
        return _no_fit(CYCLE_FALLBACK, 0, x.copy(), np.zeros(2, dtype=np.bool_), np.full((2, n), np.nan))
    u, success, tc, to = _simulate(sim_model, aut, src, h, pts, fo, cur)
    r = np.empty((3, n))
    _residuals(measured, u, basis, project, r)
    jac = np.empty((2, n))
    for k in range(n):
        jac[0, k] = -(r[1, k] - r[0, k]) / steps[0]
        jac[1, k] = -(r[2, k] - r[0, k]) / steps[1]
    crit, paper, jtj, step, sigma, cov, raw, fine, dirs, eig = _gauss_newton(
        measured, weights, l1, u[0], r[0], success[0], success[0] and success[1] and success[2], jac)
    ok = np.ones(2, dtype=np.bool_)
    return (CYCLE_FIT, 3, x.copy(), ok, jac, crit, paper, jtj, step, sigma, cov, raw, tc[0], to[0], fine, dirs, eig)


GN_DONE, GN_FIRST_FIT, GN_STEP_FIT = 0, 1, 2
"""Outcomes of :func:`gauss_newton`: finished (fit and converged flag final); the fit at the start
point, or at a step's new point, needs Python (a pre-compressed start): go on from the state returned."""


@njit(cache=True, nogil=True)
def _max_nan(a, b):
    """np.maximum of two floats (NaN wins)."""
    return a if (a >= b or a != a) else b


@njit(cache=True, nogil=True)
def widened_radius(rad, cov, k, min_sd):
    """A copy of the trust region ``rad`` (N/V, µm), each radius raised to ``k`` standard deviations of
    ``cov`` (each at least ``min_sd``) where that is larger and finite (``k <= 0``: unchanged)."""
    out = rad.copy()
    if k > 0.0:
        for i in range(2):
            r = k * _max_nan(np.sqrt(abs(cov[i, i])), min_sd[i])
            if r > out[i] and r < np.inf:
                out[i] = r
    return out


@njit(cache=True, nogil=True)
def gauss_newton(sim_model, aut, src, h, nu_lo, nu_hi, cur, fo, measured, weights, basis, project, l1, x, fd,
                 lo, hi, rad, radius_sd, min_sd, tol, max_steps, converged_sd, close_sd, shrink):
    """cold_start.gauss_newton_fit's loop compiled: Gauss–Newton steps from ``x`` (inside the box ``lo``,
    ``hi``) in a trust region of first radius ``rad`` (N/V, µm; widened to ``radius_sd`` of the first
    fit's standard deviations, each at least ``min_sd``, see :func:`widened_radius`), each step one :func:`forward_fit`
    (steps ``fd``), the same decisions in the same float operations. Returns (code, converged,
    evaluations, steps done, x, pending point, its scale, radius, the fit at x as :class:`CycleFit`
    fields): ``GN_DONE``, or where :func:`forward_fit` cannot simulate a point (L_h <= 0), the state to
    continue from in Python (``GN_FIRST_FIT``: the fit at ``x``; ``GN_STEP_FIT``: at the pending point)."""
    args = (sim_model, aut, src, h, nu_lo, nu_hi, cur, fo, measured, weights, basis, project, l1)
    fit = forward_fit(*args, x, fd, hi)
    evaluations = fit[1]
    if fit[0] != CYCLE_FIT:
        return GN_FIRST_FIT, False, evaluations, 0, x, x.copy(), 1.0, rad, fit
    rad = widened_radius(rad, fit[10], radius_sd, min_sd)
    for k in range(max_steps):
        if not fit[14]:
            return GN_DONE, False, evaluations, k, x, x.copy(), 1.0, rad, fit
        step, cov = fit[8], fit[10]
        sd0, sd1 = np.sqrt(abs(cov[0, 0])), np.sqrt(abs(cov[1, 1]))
        if (abs(step[0]) <= _max_nan(tol[0], converged_sd * sd0)
                and abs(step[1]) <= _max_nan(tol[1], converged_sd * sd1)):
            return GN_DONE, True, evaluations, k, x, x.copy(), 1.0, rad, fit
        q0 = rad[0] / _max_nan(abs(step[0]), 1e-300)
        q1 = rad[1] / _max_nan(abs(step[1]), 1e-300)
        q = np.nan if (q0 != q0 or q1 != q1) else min(q0, q1)
        scale = q if q < 1.0 else 1.0     # min(1.0, np.min(...)) in Python: NaN gives 1.0
        x_new = np.empty(2)
        moved = np.empty(2)
        for i in range(2):
            x_new[i] = min(max(x[i] + scale * step[i], lo[i]), hi[i])
            moved[i] = abs(x_new[i] - x[i])
        if moved[0] <= tol[0] and moved[1] <= tol[1]:
            return GN_DONE, False, evaluations, k, x, x_new, scale, rad, fit
        fit_new = forward_fit(*args, x_new, fd, hi)
        evaluations += fit_new[1]
        if fit_new[0] != CYCLE_FIT:
            return GN_STEP_FIT, False, evaluations, k, x, x_new, scale, rad, fit
        if fit_new[14] and fit_new[5] < fit[5]:
            x, fit = x_new, fit_new
            rad = 2.0 * rad
        elif (scale == 1.0 and abs(step[0]) <= _max_nan(tol[0], close_sd * sd0)
              and abs(step[1]) <= _max_nan(tol[1], close_sd * sd1)):
            return GN_DONE, True, evaluations, k, x, x_new, scale, rad, fit
        else:
            for i in range(2):
                rad[i] = shrink * moved[i] + tol[i]
    return GN_DONE, False, evaluations, max_steps, x, x.copy(), 1.0, rad, fit


@njit(cache=True, nogil=True)
def point_costs(sim_model, aut, src, h, nu_lo, nu_hi, cur, fo, measured, weights, basis, project, l1, pts):
    """The cost model's costs of the points (B, 2) in (N/V, µm) (:meth:`cost.CostModel.cost_of` of
    their simulations, +inf where one failed), and whether they were simulated here (False: a point
    needs a pre-compressed start, nothing simulated)."""
    nb = pts.shape[0]
    if not _simulable(pts, fo, cur, nu_lo, nu_hi):
        return False, np.full(nb, np.nan)
    u, success, _, _ = _simulate(sim_model, aut, src, h, pts, fo, cur)
    r = np.empty((nb, cur.shape[0]))
    _residuals(measured, u, basis, project, r)
    return True, _costs(r, weights, l1, success)


class GaussNewtonRun(NamedTuple):
    """What :func:`run_gauss_newton` returns (see :func:`gauss_newton`)."""

    code: int
    converged: bool
    steps: int
    x: np.ndarray
    x_new: np.ndarray
    scale: float
    radius: np.ndarray
    fit: CycleFit


def _model_args(model: CostModel) -> tuple:
    """The compiled functions' arguments that come from the cost model and its simulator."""
    sim = model.sim
    handle = sim.kernel_handle()
    basis = c_float(model.basis) if model.robust else _NO_BASIS   # one compiled layout
    # the types are fixed here (DirectCall): C-contiguous float64 arrays (the cost model's current and
    # voltage are made so in CostModel), Python floats (the handle's) and bools
    return (handle.model, handle.automaton, handle.table, handle.h_us, handle.nu_lo, handle.nu_hi, model.current,
            float(model.injection.f_open_n), model.measured, model.weights, basis, bool(model.robust),
            model.norm == "l1")


_forward_fit = DirectCall(forward_fit)
_warm_cycle = DirectCall(warm_cycle)
_gauss_newton_loop = DirectCall(gauss_newton)
_point_costs = DirectCall(point_costs)


def run_forward_fit(model: CostModel, x: np.ndarray, fd: np.ndarray, box: Box) -> CycleFit:
    """:func:`forward_fit` for a cost model (its evaluations counted)."""
    out = CycleFit(*_forward_fit(*_model_args(model), c_float(x), c_float(fd), c_float(box.hi)))
    model.evaluations += out.evaluations
    return out


def run_cycle(model: CostModel, x0: np.ndarray, d: np.ndarray, st: np.ndarray, box: Box) -> CycleFit:
    """:func:`warm_cycle` for a cost model (its evaluations counted) from ``x0`` along ``d``, ``st``."""
    out = CycleFit(*_warm_cycle(*_model_args(model), c_float(x0), c_float(d), c_float(st), c_float(box.lo),
                                c_float(box.hi)))
    model.evaluations += out.evaluations
    return out


def run_gauss_newton(model: CostModel, x: np.ndarray, fd: np.ndarray, box: Box, radius: np.ndarray,
                     radius_sd: float, min_sd: np.ndarray, tol: np.ndarray, max_steps: int, converged_sd: float,
                     close_sd: float, shrink: float) -> GaussNewtonRun:
    """:func:`gauss_newton` for a cost model (its evaluations counted) from ``x`` (inside the box)."""
    code, converged, evaluations, steps, x, x_new, scale, rad, fit = _gauss_newton_loop(
        *_model_args(model), c_float(x), c_float(fd), c_float(box.lo), c_float(box.hi), c_float(radius),
        float(radius_sd), c_float(min_sd), c_float(tol), int(max_steps), float(converged_sd), float(close_sd), float(shrink))
    model.evaluations += int(evaluations)
    return GaussNewtonRun(int(code), bool(converged), int(steps), x, x_new, float(scale), rad, CycleFit(*fit))


def run_point_costs(model: CostModel, pts: np.ndarray) -> np.ndarray | None:
    """:func:`point_costs` for a cost model (its evaluations counted); None where a point needs Python."""
    simulated, j = _point_costs(*_model_args(model), c_float(pts))
    if not simulated:
        return None
    model.evaluations += int(j.shape[0])
    return j
