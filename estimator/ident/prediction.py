"""The published valve prediction, simulated again only when it could have changed.

The prediction (contact and opening time, plateau stroke: :func:`idle_stroke.predict_valve`) is a
simulation of 490 µs, longer than everything else in a warm update together. It depends on the
published (N_u, L_h), the preload and the measured current. :class:`ValveMemo` keeps the last
prediction of one injector and reuses it while the published estimate stays within its own standard
deviation of the point it was made for, the preload within ``F_OPEN_TOL_N`` and the charge within
``CHARGE_REL_TOL`` of the charge it was made with (the mechanics see the current only through the
charge, Q' = I; white noise on the sampled current averages out in it, a different drive does not):
what moves less than the estimate's own uncertainty cannot change the prediction by more than that
uncertainty does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from estimator.ident.idle_stroke import predict_valve
from estimator.ident.measurement import Injection
from estimator.model.fast_sim import FastSimulator

F_OPEN_TOL_N = 0.05          # preload change that forces a new prediction, N
CHARGE_REL_TOL = 0.001       # charge change anywhere in the injection, relative to its peak, that forces one


@dataclass
class ValveMemo:
    """The last prediction of one injector: the point (N/V, m), preload (N), current (A), result."""

    nu_n_per_v: float = math.nan
    lh_m: float = math.nan
    f_open_n: float = math.nan
    dt_s: float = math.nan
    charge: np.ndarray | None = field(default=None, repr=False)   # cumulative sum of the current (A x samples)
    result: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    reused: int = 0
    simulated: int = 0

    def still_valid(self, inj: Injection, nu: float, lh_m: float, sigma_nu: float, sigma_lh_m: float) -> bool:
        """True if the memo answers for this injection and point (σ: the published standard deviations)."""
        q = self.charge
        if q is None or q.size != inj.n or inj.dt_s != self.dt_s:
            return False
        if not (abs(nu - self.nu_n_per_v) <= sigma_nu and abs(lh_m - self.lh_m) <= sigma_lh_m):
            return False   # (NaN sigmas compare False: simulate)
        if not abs(inj.f_open_n - self.f_open_n) <= F_OPEN_TOL_N:
            return False
        return float(np.max(np.abs(np.cumsum(inj.current_a) - q))) <= CHARGE_REL_TOL * float(np.max(np.abs(q)))

    def predict(self, sim: FastSimulator, inj: Injection, nu: float, lh_m: float, sigma_nu: float,
                sigma_lh_m: float) -> tuple[float, float, float]:
        """Contact time (s), opening time (s) and plateau stroke (m) at (nu N/V, lh_m m)."""
        if self.still_valid(inj, nu, lh_m, sigma_nu, sigma_lh_m):
            self.reused += 1
            return self.result
        self.result = predict_valve(sim, inj, nu, lh_m)
        self.nu_n_per_v, self.lh_m, self.f_open_n, self.dt_s = nu, lh_m, inj.f_open_n, inj.dt_s
        self.charge = np.cumsum(inj.current_a, dtype=float)
        self.simulated += 1
        return self.result
