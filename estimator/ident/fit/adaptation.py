"""Temperature adaptation (eq. 26): N_u alone, from an actuator without valve (no contact).

``min_{N_u} ∫_0^t1 |U_m − y(N_u)| dt`` over the charging phase (default t1 = 170 µs), all other
parameters at their Table 1 values. A grid over the N_u bounds, then parabolic line searches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimator.ident.fit.cost import CostModel, noise_sigma_v
from estimator.ident.fit.search import Box, line_search
from estimator.ident.measurement import Injection
from estimator.model.fast_sim import FastSimulator
from estimator.units import UM_PER_M

NO_CONTACT_LH_M = 1.0   # an idle stroke of 1 m: the stack never reaches a piston


@dataclass(frozen=True)
class AdaptationResult:
    """N_u (N/V) with its 1-sigma uncertainty, the paper's cost (V*s) and a status."""

    nu_n_per_v: float
    sigma_nu: float
    cost_vs: float
    evaluations: int
    status: str
    message: str = ""


def adapt_nu(injection: Injection, sim: FastSimulator | None = None, window_s: float = 170e-6,
             norm: str = "l1", nu_bounds: tuple[float, float] | None = None) -> AdaptationResult:
    """Identify N_u of an actuator without valve from one trace (eq. 26), within ``nu_bounds`` (N/V;
    default the parameter set's N_u range). Never raises for bad data."""
    problem = injection.problem()
    if problem:
        return AdaptationResult(float("nan"), float("nan"), float("nan"), 0, "rejected", problem)
    sim = sim or FastSimulator(dt_s=injection.dt_s)
    model = CostModel(sim, injection, window_s, norm, robust=False)
    psa = sim.params.psa
    lo, hi = psa.nu_min_n_per_v, psa.nu_max_n_per_v
    if nu_bounds is not None:
        lo, hi = max(nu_bounds[0], lo), min(nu_bounds[1], hi)
    grid = np.linspace(lo, hi, 25)
    j = model(grid, NO_CONTACT_LH_M)
    x0 = grid[int(np.argmin(j))]
    box = Box(np.array([lo, NO_CONTACT_LH_M * UM_PER_M]), np.array([hi, NO_CONTACT_LH_M * UM_PER_M]))

    def f(x: np.ndarray) -> np.ndarray:
        return model(x[:, 0], NO_CONTACT_LH_M)

    x = np.array([x0, NO_CONTACT_LH_M * UM_PER_M])
    step = grid[1] - grid[0]
    for _ in range(12):
        lr = line_search(f, x, np.array([1.0, 0.0]), step, box)
        moved = abs(lr.x[0] - x[0])
        x = lr.x
        step = max(step / 4.0, 1e-5)
        if moved < 1e-5 and step <= 1e-4:
            break
    # uncertainty from the least-squares curvature of the voltage in N_u
    h = 1e-3 if x[0] + 1e-3 <= hi else -1e-3
    res = model.simulate(np.array([x[0], x[0] + h]), NO_CONTACT_LH_M)
    r0 = model.measured - res.voltage_v[0]
    sens = (res.voltage_v[1] - res.voltage_v[0]) / h
    sigma = noise_sigma_v(r0) / np.sqrt(max(float(sens @ sens), 1e-300))
    status = "at_bound" if (x[0] <= lo + 1e-3 or x[0] >= hi - 1e-3) else "ok"
    return AdaptationResult(float(x[0]), float(sigma), float(model.paper_cost_vs(res)[0]), model.evaluations,
                            status)
