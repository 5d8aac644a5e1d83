"""The result of one single-injection identification (raw estimate), with units in its fields."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from estimator.ident.coords import NuLh, cov_from_si
from estimator.ident.status import Status
from estimator.units import PER_MICRO, UM_PER_M, US_PER_S


@dataclass
class Estimate:
    """Result of one identification (raw, single injection). SI units except where named.

    ``cov`` is the covariance of (N_u [N/V], L_h [m]) from the Gauss–Newton model and the noise
    level estimated from the residual, plus ``model_error_cov`` (in (N/V, µm)) where the model cannot
    explain the samples (status ``model_mismatch``: the bias that implies, see
    :mod:`estimator.ident.fit.mismatch`; ``model_error_d`` the difference to the other cost's estimate in
    (N/V, µm), zero if it was not made); ``structure_chi2`` is the adequacy test's statistic of the plain
    model; ``preload_chi2`` and ``preload_delta_n`` the test of the header's preload force where it was
    made (:func:`estimator.ident.fit.mismatch.preload_check`), ``preload_shift`` the move the samples' own force implies
    where it is suspect (in ``model_error_cov``), ``preload_wrong`` whether the header is wrong; ``jtj`` and ``directions`` are in (N/V, µm) coordinates.
    """

    nu_n_per_v: float
    lh_m: float
    cov: np.ndarray
    cost_vs: float
    criterion: float
    evaluations: int
    status: Status
    message: str = ""
    robust: bool = False
    model_error_stat: float = float("nan")
    noise_sigma_v: float = float("nan")
    t_contact_s: float = float("nan")
    t_open_s: float = float("nan")
    stroke_m: float = float("nan")
    jtj: np.ndarray = field(default_factory=lambda: np.eye(2))
    directions: np.ndarray = field(default_factory=lambda: np.eye(2))
    structure_chi2: float = float("nan")
    model_error_cov: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    model_error_d: np.ndarray = field(default_factory=lambda: np.zeros(2))
    mismatch: bool = False    # the model cannot explain the samples (``model_error_cov`` is then added)
    excess_z: float = float("nan")   # a mismatched fit's residual excess over white noise (sd, see cold_start)
    preload_chi2: float = float("nan")      # the header's preload force against the samples (chi-square(1); NaN: not tested)
    preload_delta_n: float = float("nan")   # the change of preload force the samples point to (N)
    preload_shift: np.ndarray | None = None  # (N/V, µm) the move the samples' own preload force implies (if suspect)
    preload_wrong: bool = False              # the header's preload force cannot explain the samples
    current_noise_cov: np.ndarray | None = None  # (N/V, µm) what the measured current's noise adds (in ``cov``)

    @property
    def point(self) -> NuLh:
        """The estimate as a point of the (N/V, µm) plane."""
        return NuLh.from_si(self.nu_n_per_v, self.lh_m)

    @property
    def cov_um(self) -> np.ndarray:
        """``cov`` in (N/V, µm)."""
        return cov_from_si(self.cov)

    @property
    def sigma_nu(self) -> float:
        """1-sigma uncertainty of N_u in N/V."""
        return float(math.sqrt(max(self.cov[0, 0], 0.0)))

    @property
    def sigma_lh_m(self) -> float:
        """1-sigma uncertainty of L_h in m."""
        return float(math.sqrt(max(self.cov[1, 1], 0.0)))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary with units in the keys (µm, µs, µV·s)."""
        def num(v: float, scale: float = 1.0, nd: int = 6) -> float | None:
            return None if not math.isfinite(v) else round(v * scale, nd)
        return {
            "nu_n_per_v": num(self.nu_n_per_v), "lh_um": num(self.lh_m, UM_PER_M),
            "sigma_nu_n_per_v": num(self.sigma_nu), "sigma_lh_um": num(self.sigma_lh_m, UM_PER_M),
            "cost_uvs": num(self.cost_vs, PER_MICRO, 3), "t_contact_us": num(self.t_contact_s, US_PER_S, 3),
            "t_open_us": num(self.t_open_s, US_PER_S, 3), "stroke_um": num(self.stroke_m, UM_PER_M, 4),
            "status": self.status.value, "message": self.message, "evaluations": self.evaluations,
            "robust": self.robust, "model_error_stat": num(self.model_error_stat, 1.0, 2),
            "noise_sigma_v": num(self.noise_sigma_v, 1.0, 4), "structure_chi2": num(self.structure_chi2, 1.0, 1),
            "preload_chi2": num(self.preload_chi2, 1.0, 1), "preload_delta_n": num(self.preload_delta_n, 1.0, 2),
        }


def rejected(reason: str, evaluations: int = 0) -> Estimate:
    """An Estimate that carries only a rejection reason."""
    nan = float("nan")
    return Estimate(nan, nan, np.full((2, 2), np.nan), nan, nan, evaluations, Status.REJECTED, reason)


