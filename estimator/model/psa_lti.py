"""The PSA alone (eqs. 23-24, no valve), simulated exactly for any parameter set.

The fast simulator tabulates its matrices for one parameter set; calibration (eq. 25) varies
k_p, k_s and R_b, so it needs this small exact simulator: first-order-hold discretisation by one
matrix exponential per call, then a compiled loop.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

from estimator.model import dynamics as dyn
from estimator.model import kernel
from estimator.model.parameters import InjectorParameters


def simulate_psa(params: InjectorParameters, nu_n_per_v: float, r_ohm: float, current_a: np.ndarray,
                 dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Voltage U (V) and bottom plate displacement s3 (m) for a sampled current (linear in between).

    ``r_ohm`` replaces R(N_u) (eq. 25 identifies R per temperature); F_ext = 0, start at rest.
    """
    a, b, c, _ = dyn.psa_state_space(params, nu_n_per_v)
    n = a.shape[0]
    m = np.zeros((n + 2, n + 2))
    m[:n, :n] = a
    m[:n, n] = b[:, 0]
    m[n, n + 1] = 1.0
    e = expm(m * dt_s)
    cur = np.ascontiguousarray(current_a, dtype=float)
    y = np.empty(cur.size)
    x = np.empty((cur.size, n))
    kernel.lti_foh_kernel(np.ascontiguousarray(e[:n, :n]), np.ascontiguousarray(e[:n, n]),
                          np.ascontiguousarray(e[:n, n + 1]), np.ascontiguousarray(c[0]), float(r_ohm), cur, dt_s,
                          y, x)
    return y, x[:, dyn.S3].copy()
