"""The amplifier's measurement chain: first-order anti-aliasing filters on U and I and a skew of I.

A real amplifier does not hand the estimator the actuator's voltage and current but what its ADCs
see: each channel through an anti-aliasing filter (first order, time constant ``tau = 1/(2 pi f_c)``),
and the current sampled a little later than the voltage (a skew). Left out of the model, a 300 kHz
filter on U moves N_u by about 1 % and L_h by up to 0.5 µm.

A known chain is part of the model: :meth:`MeasurementChain.correct` undoes it on the measured
samples, once per injection, before any simulator sees them, so the fast kernel, its compiled
searches, the valve prediction and the reference simulator all model it alike. The inverse of
``tau y' + y = x`` is ``x = y + tau y'``; ``y'`` is taken by central differences (one-sided at the
ends), which amplifies white noise by ``sqrt(1 + tau^2 / (2 dt^2))`` (1.25 for 300 kHz at 0.5 µs)
where an exact recursive inverse would ring. The skew is undone by linear interpolation.

:meth:`MeasurementChain.apply` is the forward chain on a finely sampled signal (what the simulated
amplifier does): the exact discretisation of the filter for a signal linear between samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator.errors import ParameterError
from estimator.units import US_PER_S

MAX_TAU_S = 20e-6     # a filter slower than 8 kHz would not be an anti-aliasing filter of a 2 MHz ADC
MAX_SKEW_S = 5e-6


@dataclass(frozen=True)
class MeasurementChain:
    """Anti-aliasing filters and skew of the amplifier's channels (s; 0 = none).

    Attributes
    ----------
    u_filter_tau_s : time constant of the first-order filter on the voltage channel in s.
    i_filter_tau_s : the same on the current channel in s.
    i_skew_s : how much later the current is sampled than the voltage in s (I lags U for > 0).
    """

    u_filter_tau_s: float = 0.0
    i_filter_tau_s: float = 0.0
    i_skew_s: float = 0.0

    def __post_init__(self) -> None:
        for name, limit in (("u_filter_tau_s", MAX_TAU_S), ("i_filter_tau_s", MAX_TAU_S), ("i_skew_s", MAX_SKEW_S)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ParameterError(f"{name} = {v!r} s must be a finite number")
            low = -limit if name == "i_skew_s" else 0.0
            if not low <= v <= limit:
                raise ParameterError(f"{name} = {v * US_PER_S:g} µs must be within {low * US_PER_S:g}..{limit * US_PER_S:g} µs")

    @classmethod
    def from_cutoffs(cls, u_cutoff_hz: float = 0.0, i_cutoff_hz: float = 0.0, i_skew_s: float = 0.0) -> MeasurementChain:
        """A chain from the filters' -3 dB frequencies in Hz (0 = no filter)."""
        def tau(f: float) -> float:
            if not (isinstance(f, (int, float)) and math.isfinite(f) and f >= 0):
                raise ParameterError(f"cut-off frequency {f!r} Hz must be >= 0")
            return 0.0 if f == 0 else 1.0 / (2 * math.pi * f)
        return cls(tau(u_cutoff_hz), tau(i_cutoff_hz), float(i_skew_s))

    @property
    def identity(self) -> bool:
        """True if the chain changes nothing (the default)."""
        return self.u_filter_tau_s == 0.0 and self.i_filter_tau_s == 0.0 and self.i_skew_s == 0.0

    def correct(self, current_a: np.ndarray, voltage_v: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The actuator's current (A) and voltage (V) at the sample times, from the measured ones."""
        volt = unfilter(voltage_v, self.u_filter_tau_s, dt_s) if self.u_filter_tau_s else voltage_v
        return self.actuator_current(current_a, dt_s), volt

    def actuator_current(self, current_a: np.ndarray, dt_s: float) -> np.ndarray:
        """The actuator's current (A) at the sample times, from the measured one (the current half of
        :meth:`correct`)."""
        cur = shift(current_a, self.i_skew_s / dt_s) if self.i_skew_s else current_a
        return unfilter(cur, self.i_filter_tau_s, dt_s) if self.i_filter_tau_s else cur

    def apply(self, current_a: np.ndarray, voltage_v: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """What the ADCs see of the actuator's current (A) and voltage (V) sampled every ``dt_s`` s
        (a fine grid: the signals are taken as linear between samples)."""
        cur = lowpass(current_a, self.i_filter_tau_s, dt_s) if self.i_filter_tau_s else current_a
        cur = shift(cur, -self.i_skew_s / dt_s) if self.i_skew_s else cur
        volt = lowpass(voltage_v, self.u_filter_tau_s, dt_s) if self.u_filter_tau_s else voltage_v
        return cur, volt


NO_CHAIN = MeasurementChain()


def unfilter(y: np.ndarray, tau_s: float, dt_s: float) -> np.ndarray:
    """The input of a first-order filter ``tau y' + y = x`` from its sampled output: ``y + tau y'``."""
    y = np.asarray(y, dtype=float)
    if y.size < 3:
        result: np.ndarray = y.copy()
        return result
    dy = np.empty_like(y)
    dy[1:-1] = (y[2:] - y[:-2]) / (2 * dt_s)
    dy[0] = (y[1] - y[0]) / dt_s
    dy[-1] = (y[-1] - y[-2]) / dt_s
    return y + tau_s * dy


def lowpass(x: np.ndarray, tau_s: float, dt_s: float) -> np.ndarray:
    """First-order filter ``tau y' + y = x`` from rest, exact for ``x`` linear between samples; along
    the last axis of ``x``."""
    from scipy.signal import lfilter  # here: importing scipy.signal costs ≈ 0.7 s, and only a chain needs it

    x = np.asarray(x, dtype=float)
    a = math.exp(-dt_s / tau_s)
    c = 1.0 - tau_s / dt_s * (1.0 - a)
    # y[k] = a y[k-1] + c x[k] + (1 - a - c) x[k-1], from y = x = 0
    result: np.ndarray = lfilter([c, (1.0 - a) - c], [1.0, -a], x, axis=-1)
    return result


def shift(x: np.ndarray, samples: float) -> np.ndarray:
    """``x`` read ``samples`` later (linear interpolation; the ends held): ``out[k] = x(k + samples)``."""
    x = np.asarray(x, dtype=float)
    k = np.arange(x.size, dtype=float) + samples
    result: np.ndarray = np.interp(k, np.arange(x.size, dtype=float), x)
    return result
