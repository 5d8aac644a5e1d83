"""PNG plots of a bench run: estimates vs truth over injections, one voltage fit and its cost contour."""

from __future__ import annotations

from pathlib import Path

from sim_bench.hardware.scenarios import Scenario


def plot_bench(rows: list[dict], sc: Scenario, out_dir: Path, seed: int) -> list[Path]:
    """Write estimates.png (+ voltage_fit.png, cost_contour.png from one simulated injection)."""
    from estimator.ident.measurement import Injection
    from estimator.plots.figures import pyplot, save
    from estimator.plots.identification import plot_identification
    from sim_bench.hardware.node import InjectionSource

    plt = pyplot()
    fig, ax = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    for inj in sorted({r["injector"] for r in rows}):
        rs = [r for r in rows if r["injector"] == inj]
        k = [r["k"] for r in rs]
        line, = ax[0].plot(k, [r["lh_um"] for r in rs], lw=0.9, label=f"injector {inj}")
        ax[0].plot(k, [r["lh_true_um"] for r in rs], lw=0.8, ls="--", color=line.get_color())
        ax[1].plot(k, [r["nu"] for r in rs], lw=0.9, color=line.get_color())
        ax[1].plot(k, [r["nu_true"] for r in rs], lw=0.8, ls="--", color=line.get_color())
    ax[0].set_ylabel("L_h [µm] (dashed: truth)")
    ax[1].set_ylabel("N_u [N/V] (dashed: truth)")
    ax[1].set_xlabel("injection number per injector")
    ax[0].legend(fontsize=8, ncol=4)
    for a in ax:
        a.grid(alpha=0.3)
    fig.suptitle(f"bench {sc.name}: filtered estimates vs SimTruth")
    p = save(fig, out_dir / "estimates.png")
    src = InjectionSource(sc, seed + 99)
    m, _ = src.measure(0, 0, sc.seconds / 2)
    paths = plot_identification(Injection(m.current_a, m.voltage_v, m.dt_s, m.f_open_n), out_dir, grid=31)
    return [p, *paths]
