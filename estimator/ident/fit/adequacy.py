"""Does the model explain the samples? A test of a fit's residual against the measurement noise.

The noise level comes from the residual's first differences, which a smooth model error hardly
raises (it is independent of how well the model fits); a robust trimmed RMS, so a spike does not
inflate it. Two statistics are formed in units of that noise variance:

- ``structure``: the residual's energy in its ``SMOOTH_COLUMNS`` lowest cosine (DCT-II) components,
  and ``low`` in the lowest ``LOW_COLUMNS`` of them (more power where the error is smoothest).
  Under a correct model with white noise it is at most chi-square with that many degrees of freedom
  (the fit removes some of it); a structural model error puts its residual there (mechanical
  resonances below ~120 kHz in a 100 µs window, a misplaced contact), far above it.
- ``excess_z``: the whole residual energy above white noise, in standard deviations (a broadband
  error such as an unmodelled filter shows here too).

The thresholds are set for a false-alarm rate well below 1 % on the exact plant at 0.1 and 0.3 V
noise (``python -m sim_bench accuracy --sweep exact``); a linearised analysis of 10 % structural
errors leaves chi-square excesses of 50-4000, far above them.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from estimator._compiled import njit
from estimator._compiled.direct_call import DirectCall, c_float
from estimator.ident.fit.cost import MAD_PER_SIGMA, NOISE_FLOOR_V
from estimator.ident.fit.sensitivity_kernel import current_noise

SMOOTH_COLUMNS = 24          # cosines 0..23: up to ~115 kHz in a 100 µs window
LOW_COLUMNS = 8              # cosines 0..7 (up to ~35 kHz): where most structural errors leave their residual
STRUCTURE_THRESHOLD = 60.0   # chi-square(24): P(> 60) = 6e-5 under a correct model
LOW_THRESHOLD = 36.0         # chi-square(8): P(> 36) = 2e-5
EXCESS_Z_THRESHOLD = 6.0     # the whole residual's energy above white noise, standard deviations
TRIM_SIGMA = 5.0             # differences beyond this many robust standard deviations are clipped


@dataclass(frozen=True)
class Adequacy:
    """The model-adequacy test of one fit.

    Attributes
    ----------
    structure : residual energy in the smooth columns over the noise variance (chi-square units).
    low : the same in the lowest :data:`LOW_COLUMNS` of them.
    excess_z : whole residual energy above white noise, in standard deviations.
    noise_v : the noise level (V, 1 sigma) from the residual's differences.
    adequate : both statistics within their thresholds.
    """

    structure: float
    low: float
    excess_z: float
    noise_v: float
    adequate: bool

    @property
    def reason(self) -> str:
        """Why the model is inadequate (a phrase), '' if it is adequate."""
        if self.adequate:
            return ""
        return (f"model cannot explain the samples (structure chi2 {self.structure:.0f}, "
                f"residual {self.excess_z:+.1f} sd above noise {self.noise_v:.3f} V)")


def noise_level_v(residual_v: np.ndarray) -> float:
    """White-noise level (V, 1 sigma) from the first differences: their RMS over sqrt(2), with
    differences beyond :data:`TRIM_SIGMA` robust standard deviations clipped (spikes)."""
    r = np.ascontiguousarray(residual_v, dtype=float)
    if r.size < 3:
        return float("nan")
    return float(_noise_level(r, TRIM_SIGMA, NOISE_FLOOR_V))


def current_noise_a(current_a: np.ndarray) -> float:
    """White-noise level (A, 1 sigma) of a measured current: the median absolute second difference over
    0.6745 sqrt(6). An amplifier's current is piecewise linear (its switching ripple, a triangle of a
    few µs), which first differences would count as noise; second differences see only its corners
    (on the bench's 8 µs ripple: 0.0118 A measured for 0.0104 A of noise and quantisation; a
    quarter too high where a corner falls every 8 samples)."""
    return float(current_noise(c_float(current_a).ravel()))


@njit(cache=True, nogil=True)
def _noise_level(r: np.ndarray, trim: float, floor: float) -> float:
    n = r.shape[0] - 1
    d = np.empty(n)
    for k in range(n):
        d[k] = abs(r[k + 1] - r[k])
    half = n // 2
    p = np.partition(d, half)     # the median of |d| (the upper one for an even count: a scale, not a statistic)
    clip = trim * max(p[half] / MAD_PER_SIGMA, floor * np.sqrt(2.0))
    acc = 0.0
    for k in range(n):
        acc += min(d[k] * d[k], clip * clip)
    result: float = max(np.sqrt(acc / n / 2.0), floor)
    return result


@functools.lru_cache(maxsize=32)
def smooth_basis(n: int, m: int = SMOOTH_COLUMNS) -> np.ndarray:
    """Orthonormal DCT-II columns 0..m-1 over ``n`` samples, shape (n, min(m, n)); read-only."""
    m = min(m, n)
    j = np.arange(n) + 0.5
    b = np.cos(np.pi * np.outer(j, np.arange(m)) / n)
    b /= np.linalg.norm(b, axis=0)
    b.setflags(write=False)
    return b


def assess(residual_v: np.ndarray, fitted: int = 2, structure_threshold: float = STRUCTURE_THRESHOLD,
           excess_threshold: float = EXCESS_Z_THRESHOLD) -> Adequacy:
    """Test a fit's residual (V, the samples of its cost window; projected off the nuisance span in
    robust mode) for structure the model left; ``fitted`` is the number of fitted directions (the
    parameters and the nuisance columns), which the residual's degrees of freedom lose."""
    r = np.ascontiguousarray(residual_v, dtype=float)
    n = r.size
    if n < 3:
        return Adequacy(float("nan"), float("nan"), float("nan"), float("nan"), False)
    sigma, structure, low, energy = _STATISTICS(r, _rows(n), TRIM_SIGMA, NOISE_FLOOR_V, LOW_COLUMNS)
    if not (n > fitted + 2 and math.isfinite(sigma) and math.isfinite(energy)):
        return Adequacy(float("nan"), float("nan"), float("nan"), sigma, False)
    dof = n - fitted
    excess = (energy / sigma ** 2 - dof) / math.sqrt(2.0 * dof)
    adequate = structure <= structure_threshold and low <= structure_threshold * LOW_THRESHOLD / STRUCTURE_THRESHOLD \
        and excess <= excess_threshold
    return Adequacy(structure, low, excess, sigma, adequate)


def structure_z(residual_v: np.ndarray, fitted: int = 2) -> float:
    """The residual's (V) smooth structure (:func:`assess`) in standard deviations above its expectation
    under a correct model (chi-square of :data:`SMOOTH_COLUMNS` components)."""
    return (assess(residual_v, fitted).structure - SMOOTH_COLUMNS) / math.sqrt(2.0 * SMOOTH_COLUMNS)


@functools.lru_cache(maxsize=32)
def _rows(n: int) -> np.ndarray:
    """:func:`smooth_basis` transposed, C-contiguous (a column per row), read-only."""
    rows = np.ascontiguousarray(smooth_basis(n).T)
    rows.setflags(write=False)
    return rows


@njit(cache=True, nogil=True)
def _statistics(r: np.ndarray, rows: np.ndarray, trim: float, floor: float, low_columns: int) -> tuple[float, float, float, float]:
    """(noise level V, structure, low, residual energy V^2) of one residual in one compiled call;
    ``rows`` the smooth basis's columns as rows."""
    sigma = _noise_level(r, trim, floor)
    var = sigma * sigma
    structure = 0.0
    low = 0.0
    for j in range(rows.shape[0]):
        c = 0.0
        for k in range(r.shape[0]):
            c += rows[j, k] * r[k]
        c2 = c * c / var
        structure += c2
        if j < low_columns:
            low += c2
    energy = 0.0
    for k in range(r.shape[0]):
        energy += r[k] * r[k]
    return sigma, structure, low, energy


_STATISTICS = DirectCall(_statistics)   # r: C float64 1-D, rows: read-only C float64 2-D, floats, an int
