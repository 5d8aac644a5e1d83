"""Cramér–Rao bound of (N_u, L_h) for one injection under white Gaussian voltage noise.

For y = U_sim(θ) + e, e ~ N(0, σ² I) sampled every dt, the Fisher information is
F = Jᵀ J / σ² with J = ∂U_sim/∂θ over the window's samples; cov(θ̂) ≥ F⁻¹. J is taken by central
differences of the exact simulator. With ``robust=True`` the nuisance span is projected out of J
first (the information left when smooth I/Q-shaped model errors are absorbed).
"""

from __future__ import annotations

import numpy as np

from estimator.ident.fit.cost import nuisance_basis
from estimator.model.drive import sample_count
from estimator.model.fast_sim import FastSimulator

FD = (1e-3, 1e-9)   # N/V, m


def crb(sim: FastSimulator, current_a: np.ndarray, nu_n_per_v: float, lh_m: float, f_open_n: float,
        sigma_v: float, window_s: float = 100e-6, robust: bool = False) -> np.ndarray:
    """Lower bound of the covariance of (N_u [N/V], L_h [m]), shape (2, 2)."""
    n = min(current_a.size, sample_count(window_s, sim.dt_s))
    cur = np.ascontiguousarray(current_a[:n])
    nu = np.array([nu_n_per_v + FD[0], nu_n_per_v - FD[0], nu_n_per_v, nu_n_per_v])
    lh = np.array([lh_m, lh_m, lh_m + FD[1], lh_m - FD[1]])
    res = sim.simulate(cur, nu, lh, f_open_n, exact=True)
    u = res.voltage_v
    jac = np.stack([(u[0] - u[1]) / (2 * FD[0]), (u[2] - u[3]) / (2 * FD[1])], axis=1)
    if robust:
        b = nuisance_basis(cur, sim.dt_s)
        jac = jac - b @ (b.T @ jac)
    fisher = jac.T @ jac / sigma_v ** 2
    return np.linalg.inv(fisher)


def crb_opening_time(sim: FastSimulator, current_a: np.ndarray, nu_n_per_v: float, lh_m: float, f_open_n: float,
                     cov: np.ndarray) -> float:
    """Standard deviation (s) of the valve-opening time implied by a (N_u, L_h) covariance (delta method)."""
    nu = np.array([nu_n_per_v + FD[0], nu_n_per_v - FD[0], nu_n_per_v, nu_n_per_v])
    lh = np.array([lh_m, lh_m, lh_m + 1e-8, lh_m - 1e-8])
    res = sim.simulate(np.ascontiguousarray(current_a), nu, lh, f_open_n, exact=True)
    t = res.t_open_s
    grad = np.array([(t[0] - t[1]) / (2 * FD[0]), (t[2] - t[3]) / 2e-8])
    if not np.all(np.isfinite(grad)):
        return float("nan")
    return float(np.sqrt(grad @ cov @ grad))
