"""The automatic local-first cold start in one compiled call (numba).

:func:`estimator.ident.idle_stroke._local_first_auto` fits the plain cost from the start point, the
robust cost from the plain optimum, decides between them by the likelihood ratio, rings the
published fit (and the other one where the choice is close or it sits at a bound) and checks the
chosen fit's residual. Its compiled pieces (:func:`compiled_cycle.gauss_newton`,
:func:`compiled_cycle.point_costs`) were one call each, with ≈ 0.2 ms of Python between them per
injection (the fit objects, the likelihood ratio's projection, the ring's points): as much again as
the ring's simulations. :func:`local_first_auto` makes the same decisions with the same compiled
pieces in one call; the likelihood ratio and the residual check are their compiled twins (the
projection summed in loops: equal to numpy's to rounding).

Only the common case is compiled. Where the Python path would leave the compiled pieces (a point
that needs a pre-compressed start, L_h <= 0; a Gauss–Newton fit that stalled and goes on with the
line searches) the call returns ``AUTO_PYTHON`` having changed nothing, and the caller runs the
Python path from the start (the same simulations again: rare, 0.3 % of a lot's injections).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from estimator.ident.compiled_cycle import GN_DONE, CycleFit, _max_nan, _model_args, gauss_newton, point_costs
from estimator.ident.cost import CostModel, noise_sigma
from estimator.ident.search import Box
from estimator.model.direct_call import DirectCall, c_float

AUTO_DONE, AUTO_GLOBAL, AUTO_PYTHON = 0, 1, 2
"""Outcomes of :func:`local_first_auto`: the chosen fit passed every check; the local fits failed a
check (the caller runs the global search, the simulations so far counted); the Python path is needed
(nothing counted)."""


class AutoRun(NamedTuple):
    """What :func:`run_local_first_auto` returns."""

    code: int
    robust: bool        # the robust fit is the chosen one
    stat: float         # the likelihood-ratio statistic of the final fits
    plain: CycleFit     # the final plain fit
    rob: CycleFit       # the final robust fit
    residual_z: float   # the chosen fit's excess_residual_z (AUTO_DONE), else NaN


@njit(cache=True, nogil=True)
def _projected(r, basis):
    """``r - basis (basis' r)`` (``basis`` (N, K) orthonormal columns, N = r's length)."""
    n, nk = basis.shape
    c = np.zeros(nk)
    for q in range(nk):
        s = 0.0
        for k in range(n):
            s += basis[k, q] * r[k]
        c[q] = s
    out = np.empty(n)
    for k in range(n):
        s = 0.0
        for q in range(nk):
            s += basis[k, q] * c[q]
        out[k] = r[k] - s
    return out


@njit(cache=True, nogil=True)
def _sum_sq(r):
    s = 0.0
    for k in range(r.shape[0]):
        s += r[k] * r[k]
    return s


@njit(cache=True, nogil=True)
def likelihood_ratio(f_plain, f_rob, basis_p):
    """:func:`model_selection.likelihood_ratio` of two :class:`CycleFit` tuples, the plain window's
    nuisance basis ``basis_p`` (N_plain, K) given: (RSS_plain - RSS_robust) / sigma^2 (NaN if a fit failed)."""
    if not (f_plain[14] and f_rob[14]):
        return np.nan
    n = basis_p.shape[0]
    r_plain = f_plain[11][:n]
    r_rob = _projected(f_rob[11][:n].copy(), basis_p)
    sigma = noise_sigma(r_rob)
    return (_sum_sq(r_plain) - _sum_sq(r_rob)) / sigma ** 2


@njit(cache=True, nogil=True)
def excess_residual_z(fit, n, basis, project):
    """:func:`cold_start.excess_residual_z` of a :class:`CycleFit` tuple over ``n`` samples (projected
    off ``basis`` if ``project``)."""
    r = fit[11][:n].copy()
    k = 2
    if project:
        r = _projected(r, basis)
        k += basis.shape[1]
    dof = max(n - k, 1)
    sigma = noise_sigma(r)
    return (_sum_sq(r) / sigma ** 2 - dof) / np.sqrt(2.0 * dof)


@njit(cache=True, nogil=True)
def _sd_radius(cov, k, min_sd):
    """:func:`cold_start.sd_radius`: ``k`` standard deviations of ``cov``, each at least ``min_sd``."""
    out = np.empty(2)
    for i in range(2):
        out[i] = k * _max_nan(np.sqrt(abs(cov[i, i])), min_sd[i])
    return out


@njit(cache=True, nogil=True)
def _at_bound(x, lo, hi, bound_tol):
    """:meth:`Box.at_bound`."""
    for i in range(2):
        if x[i] <= lo[i] + bound_tol[i] or x[i] >= hi[i] - bound_tol[i]:
            return True
    return False


@njit(cache=True, nogil=True)
def local_first_auto(sim_model, aut, src, h, nu_lo, nu_hi, fo, l1,
                     cur_p, meas_p, w_p, basis_p, cur_r, meas_r, w_r, basis_r,
                     x0, fd, lo, hi, start_radius, robust_sd, min_sd, tol, max_steps, converged_sd, close_sd,
                     shrink, ring, rescans, threshold, flip_margin, bound_tol):
    """:func:`idle_stroke._local_first_auto` up to its residual check (see the module docstring).

    ``cur_p, meas_p, w_p``: the plain cost model's window (current A, voltage V, weights s) and
    ``basis_p`` its nuisance basis (for the likelihood ratio); ``cur_r, meas_r, w_r, basis_r`` the
    robust model's. The rest are :mod:`cold_start`'s settings: the start ``x0`` (inside the box ``lo``,
    ``hi``), the Gauss–Newton loop's (:func:`compiled_cycle.gauss_newton`), the ring's probes (in
    standard deviations) and rescans, the model-error threshold and its flip margin, and the bound
    tolerance. Returns (code, evaluations of the plain cost, of the robust cost, robust chosen, the
    statistic, the final plain and robust fits as :class:`CycleFit` tuples, the chosen fit's
    :func:`excess_residual_z` (``AUTO_DONE`` only; NaN otherwise))."""
    no_basis = np.empty((0, 0))
    n_p = cur_p.shape[0]
    # the plain fit from x0 (gauss_newton_fit: x0 clipped into the box by the caller)
    gp = gauss_newton(sim_model, aut, src, h, nu_lo, nu_hi, cur_p, fo, meas_p, w_p, no_basis, False, l1,
                      x0, fd, lo, hi, start_radius.copy(), 0.0, min_sd, tol, max_steps, converged_sd, close_sd, shrink)
    ev_p = gp[2]
    f_plain = gp[8]
    ev_r = 0
    f_rob = f_plain
    stat = np.nan
    if gp[0] != GN_DONE or (f_plain[14] and not gp[1]):   # a pre-compressed start, or the line searches
        return AUTO_PYTHON, ev_p, ev_r, False, stat, f_plain, f_rob, np.nan
    if not f_plain[14]:
        return AUTO_GLOBAL, ev_p, ev_r, False, stat, f_plain, f_rob, np.nan
    # the robust fit from the plain optimum, in ROBUST_START_SD of the plain fit's (or its own) sd
    gr = gauss_newton(sim_model, aut, src, h, nu_lo, nu_hi, cur_r, fo, meas_r, w_r, basis_r, True, l1,
                      f_plain[2].copy(), fd, lo, hi, _sd_radius(f_plain[10], robust_sd, min_sd), robust_sd, min_sd,
                      tol, max_steps, converged_sd, close_sd, shrink)
    ev_r = gr[2]
    f_rob = gr[8]
    if gr[0] != GN_DONE or (f_rob[14] and not gr[1]):
        return AUTO_PYTHON, ev_p, ev_r, False, stat, f_plain, f_rob, np.nan
    if not f_rob[14]:
        return AUTO_GLOBAL, ev_p, ev_r, False, stat, f_plain, f_rob, np.nan
    ringed = np.zeros(2, dtype=np.bool_)
    robust = False
    while True:
        stat = likelihood_ratio(f_plain, f_rob, basis_p)
        robust = np.isfinite(stat) and stat > threshold
        close = abs(stat - threshold) <= flip_margin
        chosen = 1 if robust else 0
        todo = np.zeros(2, dtype=np.int64)
        nt = 0
        for i in (chosen, 1 - chosen):
            fit_i = f_rob if i == 1 else f_plain
            usable = fit_i[14] and not _at_bound(fit_i[2], lo, hi, bound_tol)
            if not ringed[i] and (i == chosen or close or not usable):
                todo[nt] = i
                nt += 1
        if nt == 0:
            break
        for t in range(nt):
            i = todo[t]
            # ring_checked(model i, fit i, converged=True)
            fit = f_rob if i == 1 else f_plain
            cur, meas, w, basis = (cur_r, meas_r, w_r, basis_r) if i == 1 else (cur_p, meas_p, w_p, no_basis)
            converged = True
            for _ in range(rescans):
                if not (fit[14] and converged):
                    break
                # probe_ring: the lowest ring point if lower than the fit
                cov = fit[10]
                if not (np.isfinite(np.sqrt(abs(cov[0, 0]))) and np.isfinite(np.sqrt(abs(cov[1, 1])))):
                    break
                sd = _sd_radius(cov, 1.0, min_sd)
                pts = np.empty((ring.shape[0], 2))
                for b in range(ring.shape[0]):
                    for q in range(2):
                        pts[b, q] = min(max(fit[2][q] + ring[b, q] * sd[q], lo[q]), hi[q])
                simulated, j = point_costs(sim_model, aut, src, h, nu_lo, nu_hi, cur, fo, meas, w, basis, i == 1,
                                           l1, pts)
                if not simulated:
                    return AUTO_PYTHON, ev_p, ev_r, robust, stat, f_plain, f_rob, np.nan
                if i == 1:
                    ev_r += pts.shape[0]
                else:
                    ev_p += pts.shape[0]
                k = 0
                for b in range(1, j.shape[0]):
                    if j[b] < j[k]:
                        k = b
                if not j[k] < fit[5]:
                    break
                g2 = gauss_newton(sim_model, aut, src, h, nu_lo, nu_hi, cur, fo, meas, w, basis, i == 1, l1,
                                  pts[k].copy(), fd, lo, hi, _sd_radius(cov, 2.0, min_sd), 0.0, min_sd, tol,
                                  max_steps, converged_sd, close_sd, shrink)
                if i == 1:
                    ev_r += g2[2]
                else:
                    ev_p += g2[2]
                if g2[0] != GN_DONE:
                    return AUTO_PYTHON, ev_p, ev_r, robust, stat, f_plain, f_rob, np.nan
                fit2 = g2[8]
                if not (fit2[14] and fit2[5] < fit[5]):
                    break
                fit, converged = fit2, g2[1]
            if not (fit[14] and converged and not _at_bound(fit[2], lo, hi, bound_tol)):
                return AUTO_GLOBAL, ev_p, ev_r, robust, stat, f_plain, f_rob, np.nan
            if i == 1:
                f_rob = fit
            else:
                f_plain = fit
            ringed[i] = True
    z = (excess_residual_z(f_rob, cur_r.shape[0], basis_r, True) if robust
         else excess_residual_z(f_plain, n_p, no_basis, False))
    return AUTO_DONE, ev_p, ev_r, robust, stat, f_plain, f_rob, z


_local_first_auto = DirectCall(local_first_auto)


def run_local_first_auto(m_plain: CostModel, m_rob: CostModel, x0: np.ndarray, fd: np.ndarray, box: Box,
                         start_radius: np.ndarray, robust_sd: float, min_sd: np.ndarray, tol: np.ndarray,
                         max_steps: int, converged_sd: float, close_sd: float, shrink: float, ring: np.ndarray,
                         rescans: int, threshold: float, flip_margin: float,
                         bound_tol: tuple[float, float]) -> AutoRun | None:
    """:func:`local_first_auto` for the two cost models of an injection (their evaluations counted); None
    where the Python path is needed (nothing counted)."""
    a_p, a_r = _model_args(m_plain), _model_args(m_rob)
    code, ev_p, ev_r, robust, stat, f_p, f_r, z = _local_first_auto(
        *a_p[:6], a_p[7], a_p[12], a_p[6], a_p[8], a_p[9], c_float(m_plain.basis), a_r[6], a_r[8], a_r[9], a_r[10],
        c_float(x0), c_float(fd), c_float(box.lo), c_float(box.hi), c_float(start_radius), float(robust_sd),
        c_float(min_sd), c_float(tol), int(max_steps), float(converged_sd), float(close_sd), float(shrink),
        c_float(ring), int(rescans), float(threshold), float(flip_margin), c_float(bound_tol))
    if code == AUTO_PYTHON:
        return None
    m_plain.evaluations += int(ev_p)
    m_rob.evaluations += int(ev_r)
    return AutoRun(int(code), bool(robust), float(stat), CycleFit(*f_p), CycleFit(*f_r), float(z))
