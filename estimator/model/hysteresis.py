"""The actuator's charge–voltage hysteresis, for stacks whose hysteresis R(N_u)·I cannot stand in for.

Goldfarb and Celanovic (paper section 3.2) put a rate-independent hysteresis element H in series with
the stack's linear capacitance: the terminal voltage is ``U = U_p + H[Q]`` where ``U_p`` drives the
mechanics and ``Q`` is the charge. Under charge (current) drive, as here, ``Q`` is the integral of the
measured current, so ``H[Q]`` is known once the current is, and it reaches only the voltage the
amplifier measures, never the force on the stack. The paper replaces H's rising branch by ``R(N_u)·I``
(eq. 22); a part whose hysteresis that term cannot explain is given this element instead:

``U = U_p + R_s·I + s(N_u)·H[Q]``,  ``H[Q] = Σ_i w_i · play_{r_i}[Q]``,  ``s(N_u) = exp(-R_0b (N_u - N_ref))``

- ``H`` is a Prandtl–Ishlinskii operator: a weighted sum of play (backlash) operators of half-widths
  ``r_i`` (C, fixed) with weights ``w_i`` (V/C), from rest at the start of charging. It is linear in
  the weights, so a calibration fits them by least squares like any other factor.
- ``s(N_u)`` scales it with temperature as ``R(N_u)`` does (the hysteresis shrinks as the stack warms,
  Fig. 6), relative to ``N_ref``.
- ``R_s`` (Ω) is the series resistance of the cables and the amplifier's output stage, which
  ``R(N_u)·I`` carried too.

With the element, ``R(N_u)·I`` is left out of the voltage. Without it (:data:`NO_HYSTERESIS`, the
default), the model is the paper's. See ``docs/design.md`` for why this element and not a Bouc–Wen
state or Maxwell-slip elements.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimator._compiled import njit
from estimator.errors import ParameterError

NU_REF_N_PER_V = 16.39          # N_u at which s(N_u) = 1 (the paper's reference temperature)
MAX_PLAYS = 16                  # play operators an element may have
MAX_THRESHOLD_C = 10e-3         # a play's half-width at most this charge (C; a stack holds ≈ 0.4 mC)
MAX_WEIGHT_V_PER_C = 1e7        # |w_i| at most this (V/C: 10 V per µC)
MAX_SERIES_OHM = 10.0


@dataclass(frozen=True)
class Hysteresis:
    """A hysteresis element (module docstring): play half-widths (C), their weights (V/C), the series
    resistance (Ω) and the reference N_u (N/V). ``present`` when it has plays or a series
    resistance; then it replaces R(N_u)·I in the voltage."""

    thresholds_c: tuple[float, ...] = ()
    weights_v_per_c: tuple[float, ...] = ()
    series_ohm: float = 0.0
    nu_ref_n_per_v: float = NU_REF_N_PER_V

    def __post_init__(self) -> None:
        thr, w = self.thresholds_c, self.weights_v_per_c
        if not isinstance(thr, tuple) or not isinstance(w, tuple) or len(thr) != len(w):
            raise ParameterError("[hysteresis] thresholds_c and weights_v_per_c must be lists of the same length")
        if len(thr) > MAX_PLAYS:
            raise ParameterError(f"[hysteresis] at most {MAX_PLAYS} plays, got {len(thr)}")
        for name, values, lo, hi in (("thresholds_c", thr, 0.0, MAX_THRESHOLD_C),
                                     ("weights_v_per_c", w, -MAX_WEIGHT_V_PER_C, MAX_WEIGHT_V_PER_C),
                                     ("series_ohm", (self.series_ohm,), 0.0, MAX_SERIES_OHM),
                                     ("nu_ref_n_per_v", (self.nu_ref_n_per_v,), 1.0, 100.0)):
            for v in values:
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
                    raise ParameterError(f"[hysteresis] {name}: {v!r} must be a number within {lo:g}..{hi:g}")
        if list(thr) != sorted(set(thr)):
            raise ParameterError("[hysteresis] thresholds_c must rise strictly")

    @property
    def present(self) -> bool:
        """Whether the model has the element (and so leaves R(N_u)·I out)."""
        return bool(self.thresholds_c) or self.series_ohm != 0.0

    def to_mapping(self) -> dict[str, Any]:
        """The TOML table ``[hysteresis]`` (JSON-ready)."""
        return {"thresholds_c": [float(v) for v in self.thresholds_c],
                "weights_v_per_c": [float(v) for v in self.weights_v_per_c],
                "series_ohm": float(self.series_ohm), "nu_ref_n_per_v": float(self.nu_ref_n_per_v)}

    def to_toml_lines(self) -> list[str]:
        """``[hysteresis]`` as TOML lines."""
        return ["[hysteresis]"] + [f"{k} = {v!r}" for k, v in self.to_mapping().items()]

    @classmethod
    def from_mapping(cls, values: Any) -> Hysteresis:
        """From the TOML table ``[hysteresis]``; raises ParameterError."""
        if not isinstance(values, Mapping):
            raise ParameterError("[hysteresis] must be a table")
        known = {"thresholds_c", "weights_v_per_c", "series_ohm", "nu_ref_n_per_v"}
        unknown = set(values) - known
        if unknown:
            raise ParameterError(f"unknown hysteresis parameter(s): {', '.join(sorted(unknown))} "
                                 f"(known: {', '.join(sorted(known))})")
        kw: dict[str, Any] = dict(values)
        for name in ("thresholds_c", "weights_v_per_c"):
            v = kw.get(name, [])
            if not isinstance(v, (list, tuple)):
                raise ParameterError(f"[hysteresis] {name} must be a list of numbers")
            kw[name] = tuple(v)
        return cls(**kw)


NO_HYSTERESIS = Hysteresis()


@njit(cache=True, nogil=True)
def play_sum_into(current: np.ndarray, h: float, thresholds: np.ndarray, weights: np.ndarray, out: np.ndarray) -> None:
    """``out`` (N,) = Σ_i w_i play_{r_i}[Q] of the charge ``Q`` integrated from ``current`` (N,) by the
    trapezoidal rule with step ``h`` from rest at sample 0, in consistent units (A, s, C, V/C -> V; or
    A, µs, µC, V/µC -> V). Each play starts at 0: y_k = max(Q_k - r, min(Q_k + r, y_{k-1}))."""
    n = current.shape[0]
    m = thresholds.shape[0]
    y = np.zeros(m)
    q = 0.0
    for k in range(n):
        if k > 0:
            q += 0.5 * h * (current[k - 1] + current[k])
        s = 0.0
        for i in range(m):
            yi = min(q + thresholds[i], y[i])
            yi = max(q - thresholds[i], yi)
            y[i] = yi
            s += weights[i] * yi
        out[k] = s


def temperature_scale(hysteresis: Hysteresis, r0b_v_per_n: float, nu_n_per_v: float) -> float:
    """s(N_u) = R(N_u) / R(N_ref) = exp(-R_0b (N_u - N_ref)), the element's scale at ``nu_n_per_v``."""
    return math.exp(-r0b_v_per_n * (nu_n_per_v - hysteresis.nu_ref_n_per_v))


def element_voltage(hysteresis: Hysteresis, r0b_v_per_n: float, current_a: np.ndarray, dt_s: float,
                    nu_n_per_v: float) -> np.ndarray:
    """The element's share of the terminal voltage (V) for the actuator current ``current_a`` (A) sampled
    every ``dt_s`` s from the start of charging: ``R_s·I + s(N_u)·H[Q]`` (zeros without the element)."""
    cur = np.ascontiguousarray(current_a, dtype=float)
    out = np.zeros(cur.size)
    if not hysteresis.present:
        return out
    play_sum_into(cur, float(dt_s), np.array(hysteresis.thresholds_c, dtype=float),
                  np.array(hysteresis.weights_v_per_c, dtype=float), out)
    result: np.ndarray = temperature_scale(hysteresis, r0b_v_per_n, nu_n_per_v) * out + hysteresis.series_ohm * cur
    return result
