"""One measured injection (sampled current and voltage) and its validity checks.

Checks return a reason instead of raising deep inside the estimator: a bad trace becomes a
``rejected`` result with that reason, never an exception escaping the update.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from estimator._compiled import njit
from estimator.errors import TraceError
from estimator.model.chain import MeasurementChain
from estimator.model.drive import SAMPLE_PERIOD_REL_TOL, TableDrive, sample_count
from estimator.model.parameters import NOMINAL_PRELOAD_N
from estimator.units import US_PER_S

MIN_WINDOW_S = 40e-6          # shorter windows hold too little of the charging phase to identify anything
MAX_ABS_CURRENT_A = 100.0     # beyond any injector amplifier
MAX_ABS_VOLTAGE_V = 1000.0
MIN_PEAK_CURRENT_A = 0.2      # a "flat" current does not excite the actuator


@njit(cache=True, nogil=True)
def _extremes(i: np.ndarray, u: np.ndarray) -> tuple[float, float, float, float]:
    """(max, min) of ``i`` and of ``u`` in one pass each; NaN if either holds a NaN (as numpy's max)."""
    i_max, i_min, u_max, u_min = -np.inf, np.inf, -np.inf, np.inf
    for k in range(i.shape[0]):
        v = i[k]
        if v != v:
            return np.nan, np.nan, np.nan, np.nan
        i_max, i_min = max(i_max, v), min(i_min, v)
    for k in range(u.shape[0]):
        v = u[k]
        if v != v:
            return np.nan, np.nan, np.nan, np.nan
        u_max, u_min = max(u_max, v), min(u_min, v)
    return i_max, i_min, u_max, u_min


def median(x: np.ndarray) -> float:
    """``np.median`` of a 1-D float array without NaN, the same to the bit (the mean of the two middle
    values for an even size), at a third of its cost for a trace's ~200 sample steps."""
    n = x.size
    k = n // 2
    if n % 2:
        return float(np.partition(x, k)[k])
    p = np.partition(x, (k - 1, k))
    return float((p[k - 1] + p[k]) / 2)


@dataclass(frozen=True)
class Injection:
    """Sampled amplifier signals of one injection, uniformly sampled from t = 0 (SI units).

    Attributes
    ----------
    current_a, voltage_v : (N,) samples at t = k * dt_s.
    dt_s : sample period in s.
    f_open_n : valve preload for this injection in N (spring + rail pressure).
    injector_id, counter : identification on the bus (informative).
    temperature_c : fuel temperature in degC if known (NaN otherwise); the recursive estimator uses
        its changes to predict N_u (eq. 25).
    time_s : time of the injection in s on any monotonic clock (bus timestamp, trace metadata), NaN if
        unknown; the recursive estimator scales its process noise by the time between injections.
    chain_corrected : True once the measurement chain has been undone (:meth:`through_chain`).
    """

    current_a: np.ndarray
    voltage_v: np.ndarray
    dt_s: float
    f_open_n: float = NOMINAL_PRELOAD_N
    injector_id: int = 0
    counter: int = 0
    temperature_c: float = float("nan")
    time_s: float = float("nan")
    chain_corrected: bool = False

    def through_chain(self, chain: MeasurementChain) -> Injection:
        """The actuator's own current and voltage with the amplifier's ``chain`` undone (once: an
        injection already corrected, or an identity chain, is returned as it is)."""
        if self.chain_corrected or chain.identity:
            return self
        cur, volt = chain.correct(self.current_a, self.voltage_v, self.dt_s)
        return replace(self, current_a=cur, voltage_v=volt, chain_corrected=True)

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.current_a.size)

    def drive(self) -> TableDrive:
        """The measured current as a drive: these samples, then zero (the amplifier holding the charge)."""
        return TableDrive.sampled(self.current_a, self.dt_s)

    @property
    def t_s(self) -> np.ndarray:
        """Sample times in s."""
        return np.arange(self.n) * self.dt_s

    @property
    def duration_s(self) -> float:
        """Time of the last sample in s."""
        return (self.n - 1) * self.dt_s

    def problem(self) -> str | None:
        """Why this injection cannot be identified (one short phrase), or None if it can."""
        i, u = self.current_a, self.voltage_v
        if i.ndim != 1 or u.shape != i.shape:
            return "current and voltage differ in length"
        if not (math.isfinite(self.dt_s) and self.dt_s > 0):
            return "invalid sample period"
        if i.size == 0:
            return "too short (no samples)"
        i_max, i_min, u_max, u_min = _extremes(np.ascontiguousarray(i, dtype=float),
                                               np.ascontiguousarray(u, dtype=float))
        if not all(map(math.isfinite, (i_max, i_min, u_max, u_min))):   # NaN propagates into them
            return "NaN or infinite samples"
        if not math.isfinite(self.f_open_n) or not (0.0 <= self.f_open_n <= 5000.0):
            return "preload force out of range"
        if self.duration_s < MIN_WINDOW_S - 1e-12:
            return f"too short ({self.duration_s * US_PER_S:.1f} µs < {MIN_WINDOW_S * US_PER_S:.0f} µs)"
        if max(i_max, -i_min) > MAX_ABS_CURRENT_A or max(u_max, -u_min) > MAX_ABS_VOLTAGE_V:
            return "sample values out of range"
        if i_max < MIN_PEAK_CURRENT_A or i_max - i_min < MIN_PEAK_CURRENT_A:
            return "flat current (no charging pulse)"
        return None

    def window(self, t_end_s: float) -> Injection:
        """The samples with t <= t_end_s (a view-sized copy)."""
        k = min(self.n, sample_count(t_end_s, self.dt_s))
        return Injection(self.current_a[:k], self.voltage_v[:k], self.dt_s, self.f_open_n,
                         self.injector_id, self.counter, self.temperature_c, self.time_s, self.chain_corrected)

    @classmethod
    def from_samples(cls, t_s: np.ndarray, current_a: np.ndarray, voltage_v: np.ndarray,
                     f_open_n: float = NOMINAL_PRELOAD_N, **kw: object) -> Injection:
        """Build from sample times; raises :class:`TraceError` unless they are uniform and start at 0."""
        t = np.asarray(t_s, dtype=float)
        if t.ndim != 1 or t.size < 3:
            raise TraceError("too short (fewer than 3 samples)")
        if not np.all(np.isfinite(t)):
            raise TraceError("NaN in sample times")
        d = t[1:] - t[:-1]
        dt = median(d)
        if dt <= 0 or np.max(np.abs(d - dt)) > max(SAMPLE_PERIOD_REL_TOL * dt, 1e-12):
            raise TraceError("wrong sampling: sample times are not uniform")
        if abs(t[0]) > 1e-3 * dt:
            raise TraceError(f"wrong sampling: first sample at {t[0] * US_PER_S:.3f} µs, expected 0")
        return cls(np.asarray(current_a, dtype=float), np.asarray(voltage_v, dtype=float), dt,
                   float(f_open_n), **kw)  # type: ignore[arg-type]
