"""The simulated injector plant: true hybrid dynamics plus what a real amplifier's ADC adds.

The plant runs on a grid ``oversample`` times finer than the measurement (so the chopper ripple and
contact events are resolved independently of the estimator's 0.5 µs grid), then the ADC samples
it: Gaussian noise, 12-bit quantisation over a stated range, clipping.

Mismatch option: a real actuator's voltage is not R(N_u)·I on top of the linear
model but a rate-independent hysteresis of the charge, H[Q], as in Goldfarb & Celanovic (paper
section 3.2), plus the resistance of cables and amplifier output stage. With ``mismatch`` the
plant's voltage is ``U_linear + H[Q] + R_s·I`` where H is a Prandtl–Ishlinskii operator (a weighted
sum of play operators), sized so that the best-adapted model is off by about ±2 V (Fig. 7).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from estimator._compiled import njit
from estimator.model.chain import NO_CHAIN, MeasurementChain
from estimator.model.drive import SAMPLE_PERIOD_S, ChopperRipple, Drive, StandardDrive, sample_count, sample_times
from estimator.model.fast_sim import PLATEAU_WINDOW_S, FastSimulator
from estimator.model.parameters import NOMINAL_PRELOAD_N, InjectorParameters

# Prandtl–Ishlinskii operator of the mismatch plant: thresholds in C, weights in V/C. The paper
# (section 3.3) replaces the rising branch of H[Q] by R(N_u)·I: for a trapezoidal charge, H rises
# steeply while the current ramps up and then flattens. These weights give that concave loading
# curve (slopes 110, 60, 30, 10, 5, 4, 3 kV/C between the thresholds; about 4 V at 0.06 mC, 5.5 V at
# 0.35 mC) at the reference temperature, and the whole operator scales with R(N_u)/R(N_REF) as the
# hysteresis shrinks with temperature (Fig. 6). Sized so the adapted model is off by about ±2 V.
PI_THRESHOLDS_C = (0.0, 0.02e-3, 0.04e-3, 0.06e-3, 0.1e-3, 0.2e-3, 0.35e-3)
PI_WEIGHTS_V_PER_C = (110e3, -50e3, -30e3, -20e3, -5e3, -1e3, -1e3)
PI_NU_REF_N_PER_V = 16.39
SERIES_RESISTANCE_OHM = 0.2


@njit(cache=True)
def play_operator(q: np.ndarray, r: float, y0: float = 0.0) -> np.ndarray:
    """Backlash (play) operator of half-width r on the sequence q: y = max(q - r, min(q + r, y_prev))."""
    y = np.empty_like(q)
    prev = y0
    for k in range(q.shape[0]):
        prev = max(q[k] - r, min(q[k] + r, prev))
        y[k] = prev
    return y


def pi_hysteresis(q: np.ndarray, thresholds=PI_THRESHOLDS_C, weights=PI_WEIGHTS_V_PER_C) -> np.ndarray:
    """Prandtl–Ishlinskii operator H[Q] = sum_i w_i play_{r_i}[Q] in V (Q in C, from rest at 0)."""
    return sum(w * play_operator(q, r) for r, w in zip(thresholds, weights))


# Bouc–Wen hysteresis of the charge, a shape no sum of plays the estimator learns is built from: dz = (A -
# (beta sign(dQ z) + gamma) |z|) dQ (exponent 1), the voltage K z. Sized like the Prandtl–Ishlinskii
# operator above: about 4 V at 0.06 mC and 5.5 V at 0.35 mC on the rising branch.
BW_A_V_PER_C, BW_BETA_PER_C, BW_GAMMA_PER_C = 110e3, 12e3, 8e3


@njit(cache=True)
def bouc_wen_hysteresis(q: np.ndarray, a: float = BW_A_V_PER_C, beta: float = BW_BETA_PER_C,
                        gamma: float = BW_GAMMA_PER_C) -> np.ndarray:
    """The Bouc–Wen state z (V) along the charge sequence ``q`` (C), from rest, in small steps."""
    out = np.empty_like(q)
    z = 0.0
    out[0] = 0.0
    for k in range(1, q.shape[0]):
        dq = q[k] - q[k - 1]
        z += (a - (beta * np.sign(dq * z) + gamma) * abs(z)) * dq
        out[k] = z
    return out


HYSTERESIS_SHAPES = ("prandtl-ishlinskii", "bouc-wen")


@dataclass(frozen=True)
class AdcConfig:
    """ADC of the amplifier: noise (1 sigma), bits and input range of each channel."""

    voltage_noise_v: float = 0.1
    current_noise_a: float = 0.01
    bits: int = 12
    voltage_range_v: tuple[float, float] = (-50.0, 250.0)
    current_range_a: tuple[float, float] = (-20.0, 20.0)

    def quantise(self, x: np.ndarray, rng_lo_hi: tuple[float, float]) -> np.ndarray:
        """Round to the ADC grid of ``bits`` over the range and clip to it."""
        lo, hi = rng_lo_hi
        if self.bits <= 0:
            return np.clip(x, lo, hi)
        lsb = (hi - lo) / (2 ** self.bits - 1)
        return lo + np.round((np.clip(x, lo, hi) - lo) / lsb) * lsb


@dataclass(frozen=True)
class PlantConfig:
    """Everything about the simulated measurement except N_u, L_h and F_open."""

    adc: AdcConfig = field(default_factory=AdcConfig)
    window_s: float = 100e-6             # sent/measured window from the start of charging
    dt_s: float = SAMPLE_PERIOD_S        # measurement sample period
    oversample: int = 4                  # plant grid = dt / oversample
    drive: Drive = field(default_factory=StandardDrive)   # the commanded current (a scenario's drive)
    ripple_a: float = 0.15               # chopper ripple amplitude (triangle, peak) while charging
    ripple_period_s: float = 8e-6        # chopper period
    mismatch: bool = False               # hysteresis H[Q] + series resistance instead of R(N_u) I
    hysteresis_gain: float = 1.0         # with mismatch: H[Q] times this
    hysteresis_shape: str = "prandtl-ishlinskii"   # with mismatch: H's form (HYSTERESIS_SHAPES)
    chain: MeasurementChain = NO_CHAIN   # the amplifier's anti-aliasing filters and I/U skew

    def amplifier(self, drive: Drive, phase: float) -> Drive:
        """What the amplifier delivers for the commanded ``drive``: it plus the chopper ripple at ``phase``."""
        return ChopperRipple(drive, self.ripple_a, self.ripple_period_s, phase)


@dataclass(frozen=True)
class Measurement:
    """One simulated injection: what the ADC delivers and the plant's truth."""

    current_a: np.ndarray
    voltage_v: np.ndarray
    dt_s: float
    f_open_n: float
    nu_n_per_v: float
    lh_m: float
    t_contact_s: float
    t_open_s: float
    stroke_m: float            # mean plunger stroke over 215-490 µs, window current then hold
    clean_voltage_v: np.ndarray


def true_current(t_s: np.ndarray, cfg: PlantConfig, phase: float = 0.0) -> np.ndarray:
    """What the amplifier delivers at ``t_s`` (s): the configured drive plus the chopper ripple (A)."""
    return cfg.amplifier(cfg.drive, phase).current(t_s)


class Plant:
    """Simulates measured injections; one instance per plant grid (it caches transition matrices).

    ``params``: the injector's true structural parameters (default Tables 1-2; a series part's own,
    see :mod:`sim_bench.hardware.series_part`)."""

    def __init__(self, cfg: PlantConfig | None = None, params: InjectorParameters | None = None) -> None:
        self.cfg = cfg or PlantConfig()
        self.sim = FastSimulator(params, dt_s=self.cfg.dt_s / self.cfg.oversample)

    def warm_up(self) -> None:
        """One throw-away simulation: loads the compiled kernels before real-time work starts."""
        self.measure(17.0, 3e-6, NOMINAL_PRELOAD_N, np.random.default_rng(0))

    def measure(self, nu_n_per_v: float, lh_m: float, f_open_n: float, rng: np.random.Generator,
                drive: Drive | None = None) -> Measurement:
        """One injection with truth, driven by the configured drive (or ``drive``: a corrected one) plus
        the amplifier's ripple."""
        cfg = self.cfg if drive is None else replace(self.cfg, drive=drive)
        m = cfg.oversample
        # simulate long enough for the plateau stroke and the whole window: the window's current, then
        # held (zero current)
        t_fine = sample_times(max(PLATEAU_WINDOW_S[1], cfg.window_s), self.sim.dt_s)
        phase = float(rng.uniform())
        cur = true_current(t_fine, cfg, phase)
        cur = np.where(t_fine <= cfg.window_s + 1e-12, cur, 0.0)
        res = self.sim.simulate(cur, nu_n_per_v, lh_m, f_open_n, exact=True)
        if not res.success[0]:
            raise ValueError(f"plant simulation failed: {res.message[0]}")
        u = res.voltage_v[0]
        if cfg.mismatch:
            q = np.concatenate(([0.0], np.cumsum(0.5 * (cur[1:] + cur[:-1]) * self.sim.dt_s)))
            psa = self.sim.params.psa
            r_model = psa.resistance_ohm(nu_n_per_v)
            scale = r_model / psa.resistance_ohm(PI_NU_REF_N_PER_V)
            h = bouc_wen_hysteresis(q) if cfg.hysteresis_shape == "bouc-wen" else pi_hysteresis(q)
            u = u - r_model * cur + cfg.hysteresis_gain * scale * h + SERIES_RESISTANCE_OHM * cur
        if not cfg.chain.identity:
            cur, u = cfg.chain.apply(cur, u, self.sim.dt_s)
        n_meas = sample_count(cfg.window_s, cfg.dt_s)
        idx = np.arange(n_meas) * m
        clean_u, clean_i = u[idx], cur[idx]
        adc = cfg.adc
        meas_u = adc.quantise(clean_u + adc.voltage_noise_v * rng.standard_normal(n_meas), adc.voltage_range_v)
        meas_i = adc.quantise(clean_i + adc.current_noise_a * rng.standard_normal(n_meas), adc.current_range_a)
        return Measurement(meas_i, meas_u, cfg.dt_s, f_open_n, nu_n_per_v, lh_m, float(res.t_contact_s[0]),
                           float(res.t_open_s[0]), float(res.plateau_stroke_m()[0]), clean_u)
