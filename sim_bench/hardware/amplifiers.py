"""Simulated amplifiers: the standard current each delivers at scale 1, and its switching ripple.

A drive correction scales an amplifier's *own* standard drive and moves its start; amplifiers differ in
the shape of that drive even where they put the same charge into the actuator. The profiles here are
the ones every compensation figure is measured on:

- ``standard``: the built-in trapezoid (:class:`~estimator.model.drive.StandardDrive`) with a ±0.15 A
  chopper ripple of 8 µs, the plant the estimator was first written against;
- ``short-high``: the same charge in a shorter plateau at a higher current (rise 15 µs, flat to 115 µs,
  down at 130 µs: 1.39 × the plateau current), a ±0.15 A ripple of 6 µs;
- ``current-controlled``: a current controller following the trapezoid with the step response of an
  under-damped loop (40 kHz, damping 0.45: ≈ 20 % overshoot at each corner, the current lagging by a
  few µs) and a ±0.3 A hysteresis-band ripple of 5 µs.

Two more are selectable by name and not in ``compensation``'s default run (:data:`EXTRA_PROFILES`):
shapes the estimator was never tuned on, for checking that a result does not depend on the three:

- ``boost-hold``: a boost to 1.8 × the plateau current for 25 µs (8 µs ramps), then a lower hold
  current to 140 µs, the trapezoid's charge; a ±0.2 A ripple of 7 µs;
- ``slow-ramp``: a linear rise over 60 µs, flat to 130 µs, down at 150 µs, the trapezoid's charge (the
  valve opens while the current still rises); a ±0.1 A ripple of 10 µs.

Each scales linearly with the correction's scale (its ripple does not: a switching amplifier's band is
its own). ``python -m sim_bench compensation --amplifier NAME`` runs a lot on one of them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estimator.model.drive import (
    STANDARD_AMPLITUDE_A,
    Drive,
    StandardDrive,
    TableDrive,
    TimeFunction,
    register_drive,
    trapezoid,
)

CHARGE_DURATION_S = 160e-6      # the standard trapezoid's charge / plateau current: 20/2 + 140 + 20/2 µs
FINE_DT_S = 0.05e-6             # the controller's response is computed on this grid (s)
HORIZON_S = 750e-6


@dataclass(frozen=True)
class Scaled(TimeFunction):
    """``scale`` × a drive's current."""

    base: Drive
    scale: float

    def current(self, t_s: np.ndarray) -> np.ndarray:
        return self.scale * self.base.current(t_s)


def short_high() -> Drive:
    """The standard charge in a shorter plateau at a higher current (the discharge mirrored at 500 µs)."""
    rise, flat_end, end = 15e-6, 115e-6, 130e-6
    amp = STANDARD_AMPLITUDE_A * CHARGE_DURATION_S / (flat_end - rise + rise)   # same area as the trapezoid
    t = np.arange(0.0, HORIZON_S, FINE_DT_S)
    cur = trapezoid(t, amp, 0.0, rise, flat_end, end) + trapezoid(t, -amp, 500e-6, rise, 500e-6 + flat_end, 500e-6 + end)
    return TableDrive.sampled(cur, FINE_DT_S)


def current_controlled(natural_hz: float = 40e3, damping: float = 0.45) -> Drive:
    """The trapezoid as an under-damped current loop follows it (exact discretisation of the
    second-order loop on a fine grid; unit DC gain, so the charge is the trapezoid's)."""
    from scipy.signal import cont2discrete, dlsim

    t = np.arange(0.0, HORIZON_S, FINE_DT_S)
    ref = StandardDrive().current(t)
    w = 2 * np.pi * natural_hz
    a = np.array([[0.0, 1.0], [-w * w, -2 * damping * w]])
    b = np.array([[0.0], [w * w]])
    c = np.array([[1.0, 0.0]])
    ad, bd, cd, dd, _ = cont2discrete((a, b, c, np.zeros((1, 1))), FINE_DT_S, method="zoh")
    _, y, _ = dlsim((ad, bd, cd, dd, FINE_DT_S), ref)
    return TableDrive.sampled(np.asarray(y).ravel(), FINE_DT_S)


def boost_hold() -> Drive:
    """A boost to 1.8 × the plateau current for 25 µs, then a hold current to 140 µs (8 µs ramps; the
    boost ramps down while the hold ramps up), scaled to the trapezoid's charge; the discharge a
    trapezoid at 500 µs."""
    t = np.arange(0.0, HORIZON_S, FINE_DT_S)
    charge = STANDARD_AMPLITUDE_A * CHARGE_DURATION_S
    cur = trapezoid(t, 1.8, 0.0, 8e-6, 25e-6, 33e-6) + trapezoid(t, 1.0, 25e-6, 8e-6, 140e-6, 148e-6)
    cur *= charge / (float(np.sum(cur)) * FINE_DT_S)
    return TableDrive.sampled(cur + _discharge(t), FINE_DT_S)


def slow_ramp() -> Drive:
    """A linear rise over 60 µs, flat to 130 µs, down at 150 µs, scaled to the trapezoid's charge; the
    discharge a trapezoid at 500 µs."""
    t = np.arange(0.0, HORIZON_S, FINE_DT_S)
    cur = trapezoid(t, 1.0, 0.0, 60e-6, 130e-6, 150e-6)
    cur *= STANDARD_AMPLITUDE_A * CHARGE_DURATION_S / (float(np.sum(cur)) * FINE_DT_S)
    return TableDrive.sampled(cur + _discharge(t), FINE_DT_S)


def _discharge(t_s: np.ndarray) -> np.ndarray:
    """The standard trapezoid's discharge moved to 500 µs (A)."""
    return trapezoid(t_s, -STANDARD_AMPLITUDE_A, 500e-6, 20e-6, 640e-6, 660e-6)


@dataclass(frozen=True)
class Amplifier:
    """An amplifier: its standard drive at scale 1 (no ripple) and its ripple (peak A, period s)."""

    name: str
    standard: Drive = field(default_factory=StandardDrive)
    ripple_a: float = 0.15
    ripple_period_s: float = 8e-6

    def drive(self, scale: float = 1.0) -> Drive:
        """The commanded current for a correction's ``scale`` (the standard drive itself at 1)."""
        return self.standard if scale == 1.0 else Scaled(self.standard, scale)


def amplifier(name: str) -> Amplifier:
    """The profile ``name`` (:data:`PROFILES`); ValueError naming the known ones."""
    if name == "standard":
        return Amplifier("standard")
    if name == "short-high":
        return Amplifier("short-high", short_high(), 0.15, 6e-6)
    if name == "current-controlled":
        return Amplifier("current-controlled", current_controlled(), 0.3, 5e-6)
    if name == "boost-hold":
        return Amplifier("boost-hold", boost_hold(), 0.2, 7e-6)
    if name == "slow-ramp":
        return Amplifier("slow-ramp", slow_ramp(), 0.1, 10e-6)
    raise ValueError(f"unknown amplifier {name!r}; one of {', '.join(PROFILES + EXTRA_PROFILES)}")


PROFILES = ("standard", "short-high", "current-controlled")   # compensation's default run: every figure
EXTRA_PROFILES = ("boost-hold", "slow-ramp")                   # by name only
STANDARD = Amplifier("standard")


# selectable by name in every command that simulates (``sim_bench simulate --drive short-high``)
register_drive("short-high", short_high)
register_drive("current-controlled", current_controlled)
register_drive("boost-hold", boost_hold)
register_drive("slow-ramp", slow_ramp)
