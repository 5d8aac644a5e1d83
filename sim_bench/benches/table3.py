"""Reproduction of the paper's Table 3 "sim" column for PSA No. 1 with the standard drive.

The paper identifies (N_u, L_h) on measurements and reports the plateau plunger stroke of the
adapted model ("sim"). Feeding those identified values into our model with one trapezoidal drive,
scaled once so that measurement 1 gives the paper's 24.50 µm, must reproduce the other rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from estimator.model.drive import STANDARD_AMPLITUDE_A, StandardDrive
from estimator.model.fast_sim import FastSimulator

# Table 3, PSA No. 1: (measurement, N_u [N/V], L_h [µm], s_4,s meas [µm], s_4,s sim [µm], cost [µVs])
PAPER_PSA1 = (
    (1, 16.39, 0.6, 24.89, 24.50, 51.18),
    (2, 16.37, 2.5, 22.04, 22.59, 46.61),
    (3, 16.35, 6.8, 18.88, 18.40, 42.84),
    (4, 16.37, 8.4, 16.75, 16.71, 46.08),
)
T_END_S = 500e-6


@dataclass(frozen=True)
class Table3Row:
    """One reproduced row: the paper's values and ours (µm)."""

    meas: int
    nu_n_per_v: float
    lh_um: float
    paper_meas_um: float
    paper_sim_um: float
    ours_um: float
    t_contact_us: float
    t_open_us: float

    @property
    def diff_um(self) -> float:
        """Ours minus the paper's "sim" stroke (µm)."""
        return self.ours_um - self.paper_sim_um


def reproduce(sim: FastSimulator | None = None, amplitude_a: float = STANDARD_AMPLITUDE_A) -> list[Table3Row]:
    """Simulate the four PSA No. 1 rows with the standard drive of the given amplitude (A)."""
    sim = sim or FastSimulator()
    nu = np.array([r[1] for r in PAPER_PSA1])
    lh = np.array([r[2] for r in PAPER_PSA1]) * 1e-6
    res = sim.simulate(StandardDrive(amplitude_a).samples(T_END_S), nu, lh, exact=True)
    stroke = res.plateau_stroke_m() * 1e6
    return [Table3Row(r[0], r[1], r[2], r[3], r[4], float(stroke[i]), float(res.t_contact_s[i] * 1e6),
                      float(res.t_open_s[i] * 1e6)) for i, r in enumerate(PAPER_PSA1)]


def fit_drive_amplitude(sim: FastSimulator | None = None) -> float:
    """The standard-drive amplitude (A) at which row 1 gives the paper's 24.50 µm."""
    sim = sim or FastSimulator()
    _, nu, lh, _, target, _ = PAPER_PSA1[0]

    def excess(a: float) -> float:
        res = sim.simulate(StandardDrive(a).samples(T_END_S), nu, lh * 1e-6, exact=True)
        return float(res.plateau_stroke_m()[0] * 1e6 - target)

    return brentq(excess, 2.0, 8.0, xtol=1e-9)


def format_table(rows: list[Table3Row]) -> str:
    """The reproduction in the layout of Table 3 (PSA No. 1), with our column beside the paper's."""
    head = (f"{'meas':>4} {'N_u [N/V]':>9} {'L_h [µm]':>8} {'s4s meas':>9} {'s4s sim':>8} "
            f"{'s4s ours':>9} {'ours-sim':>8} {'t_contact':>9} {'t_open':>7}")
    units = f"{'':>4} {'':>9} {'':>8} {'[µm]':>9} {'[µm]':>8} {'[µm]':>9} {'[µm]':>8} {'[µs]':>9} {'[µs]':>7}"
    lines = ["Table 3, PSA No. 1 - paper (meas, sim) vs this model with the standard drive", head, units]
    for r in rows:
        lines.append(f"{r.meas:>4} {r.nu_n_per_v:>9.2f} {r.lh_um:>8.1f} {r.paper_meas_um:>9.2f} "
                     f"{r.paper_sim_um:>8.2f} {r.ours_um:>9.2f} {r.diff_um:>+8.2f} {r.t_contact_us:>9.2f} "
                     f"{r.t_open_us:>7.2f}")
    return "\n".join(lines)
