"""The preload force's sensitivity and the measured current's noise covariance of a fit, in one
compiled call (:func:`estimator.ident.fit.mismatch.sensitivities` decides what they mean).

Five simulations at the fit's point: the point itself, a step in N_u, in L_h and in F_open (one batch),
and the point driven by the current offset by a small step (the probe of the current's noise). As
numpy calls from Python they cost a checked update about 0.7 ms on a slow hour, mostly in the calls
around the simulations; here they cost about the simulations.
"""

from __future__ import annotations

import math

import numpy as np

from estimator._compiled import njit
from estimator.ident.coords import UM_PER_M
from estimator.ident.fit.cost import MAD_PER_SIGMA
from estimator.model import kernel
from estimator.model.automaton import Automaton

SENS_OK = 0          # sensitivity and current-noise covariance computed
SENS_FAILED = 1      # a simulation failed or the fit's directions are degenerate: neither
NOISE_FAILED = 2     # the sensitivity only: the probe simulation failed or its covariance is not finite
NOISE_NONE = 3       # the sensitivity, and a current without noise or without current: covariance zero

MAD_SCALE = MAD_PER_SIGMA * math.sqrt(6.0)   # median |second difference| of white noise, in its sigma


@njit(cache=True, nogil=True)
def current_noise(cur: np.ndarray) -> float:
    """White-noise level (A, 1 sigma) of a sampled current: the median absolute second difference
    over ``MAD_PER_SIGMA`` sqrt(6) (0 for fewer than three samples)."""
    n = cur.shape[0] - 2
    if n <= 0:
        return 0.0
    d2 = np.empty(n)
    for k in range(n):
        d2[k] = abs(cur[k + 2] - 2.0 * cur[k + 1] + cur[k])
    result: float = np.median(d2) / MAD_SCALE
    return result


@njit(cache=True, nogil=True)
def _project(r: np.ndarray, basis: np.ndarray) -> None:
    """``r`` minus its part in the orthonormal columns of ``basis`` (in place)."""
    for c in range(basis.shape[1]):
        dot = 0.0
        for k in range(r.shape[0]):
            dot += basis[k, c] * r[k]
        for k in range(r.shape[0]):
            r[k] -= dot * basis[k, c]


@njit(cache=True, nogil=True)
def sensitivities(model: kernel.KernelModel, aut: Automaton, src: np.ndarray, h_us: float, cur: np.ndarray,
                  nu: float, lh_um: float, f_open_n: float, h_nu: float, h_lh_um: float, preload_step: float,
                  probe: float, basis: np.ndarray, robust: bool,
                  jac: np.ndarray, du: np.ndarray, s: np.ndarray, u0: np.ndarray, cov: np.ndarray) -> int:
    """Fill ``jac`` (2, N: dU/dN_u in V per N/V, dU/dL_h in V per µm), ``du`` (N: dU/dF_open, V/N),
    ``s`` (2: the fit's move per newton of F_open, (J J')^-1 J du), ``u0`` (N: the voltage at the point,
    V) and ``cov`` (2, 2: what the current's noise adds to the fit, in N/V and µm) for the fit at
    (``nu`` N/V, ``lh_um`` µm, ``f_open_n`` N) of the window's current ``cur`` (A, N samples). Finite
    differences of ``h_nu``, ``h_lh_um`` and ``preload_step`` × F_open; the current probe is ``probe``
    × its peak. In ``robust`` mode the derivatives are taken without their part in ``basis``'s columns
    (the nuisance span). Returns one of the ``SENS_``/``NOISE_`` codes."""
    n = cur.shape[0]
    nus = np.array([nu, nu + h_nu, nu, nu])
    lhs = np.array([lh_um, lh_um, lh_um + h_lh_um, lh_um]) / UM_PER_M
    fos = np.array([f_open_n, f_open_n, f_open_n, f_open_n * (1.0 + preload_step)])
    u, _, _, _, _, _, _, ok = kernel.run_table(model, aut, src, nus, lhs, fos, cur, h_us)
    for b in range(4):
        if not ok[b]:
            return SENS_FAILED
    for k in range(n):
        u0[k] = u[0, k]
        jac[0, k] = (u[1, k] - u[0, k]) / h_nu
        jac[1, k] = (u[2, k] - u[0, k]) / h_lh_um
        du[k] = (u[3, k] - u[0, k]) / (preload_step * f_open_n)
    if robust:
        _project(jac[0], basis)
        _project(jac[1], basis)
        _project(du, basis)
    a00, a01, a11, b0, b1 = 0.0, 0.0, 0.0, 0.0, 0.0
    for k in range(n):
        a00 += jac[0, k] * jac[0, k]
        a01 += jac[0, k] * jac[1, k]
        a11 += jac[1, k] * jac[1, k]
        b0 += jac[0, k] * du[k]
        b1 += jac[1, k] * du[k]
    det = a00 * a11 - a01 * a01
    if not (np.isfinite(a00) and np.isfinite(a01) and np.isfinite(a11)) or abs(det) <= 1e-14 * a00 * a11:
        return SENS_FAILED
    s[0] = (a11 * b0 - a01 * b1) / det
    s[1] = (a00 * b1 - a01 * b0) / det
    return _current_noise_cov(model, aut, src, h_us, cur, nu, lh_um / UM_PER_M, f_open_n, probe, jac, u0,
                              a11 / det, -a01 / det, a00 / det, cov)


@njit(cache=True, nogil=True)
def _current_noise_cov(model: kernel.KernelModel, aut: Automaton, src: np.ndarray, h_us: float, cur: np.ndarray,
                       nu: float, lh_m: float, f_open_n: float, probe: float, jac: np.ndarray, u0: np.ndarray,
                       i00: float, i01: float, i11: float, cov: np.ndarray) -> int:
    """``cov`` = sigma_I^2 (J J')^-1 G G' (J J')^-1 with G = J' H, H the lower-triangular Toeplitz matrix
    of the response to a current step less its direct (white) part; ``i00``, ``i01``, ``i11``: (J J')^-1."""
    n = cur.shape[0]
    sigma_i = current_noise(cur)
    peak = 0.0
    for k in range(n):
        peak = max(peak, abs(cur[k]))
    cov[:, :] = 0.0
    if not (sigma_i > 0.0 and peak > 0.0):
        return NOISE_NONE
    delta = probe * peak
    u, _, _, _, _, _, _, ok = kernel.run_table(model, aut, src, np.array([nu]), np.array([lh_m]),
                                               np.array([f_open_n]), cur + delta, h_us)
    if not ok[0]:
        return NOISE_FAILED
    h = np.empty(n)                # the step response's increments; the first, the direct part, left out
    h[0] = 0.0
    for k in range(1, n):
        h[k] = ((u[0, k] - u0[k]) - (u[0, k - 1] - u0[k - 1])) / delta
    g = np.zeros((2, n))           # G = J' H: g[r, i] = sum over p >= i of jac[r, p] h[p - i]
    for r in range(2):
        for i in range(n):
            acc = 0.0
            for p in range(i, n):
                acc += jac[r, p] * h[p - i]
            g[r, i] = acc
    m00, m01, m11 = 0.0, 0.0, 0.0
    for i in range(n):
        m00 += g[0, i] * g[0, i]
        m01 += g[0, i] * g[1, i]
        m11 += g[1, i] * g[1, i]
    # (J J')^-1 M (J J')^-1 of the symmetric 2 x 2 matrices
    p00, p01 = i00 * m00 + i01 * m01, i00 * m01 + i01 * m11
    p10, p11 = i01 * m00 + i11 * m01, i01 * m01 + i11 * m11
    var = sigma_i * sigma_i
    cov[0, 0] = var * (p00 * i00 + p01 * i01)
    cov[0, 1] = var * (p00 * i01 + p01 * i11)
    cov[1, 0] = var * (p10 * i00 + p11 * i01)
    cov[1, 1] = var * (p10 * i01 + p11 * i11)
    for r in range(2):
        for c in range(2):
            if not np.isfinite(cov[r, c]):
                return NOISE_FAILED
    return SENS_OK
