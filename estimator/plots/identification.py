"""PNG figures of an identification, in the spirit of the paper's Figs. 7/13 and 14 (needs matplotlib)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from estimator.errors import EstimatorError
from estimator.ident.config import IdentConfig
from estimator.ident.fit.cost import CostModel
from estimator.ident.fit.idle_stroke import effective_window_s, identify, search_box
from estimator.ident.measurement import Injection
from estimator.model.fast_sim import FastSimulator
from estimator.plots.figures import pyplot, save
from estimator.units import M_PER_UM, PER_MICRO, S_PER_US, UM_PER_M, US_PER_S


def plot_identification(inj: Injection, out_dir: Path, config: IdentConfig | None = None, grid: int = 41,
                        sim: FastSimulator | None = None) -> list[Path]:
    """Identify the injection and write ``voltage_fit.png`` and ``cost_contour.png`` into ``out_dir``.

    ``grid`` contour points per axis (3..201); ``sim`` the simulator (default: Tables 1-2 at the trace's period).
    """
    if not 3 <= grid <= 201:
        raise EstimatorError(f"contour grid {grid} must have 3..201 points per axis")
    plt = pyplot()
    config = config or IdentConfig()
    sim = sim or FastSimulator(dt_s=inj.dt_s)
    est = identify(inj, sim, config)
    if est.status == "rejected":
        raise EstimatorError(f"trace rejected: {est.message}")
    out_dir.mkdir(parents=True, exist_ok=True)
    res = sim.simulate(inj.current_a, est.nu_n_per_v, est.lh_m, inj.f_open_n)
    t_us = inj.t_s * US_PER_S
    window_us = effective_window_s(config, inj, est.robust) * US_PER_S

    fig, ax = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    ax[0].plot(t_us, inj.voltage_v, lw=0.8, label="measured U_m")
    ax[0].plot(t_us, res.voltage_v[0], lw=0.8, label=f"model (N_u={est.nu_n_per_v:.3f} N/V, L_h={est.lh_m * UM_PER_M:.2f} µm)")
    ax[0].set_ylabel("U [V]")
    ax[0].legend(loc="lower right")
    ax[1].plot(t_us, inj.voltage_v - res.voltage_v[0], lw=0.8, color="C3")
    ax[1].set_ylabel("U_m - U_sim [V]")
    ax[2].plot(t_us, res.s3_m[0] * UM_PER_M, lw=0.8, label="s3 (bottom plate)")
    ax[2].plot(t_us, res.s4_m[0] * UM_PER_M, lw=0.8, label="s4 (plunger)")
    ax[2].axhline(est.lh_m * UM_PER_M, color="k", lw=0.5, ls=":", label="L_h")
    ax[2].set_ylabel("[µm]")
    ax[2].set_xlabel("t [µs]")
    ax[2].legend(loc="upper left")
    for a in ax:
        a.axvline(window_us, color="k", lw=0.6, ls="--")
        a.grid(alpha=0.3)
    fig.suptitle(f"identification ({est.status}{', robust' if est.robust else ''}), window 0-{window_us:.0f} µs")
    p1 = save(fig, out_dir / "voltage_fit.png")

    model = CostModel(sim, inj, window_us * S_PER_US, "l1", est.robust)
    box = search_box(config, sim, inj.f_open_n)
    half = np.array([max(8 * est.sigma_nu, 0.15), max(8 * est.sigma_lh_m * UM_PER_M, 1.0)])
    lo = np.maximum(box.lo, [est.nu_n_per_v - half[0], est.lh_m * UM_PER_M - half[1]])
    hi = np.minimum(box.hi, [est.nu_n_per_v + half[0], est.lh_m * UM_PER_M + half[1]])
    nu = np.linspace(lo[0], hi[0], grid)
    lh = np.linspace(lo[1], hi[1], grid)
    g_nu, g_lh = np.meshgrid(nu, lh)
    j = model(g_nu.ravel(), g_lh.ravel() * M_PER_UM).reshape(grid, grid) * PER_MICRO
    fig, ax = plt.subplots(figsize=(6.5, 5))
    finite = np.isfinite(j)
    cs = ax.contourf(g_nu, g_lh, np.where(finite, j, np.nan), levels=30, cmap="viridis")
    fig.colorbar(cs, label="J = ∫|U_m - U_sim| dt [µV·s]" + (" (projected)" if est.robust else ""))
    ax.plot(est.nu_n_per_v, est.lh_m * UM_PER_M, "r+", ms=14, mew=2, label="minimum")
    cov = np.asarray(est.cov_um, dtype=float)
    if np.all(np.isfinite(cov)):   # the estimate's 2σ ellipse (N/V, µm): the valley's direction and width
        w, v = np.linalg.eigh(cov)
        a = np.linspace(0.0, 2.0 * np.pi, 100)
        ring = v @ (2.0 * np.sqrt(np.clip(w, 0.0, None))[:, None] * np.vstack([np.cos(a), np.sin(a)]))
        ax.plot(est.nu_n_per_v + ring[0], est.lh_m * UM_PER_M + ring[1], "r-", lw=1.0, label="2σ")
    ax.set_xlabel("N_u [N/V]")
    ax.set_ylabel("L_h [µm]")
    ax.legend()
    ax.set_title("cost function J(N_u, L_h) (Fig. 14)")
    p2 = save(fig, out_dir / "cost_contour.png")
    return [p1, p2]
