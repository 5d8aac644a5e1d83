"""Kalman steps of the recursive estimator as pure functions (no state of their own).

State ``x = [N_u (N/V), L_h (µm), r (N/V per s), b (N/V per degC)]``: the coupling factor, the idle
stroke, the drift rate of N_u that temperature does not explain, and the injector's temperature
slope dN_u/dT (eq. 25, learned online). The measurement is the raw single-injection estimate
``z = [N_u, L_h]`` with its Gauss–Newton covariance ``R``.

Prediction over ``dt`` seconds and ``dT`` degC: ``N_u += tau (1 - a) r + b dT`` with ``a = exp(-dt/tau)``
(a drift rate decays: warm-ups end), ``r *= a``; L_h and b are random walks. Process noise per
injection (a floor for model jitter) plus per second (random walks of N_u, L_h and r). Variances are
capped by the physical ranges, so a long gap means "anywhere in the range", not infinity.

A gate failure is explained by the generalised likelihood ratio of a jump in N_u alone, in L_h
alone, or in both (:func:`jump_components`); :func:`release` forgets what the filter knew about
the components that jumped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

N_STATE = 4
NU, LH, RATE, SLOPE = range(N_STATE)
H = np.eye(2, N_STATE)          # z = H x: the raw estimate measures N_u and L_h
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
    max_var: tuple[float, float, float, float]   # caps of the diagonal: (N/V)^2, µm^2, (N/V/s)^2, (N/V/degC)^2


def predict(x: np.ndarray, p: np.ndarray, dt_s: float, d_temp_c: float | None,
            noise: ProcessNoise) -> tuple[np.ndarray, np.ndarray]:
    """State and covariance ``dt_s`` seconds and ``d_temp_c`` degC (None: not measured) later."""
    a = math.exp(-dt_s / noise.rate_tau_s)
    f = np.eye(N_STATE)
    f[NU, RATE] = noise.rate_tau_s * (1.0 - a)
    f[RATE, RATE] = a
    f[NU, SLOPE] = d_temp_c or 0.0
    q = np.zeros((N_STATE, N_STATE))
    known = d_temp_c is not None     # a measured temperature explains most drift: less left to chase
    qr = (noise.rate_per_sqrt_s_known_t if known else noise.rate_per_sqrt_s) ** 2
    q_nu = noise.nu_per_sqrt_s_known_t if known else noise.nu_per_sqrt_s
    q[NU, NU] = noise.nu_per_injection ** 2 + q_nu ** 2 * dt_s + qr * dt_s ** 3 / 3.0
    q[NU, RATE] = q[RATE, NU] = qr * dt_s ** 2 / 2.0
    q[RATE, RATE] = qr * dt_s
    q[LH, LH] = noise.lh_per_injection_um ** 2 + noise.lh_per_sqrt_s_um ** 2 * dt_s
    q[SLOPE, SLOPE] = noise.slope_per_sqrt_s ** 2 * dt_s
    x = f @ x
    p = f @ p @ f.T + q
    return x, cap(p, noise.max_var)


def cap(p: np.ndarray, max_var) -> np.ndarray:
    """``p`` with each variance at most its cap (rows and columns scaled, so it stays positive definite)."""
    d = np.sqrt(np.minimum(1.0, np.asarray(max_var) / np.maximum(np.diag(p), 1e-300)))
    return p * np.outer(d, d)


@dataclass(frozen=True)
class Innovation:
    """Innovation ``e = z - H x`` (N/V, µm), its covariance ``s`` and ``d2 = e' s^-1 e``."""

    e: np.ndarray
    s: np.ndarray
    d2: float


def innovation(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray) -> Innovation:
    """The innovation of measurement ``z`` (covariance ``r``) against the state."""
    e = z - H @ x
    s = H @ p @ H.T + r
    return Innovation(e, s, float(e @ np.linalg.solve(s, e)))


def update(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update with ``z`` (Joseph form: stays symmetric positive definite)."""
    s = H @ p @ H.T + r
    k = np.linalg.solve(s, H @ p).T          # p H' s^-1 (s, p symmetric)
    x = x + k @ (z - H @ x)
    ikh = np.eye(N_STATE) - k @ H
    p = ikh @ p @ ikh.T + k @ r @ k.T
    return x, 0.5 * (p + p.T)


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


def release(p: np.ndarray, components: tuple[int, ...], max_var) -> np.ndarray:
    """Forget the state's knowledge of ``components`` (a jump of N_u also forgets its drift rate)."""
    p = p.copy()
    comps = set(components) | ({RATE} if NU in components else set())
    for i in comps:
        p[i, :] = 0.0
        p[:, i] = 0.0
        p[i, i] = max_var[i]
    return p


def initial(z: np.ndarray, r: np.ndarray, rate_var: float, slope: float, slope_var: float) -> tuple[np.ndarray, np.ndarray]:
    """State and covariance from a first raw estimate: no drift, the prior temperature slope."""
    x = np.array([z[0], z[1], 0.0, slope])
    p = np.zeros((N_STATE, N_STATE))
    p[:2, :2] = r
    p[RATE, RATE] = rate_var
    p[SLOPE, SLOPE] = slope_var
    return x, p
