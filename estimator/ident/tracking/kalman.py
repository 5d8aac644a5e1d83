"""Kalman steps of the recursive estimator as pure functions (no state of their own).

State ``x = [N_u (N/V), L_h (µm), r (N/V per s), b (N/V per degC), w (µm per injection)]``: the
coupling factor, the idle stroke, the drift rate of N_u that temperature does not explain, the
injector's temperature slope dN_u/dT (eq. 25, learned online), and the idle stroke's growth per
injection (wear). The measurement is the raw single-injection estimate ``z = [N_u, L_h]`` with its
Gauss–Newton covariance ``R``.

Prediction to the next injection, ``dt`` seconds and ``dT`` degC later: ``N_u += tau (1 - a) r + b dT``
with ``a = exp(-dt/tau)`` (a drift rate decays: warm-ups end), ``r *= a``; ``L_h += w`` (wear goes
with the injections, not with the time between them); b and w are random walks. Process noise per
injection (a floor for model jitter, and w's walk) plus per second (random walks of N_u, L_h and r).
Without w a steady wear leaves the filtered L_h behind by its rate over the filter's gain (0.02-0.03
µm at 0.003 µm per injection, with a σ of 0.012 µm). Variances are capped by the physical ranges, so
a long gap means "anywhere in the range", not infinity.

A gate failure is explained by the generalised likelihood ratio of a jump in N_u alone, in L_h
alone, or in both (:func:`jump_components`); :func:`release` forgets what the filter knew about
the components that jumped.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimator._compiled import njit
from estimator._compiled.direct_call import DirectCall, c_float

N_STATE = 5
NU, LH, RATE, SLOPE, WEAR = range(N_STATE)
CHI2_1DOF_1E4 = 15.14           # P(chi2(1) > 15.14) = 1e-4: a one-component jump explains the innovation


@dataclass(frozen=True)
class ProcessNoise:
    """Process noise and physical bounds of the state (units as in the names)."""

    nu_per_injection: float            # N/V
    lh_per_injection_um: float         # µm
    nu_per_sqrt_s: float               # N/V / sqrt(s), temperature unknown
    nu_per_sqrt_s_known_t: float       # N/V / sqrt(s) left when the temperature change is measured
    lh_per_sqrt_s_um: float            # µm / sqrt(s)
    rate_per_sqrt_s: float             # N/V/s / sqrt(s), temperature unknown
    rate_per_sqrt_s_known_t: float     # N/V/s / sqrt(s) when the temperature change is measured
    slope_per_sqrt_s: float            # N/V/degC / sqrt(s)
    rate_tau_s: float                  # s
    max_var: tuple[float, float, float, float, float]   # caps of the diagonal: (N/V)^2, µm^2, (N/V/s)^2,
    # (N/V/degC)^2, (µm per injection)^2
    wear_per_injection_um: float = 0.0   # µm per injection, per injection: the wear rate's random walk

    @functools.cached_property
    def _predict_args(self) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
        """:func:`_predict`'s noise arguments with the temperature change unknown and known: floats, and
        the caps as a float64 array (built once per noise, not per injection)."""
        caps = c_float(self.max_var)

        def args(q_nu: float, q_rate: float) -> tuple[Any, ...]:
            return (float(self.rate_tau_s), float(self.nu_per_injection), float(q_nu), float(q_rate),
                    float(self.lh_per_injection_um), float(self.lh_per_sqrt_s_um), float(self.slope_per_sqrt_s),
                    float(self.wear_per_injection_um), caps)
        return (args(self.nu_per_sqrt_s, self.rate_per_sqrt_s),
                args(self.nu_per_sqrt_s_known_t, self.rate_per_sqrt_s_known_t))


def predict(x: np.ndarray, p: np.ndarray, dt_s: float, d_temp_c: float | None,
            noise: ProcessNoise) -> tuple[np.ndarray, np.ndarray]:
    """State and covariance ``dt_s`` seconds and ``d_temp_c`` degC (None: not measured) later."""
    known = d_temp_c is not None     # a measured temperature explains most drift: less left to chase
    result: tuple[np.ndarray, np.ndarray] = _PREDICT(c_float(x), c_float(p), float(dt_s), float(d_temp_c or 0.0), *noise._predict_args[known])
    return result


@njit(cache=True, nogil=True)
def _predict(x: np.ndarray, p: np.ndarray, dt: float, dtemp: float, tau: float, nu_inj: float, q_nu: float, q_rate: float,
             lh_inj: float, q_lh: float, q_slope: float, q_wear: float,
             max_var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``x' = F x``, ``p' = cap(F p F' + Q)``: the drift rate decays with ``tau`` (s) into N_u, the
    temperature slope acts over ``dtemp``, one injection's wear adds to L_h; Q per injection (the
    floors, the wear rate's walk) and per second (random walks of N_u, L_h, the rate (integrated into
    N_u) and the slope)."""
    a = math.exp(-dt / tau)
    f = np.eye(N_STATE)
    f[NU, RATE] = tau * (1.0 - a)
    f[RATE, RATE] = a
    f[NU, SLOPE] = dtemp
    f[LH, WEAR] = 1.0
    q = np.zeros((N_STATE, N_STATE))
    qr = q_rate * q_rate
    q[NU, NU] = nu_inj ** 2 + q_nu ** 2 * dt + qr * dt ** 3 / 3.0
    q[NU, RATE] = qr * dt ** 2 / 2.0
    q[RATE, NU] = q[NU, RATE]
    q[RATE, RATE] = qr * dt
    q[LH, LH] = lh_inj ** 2 + q_lh ** 2 * dt
    q[SLOPE, SLOPE] = q_slope ** 2 * dt
    q[WEAR, WEAR] = q_wear ** 2
    xn = np.zeros(N_STATE)
    fp = np.zeros((N_STATE, N_STATE))
    for i in range(N_STATE):
        for k in range(N_STATE):
            xn[i] += f[i, k] * x[k]
            for j in range(N_STATE):
                fp[i, j] += f[i, k] * p[k, j]
    pn = q.copy()
    for i in range(N_STATE):
        for j in range(N_STATE):
            for k in range(N_STATE):
                pn[i, j] += fp[i, k] * f[j, k]
    return xn, cap(pn, max_var)


@njit(cache=True, nogil=True)
def cap(p: np.ndarray, max_var: np.ndarray) -> np.ndarray:
    """``p`` with each variance at most its cap ``max_var`` (rows and columns scaled, so it stays
    positive definite)."""
    n = p.shape[0]
    d = np.empty(n)
    for i in range(n):
        d[i] = math.sqrt(min(1.0, max_var[i] / max(p[i, i], 1e-300)))
    out = np.empty_like(p)
    for i in range(n):
        for j in range(n):
            out[i, j] = p[i, j] * (d[i] * d[j])
    return out


@dataclass(frozen=True)
class Innovation:
    """Innovation ``e = z - H x`` (N/V, µm), its covariance ``s`` and ``d2 = e' s^-1 e``."""

    e: np.ndarray
    s: np.ndarray
    d2: float


def innovation(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray) -> Innovation:
    """The innovation of measurement ``z`` (covariance ``r``) against the state."""
    e, s, d2 = _INNOVATION(c_float(x), c_float(p), c_float(z), c_float(r))
    return Innovation(e, s, d2)


@njit(cache=True, nogil=True)
def _innovation(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``e = z - H x``, ``s = H p H' + r`` and ``e' s^-1 e`` (H picks N_u and L_h)."""
    e = np.empty(2)
    s = np.empty((2, 2))
    for i in range(2):
        e[i] = z[i] - x[i]
        for j in range(2):
            s[i, j] = p[i, j] + r[i, j]
    det = s[0, 0] * s[1, 1] - s[0, 1] * s[1, 0]
    d2 = (s[1, 1] * e[0] * e[0] - (s[0, 1] + s[1, 0]) * e[0] * e[1] + s[0, 0] * e[1] * e[1]) / det
    return e, s, d2


def update(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update with ``z`` (Joseph form: stays symmetric positive definite)."""
    result: tuple[np.ndarray, np.ndarray] = _UPDATE(c_float(x), c_float(p), c_float(z), c_float(r))
    return result


@njit(cache=True, nogil=True)
def _update(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gain ``K = p H' s^-1``, ``x + K (z - H x)``, ``(I - K H) p (I - K H)' + K r K'`` symmetrised."""
    n = N_STATE
    s00, s01, s10, s11 = p[0, 0] + r[0, 0], p[0, 1] + r[0, 1], p[1, 0] + r[1, 0], p[1, 1] + r[1, 1]
    det = s00 * s11 - s01 * s10
    k = np.empty((n, 2))
    for i in range(n):                      # K = (s^-1 H p)' with s^-1 = [[s11, -s01], [-s10, s00]] / det
        k[i, 0] = (s11 * p[0, i] - s01 * p[1, i]) / det
        k[i, 1] = (-s10 * p[0, i] + s00 * p[1, i]) / det
    e0, e1 = z[0] - x[0], z[1] - x[1]
    xn = np.empty(n)
    for i in range(n):
        xn[i] = x[i] + k[i, 0] * e0 + k[i, 1] * e1
    ikh = np.eye(n)
    for i in range(n):
        ikh[i, 0] -= k[i, 0]
        ikh[i, 1] -= k[i, 1]
    a = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            for m in range(n):
                a[i, j] += ikh[i, m] * p[m, j]
    pn = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for m in range(n):
                acc += a[i, m] * ikh[j, m]
            for u in range(2):
                for v in range(2):
                    acc += k[i, u] * r[u, v] * k[j, v]
            pn[i, j] = acc
    out = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            out[i, j] = 0.5 * (pn[i, j] + pn[j, i])
    return xn, out


def gated_update(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray,
                 gate: float) -> tuple[np.ndarray, np.ndarray, Innovation, bool]:
    """Update only if the innovation passes the chi-square ``gate``; returns (x, p, innovation, accepted)."""
    inn = innovation(x, p, z, r)
    if not inn.d2 <= gate:
        return x, p, inn, False
    x, p = update(x, p, z, r)
    return x, p, inn, True


def jump_components(inn: Innovation, gate_1dof: float = CHI2_1DOF_1E4) -> tuple[int, ...]:
    """Which components jumped: ``(NU,)``, ``(LH,)`` or ``(NU, LH)``, by the generalised likelihood ratio.

    For a jump of unknown size along one component the innovation left over is
    ``d2 - (s^-1 e)_i^2 / (s^-1)_ii``; if the better single component leaves a chi-square(1) value
    within ``gate_1dof``, that component alone explains the disagreement.
    """
    si = np.linalg.inv(inn.s)
    w = si @ inn.e
    left = [inn.d2 - w[i] ** 2 / si[i, i] for i in (NU, LH)]
    i = int(np.argmin(left))
    return (i,) if left[i] <= gate_1dof else (NU, LH)


def release(p: np.ndarray, components: tuple[int, ...], max_var: np.ndarray | tuple[float, ...]) -> np.ndarray:
    """Forget the state's knowledge of ``components`` (a jump of N_u also forgets its drift rate, one
    of L_h its wear rate: another part)."""
    p = p.copy()
    comps = set(components) | ({RATE} if NU in components else set()) | ({WEAR} if LH in components else set())
    for i in comps:
        p[i, :] = 0.0
        p[:, i] = 0.0
        p[i, i] = max_var[i]
    return p


def initial(z: np.ndarray, r: np.ndarray, rate_var: float, slope: float, slope_var: float,
            wear_var: float) -> tuple[np.ndarray, np.ndarray]:
    """State and covariance from a first raw estimate: no drift, the prior temperature slope, no wear
    (with the variance ``wear_var``, (µm per injection)^2)."""
    x = np.array([z[0], z[1], 0.0, slope, 0.0])
    p = np.zeros((N_STATE, N_STATE))
    p[:2, :2] = r
    p[RATE, RATE] = rate_var
    p[SLOPE, SLOPE] = slope_var
    p[WEAR, WEAR] = wear_var
    return x, p


_PREDICT, _INNOVATION, _UPDATE = DirectCall(_predict), DirectCall(_innovation), DirectCall(_update)
