"""The one coordinate type of the (N_u, L_h) plane: N_u in N/V, L_h in µm (searches, filter, JSON).

SI metres appear only at the boundary to the simulator (``lh_m``) and in :class:`Estimate`'s SI
fields; every conversion of the plane goes through here (the factors themselves are
:mod:`estimator.units`').
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from estimator.units import UM_PER_M

__all__ = ["TO_SI", "UM_PER_M", "NuLh", "cov_from_si", "cov_to_si"]


class NuLh(NamedTuple):
    """A point of the search plane: coupling factor N_u (N/V) and idle stroke L_h (µm)."""

    nu_n_per_v: float
    lh_um: float

    @property
    def lh_m(self) -> float:
        """L_h in m (for the simulator)."""
        return self.lh_um / UM_PER_M

    def array(self) -> np.ndarray:
        """``[N_u N/V, L_h µm]`` as a float array."""
        return np.array([self.nu_n_per_v, self.lh_um], dtype=float)

    @classmethod
    def of(cls, x: np.ndarray) -> NuLh:
        """From an array ``[N_u N/V, L_h µm]``."""
        return cls(float(x[0]), float(x[1]))

    @classmethod
    def from_si(cls, nu_n_per_v: float, lh_m: float) -> NuLh:
        """From N_u in N/V and L_h in m."""
        return cls(float(nu_n_per_v), float(lh_m) * UM_PER_M)


#: scale of (N/V, µm) coordinates to SI (N/V, m): ``x_si = x * TO_SI``
TO_SI = np.array([1.0, 1.0 / UM_PER_M])


_COV_TO_SI = np.outer(TO_SI, TO_SI)


def cov_to_si(cov_um: np.ndarray) -> np.ndarray:
    """A (2, 2) covariance in (N/V, µm) converted to (N/V, m)."""
    return cov_um * _COV_TO_SI


def cov_from_si(cov_m: np.ndarray) -> np.ndarray:
    """A (2, 2) covariance in (N/V, m) converted to (N/V, µm)."""
    return cov_m / _COV_TO_SI
