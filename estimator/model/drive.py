"""Amplifier current drives: the :class:`Drive` protocol, its shapes, and the registry of named shapes.

A drive is the current (A) the amplifier pushes into the actuator from the start of charging
(t = 0). Every simulation in the product takes its current from a drive: the bench plant (a
scenario's drive), the identifier's valve prediction (the measured current, then the amplifier
holding the charge), and every command that simulates (``sim_bench simulate --drive``, ``table3``,
``calibration-traces``, ``speed``, the daemon's warm-up).

Between samples the current is taken as linear (first-order hold); both simulators use the same
convention, so a sampled current means the same input to each.

A new drive shape is one class here with ``current(t_s)`` (and, if it has a name users may type,
one :func:`register_drive` call): the plant, the scenarios and the commands take it from there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from estimator.errors import TraceError

SAMPLE_PERIOD_S = 0.5e-6  # the paper's sampling time, 0.5 µs (section 5.2)
SAMPLE_PERIOD_REL_TOL = 1e-6  # two sample periods this close (relative) are the same grid

# Trapezoid corners of the standard drive (s): charge 0-180 µs, hold to 500 µs, discharge after.
CHARGE_RISE_S = 20e-6
CHARGE_FALL_START_S = 160e-6
CHARGE_END_S = 180e-6
DISCHARGE_START_S = 500e-6
# Plateau current (A) chosen so that PSA No. 1 measurement 1 of Table 3 (N_u = 16.39 N/V,
# L_h = 0.6 µm, F_open = 28 N) gives a mean plunger stroke of 24.50 µm over 215-490 µs.
# Re-derived by ``python -m sim_bench table3 --fit-drive`` and checked by tests/test_table3.py.
STANDARD_AMPLITUDE_A = 4.2870333


def sample_count(t_end_s: float, dt_s: float = SAMPLE_PERIOD_S) -> int:
    """Number of sample instants 0, dt, ..., up to and including t_end (s)."""
    return int(round(t_end_s / dt_s)) + 1


def sample_times(t_end_s: float, dt_s: float = SAMPLE_PERIOD_S) -> np.ndarray:
    """Sample instants 0, dt, ..., up to and including t_end (s)."""
    return np.arange(sample_count(t_end_s, dt_s)) * dt_s


@runtime_checkable
class Drive(Protocol):
    """An amplifier current program: ``current(t_s)`` in A at times ``t_s`` (s from the start of charging),
    and ``samples(t_end_s, dt_s)``, the current on the grid 0, dt, ..., t_end that the simulators take."""

    def current(self, t_s: np.ndarray) -> np.ndarray:
        """Current (A) at the times ``t_s`` (s)."""
        ...

    def samples(self, t_end_s: float, dt_s: float = SAMPLE_PERIOD_S) -> np.ndarray:
        """Current (A) at the sample instants 0, dt, ..., t_end (s)."""
        ...


class TimeFunction:
    """Base of drives defined by a function of time: ``samples`` evaluates ``current`` on the grid."""

    def current(self, t_s: np.ndarray) -> np.ndarray:  # pragma: no cover - every shape overrides it
        raise NotImplementedError

    def samples(self, t_end_s: float, dt_s: float = SAMPLE_PERIOD_S) -> np.ndarray:
        """Current (A) at the sample instants 0, dt, ..., t_end (s)."""
        return self.current(sample_times(t_end_s, dt_s))


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
    result: np.ndarray = charge + dis
    return result


@dataclass(frozen=True)
class StandardDrive(TimeFunction):
    """The standard trapezoidal drive (:func:`standard_drive`) with plateau current ``amplitude_a`` (A)."""

    amplitude_a: float = STANDARD_AMPLITUDE_A

    def current(self, t_s: np.ndarray) -> np.ndarray:
        return standard_drive(t_s, self.amplitude_a)


@dataclass(frozen=True)
class ChopperRipple(TimeFunction):
    """A drive plus the triangular ripple (peak ``ripple_a`` A, period ``period_s`` s, phase in periods)
    of a switching amplifier, present while the commanded current flows (|I| > ``above_a``)."""

    base: Drive
    ripple_a: float
    period_s: float
    phase: float = 0.0
    above_a: float = 0.5

    def current(self, t_s: np.ndarray) -> np.ndarray:
        base = self.base.current(t_s)
        if self.ripple_a <= 0:
            return base
        saw = ((t_s / self.period_s + self.phase) % 1.0)
        tri = 4.0 * np.abs(saw - 0.5) - 1.0
        result: np.ndarray = base + self.ripple_a * tri * (np.abs(base) > self.above_a)
        return result


@dataclass(frozen=True, eq=False)
class TableDrive(TimeFunction):
    """A current given at increasing times (a measured or designed current), linear between them and
    zero outside them (an amplifier that is not driving carries no current).

    Build it with :meth:`from_table` (checks the table) or :meth:`sampled` (a current sampled every
    ``dt_s`` from t = 0, e.g. an injection's measurement: on a grid of the same period its samples are
    used as they are).
    """

    t_s: np.ndarray
    current_a: np.ndarray
    dt_s: float | None = None     # uniform sampling from t = 0 (s), None: arbitrary times

    @classmethod
    def from_table(cls, t_s: np.ndarray, current_a: np.ndarray) -> TableDrive:
        """Raises :class:`TraceError` for NaN values, unequal lengths or non-increasing times."""
        t = np.asarray(t_s, dtype=float)
        i = np.asarray(current_a, dtype=float)
        if t.ndim != 1 or t.shape != i.shape or t.size < 2:
            raise TraceError("current needs at least two (t_s, current_A) samples of equal length")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(i))):
            raise TraceError("current file contains NaN or infinite values")
        if np.any(np.diff(t) <= 0):
            raise TraceError("current file times must be strictly increasing")
        return cls(t, i)

    @classmethod
    def sampled(cls, current_a: np.ndarray, dt_s: float) -> TableDrive:
        """The current ``current_a`` sampled at 0, dt, 2 dt, ... (A, s); zero after the last sample."""
        i = np.asarray(current_a, dtype=float)
        return cls(np.arange(i.size) * dt_s, i, float(dt_s))

    def current(self, t_s: np.ndarray) -> np.ndarray:
        result: np.ndarray = np.interp(np.asarray(t_s, dtype=float), self.t_s, self.current_a, left=0.0, right=0.0)
        return result

    def samples(self, t_end_s: float, dt_s: float = SAMPLE_PERIOD_S) -> np.ndarray:
        if self.dt_s is not None:
            return sampled_samples(self.current_a, self.dt_s, t_end_s, dt_s)
        return self.current(sample_times(t_end_s, dt_s))


def same_grid(sampled_dt_s: float, dt_s: float) -> bool:
    """Whether samples ``sampled_dt_s`` apart lie on the grid of period ``dt_s`` (s), within the period
    tolerance the identifier accepts: then they are used as they are."""
    return abs(sampled_dt_s - dt_s) <= SAMPLE_PERIOD_REL_TOL * dt_s


def sampled_samples(current_a: np.ndarray, sampled_dt_s: float, t_end_s: float,
                    dt_s: float = SAMPLE_PERIOD_S) -> np.ndarray:
    """:meth:`TableDrive.samples` of ``TableDrive.sampled(current_a, sampled_dt_s)`` (A, s): on the same
    grid (:func:`same_grid`) the samples themselves up to ``t_end_s``, zero after the last one, without
    building the drive (the per-injection valve prediction calls it); else the drive's interpolation."""
    if not same_grid(sampled_dt_s, dt_s):
        return TableDrive.sampled(current_a, sampled_dt_s).current(sample_times(t_end_s, dt_s))
    n = sample_count(t_end_s, dt_s)
    out = np.zeros(n)
    k = min(n, current_a.size)
    out[:k] = current_a[:k]
    return out


# Named drive shapes users can select (``--drive NAME``): name -> factory of the default instance.
DRIVES: dict[str, Callable[[], Drive]] = {}


def register_drive(name: str, factory: Callable[[], Drive]) -> None:
    """Make a drive shape selectable by name in every command; names are unique."""
    if name in DRIVES:
        raise ValueError(f"drive {name!r} registered twice")
    DRIVES[name] = factory


def named_drive(name: str) -> Drive:
    """The registered drive ``name``; ValueError naming the known drives otherwise."""
    try:
        return DRIVES[name]()
    except KeyError:
        raise ValueError(f"unknown drive {name!r}; one of {', '.join(DRIVES)}") from None


register_drive("standard", StandardDrive)
