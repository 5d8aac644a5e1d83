"""Amplifier current drives: the standard trapezoidal drive and resampling of measured currents.

Between samples the current is taken as linear (first-order hold); both simulators use the
same convention, so a sampled current means the same input to each.
"""

from __future__ import annotations

import numpy as np

from estimator.errors import TraceError

SAMPLE_PERIOD_S = 0.5e-6  # the paper's sampling time, 0.5 µs (section 5.2)

# Trapezoid corners of the standard drive (s): charge 0-180 µs, hold to 500 µs, discharge after.
CHARGE_RISE_S = 20e-6
CHARGE_FALL_START_S = 160e-6
CHARGE_END_S = 180e-6
DISCHARGE_START_S = 500e-6
# Plateau current (A) chosen so that PSA No. 1 measurement 1 of Table 3 (N_u = 16.39 N/V,
# L_h = 0.6 µm, F_open = 28 N) gives a mean plunger stroke of 24.50 µm over 215-490 µs.
# Re-derived by ``python -m sim_bench table3 --fit-drive`` and checked by tests/test_table3.py.
STANDARD_AMPLITUDE_A = 4.2870333


def trapezoid(t_s: np.ndarray, amplitude_a: float, t0_s: float, rise_s: float, flat_end_s: float,
              end_s: float) -> np.ndarray:
    """A trapezoid pulse: 0 before t0, linear up to ``amplitude`` at t0+rise, flat, linear down to 0 at end."""
    t = np.asarray(t_s, dtype=float)
    up = np.clip((t - t0_s) / rise_s, 0.0, 1.0)
    down = np.clip((end_s - t) / (end_s - flat_end_s), 0.0, 1.0)
    return amplitude_a * np.minimum(up, down) * (t >= t0_s) * (t <= end_s)


def standard_drive(t_s: np.ndarray, amplitude_a: float = STANDARD_AMPLITUDE_A) -> np.ndarray:
    """The documented standard drive in A at times ``t_s`` (s).

    Charging trapezoid 0-20 µs up, flat to 160 µs, down to 0 at 180 µs; zero current (hold)
    until 500 µs; then the mirrored discharge trapezoid 500-680 µs that returns the charge.
    """
    t = np.asarray(t_s, dtype=float)
    charge = trapezoid(t, amplitude_a, 0.0, CHARGE_RISE_S, CHARGE_FALL_START_S, CHARGE_END_S)
    dis = trapezoid(t, -amplitude_a, DISCHARGE_START_S, CHARGE_RISE_S,
                    DISCHARGE_START_S + CHARGE_FALL_START_S, DISCHARGE_START_S + CHARGE_END_S)
    return charge + dis


def sample_times(t_end_s: float, dt_s: float = SAMPLE_PERIOD_S) -> np.ndarray:
    """Sample instants 0, dt, ..., up to and including t_end (s)."""
    n = int(round(t_end_s / dt_s)) + 1
    return np.arange(n) * dt_s


def resample_current(t_s: np.ndarray, current_a: np.ndarray, t_end_s: float,
                     dt_s: float = SAMPLE_PERIOD_S) -> np.ndarray:
    """Linearly interpolate a current given at any (increasing) times onto the 0.5 µs grid.

    Outside the given times the current is held at zero: an amplifier that is not driving
    carries no current. Raises :class:`TraceError` for NaN values or non-increasing times.
    """
    t = np.asarray(t_s, dtype=float)
    i = np.asarray(current_a, dtype=float)
    if t.ndim != 1 or t.shape != i.shape or t.size < 2:
        raise TraceError("current needs at least two (t_s, current_A) samples of equal length")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(i))):
        raise TraceError("current file contains NaN or infinite values")
    if np.any(np.diff(t) <= 0):
        raise TraceError("current file times must be strictly increasing")
    grid = sample_times(t_end_s, dt_s)
    return np.interp(grid, t, i, left=0.0, right=0.0)
