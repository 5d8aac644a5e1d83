"""Calibration (eq. 25): the shared PSA parameters p = [k_p, k_s, R_b] and, per trace j, N_u,j and R_j.

From M traces of an actuator without valve at different temperatures, with the voltage and the
bottom plate displacement s3 measured, minimise

    sum_j ∫_0^t1 |U_m,j − y_j| + γ |s3m,j − s3_j| dt

then fit N_u(T) linear, R(T) exponential and R(N_u) = R0a exp(−R0b N_u) (eq. 22, Fig. 6).
Solved in two stages: least squares (scipy ``least_squares``, bounded, scaled variables) to get
into the basin quickly, then the paper's absolute-error cost polished with Powell's method.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares, minimize

from estimator.ident.fit.cost import trapezoid_weights
from estimator.ident.measurement import Injection
from estimator.model.drive import sample_count
from estimator.model.parameters import InjectorParameters, load_nominal
from estimator.model.psa_lti import simulate_psa
from estimator.units import MEGA, PER_MICRO, US_PER_S

DEFAULT_GAMMA_V_PER_M = 1e6   # 1 µm of displacement error weighs like 1 V of voltage error


@dataclass(frozen=True)
class CalibrationTrace:
    """One calibration measurement: the injection (I, U), the measured s3 (m) and the temperature (degC)."""

    injection: Injection
    s3_m: np.ndarray
    temperature_c: float


@dataclass(frozen=True)
class CalibrationResult:
    """Identified parameters and the fitted temperature laws (SI units)."""

    kp_n_per_m: float
    ks_n_per_m: float
    rb_v2s_per_mn: float
    nu_n_per_v: np.ndarray      # (M,)
    r_ohm: np.ndarray           # (M,)
    temperature_c: np.ndarray   # (M,)
    cost: float                 # eq. 25 cost, V*s
    nu_of_t: tuple[float, float]    # N_u(T) = a + b T   (N/V, N/V/degC)
    r_of_t: tuple[float, float]     # R(T) = c exp(d T)  (Ohm, 1/degC)
    r0a_ohm: float
    r0b_v_per_n: float
    evaluations: int

    def params(self, base: InjectorParameters) -> InjectorParameters:
        """``base`` with the calibrated PSA values."""
        psa = replace(base.psa, kp_n_per_m=self.kp_n_per_m, ks_n_per_m=self.ks_n_per_m,
                      rb_v2s_per_mn=self.rb_v2s_per_mn, r0a_ohm=self.r0a_ohm, r0b_v_per_n=self.r0b_v_per_n)
        return InjectorParameters(psa, base.valve)


def _unpack(theta: np.ndarray, base: InjectorParameters,
            m: int) -> tuple[float, float, float, np.ndarray, np.ndarray]:
    kp = base.psa.kp_n_per_m * theta[0]
    ks = base.psa.ks_n_per_m * theta[1]
    rb = base.psa.rb_v2s_per_mn * theta[2]
    nu = 16.0 * theta[3:3 + m]
    r = np.exp(theta[3 + m:3 + 2 * m])
    return kp, ks, rb, nu, r


def calibrate(traces: list[CalibrationTrace], base: InjectorParameters | None = None, window_s: float = 170e-6,
              gamma_v_per_m: float = DEFAULT_GAMMA_V_PER_M, polish_l1: bool = True) -> CalibrationResult:
    """Solve eq. 25 for the traces (at least two temperatures for the temperature laws)."""
    if len(traces) < 2:
        raise ValueError("calibration needs at least two traces (temperatures)")
    if len({float(t.temperature_c) for t in traces}) < 2:
        raise ValueError("calibration needs traces at two or more different temperatures (eq. 25's laws N_u(T), R(T))")
    if not (math.isfinite(window_s) and 20e-6 <= window_s <= 2e-3):
        raise ValueError(f"window {window_s * US_PER_S:g} µs must be within 20..2000 µs")
    if not (math.isfinite(gamma_v_per_m) and gamma_v_per_m > 0):
        raise ValueError(f"gamma {gamma_v_per_m!r} V/m must be a positive number")
    base = base or load_nominal()
    m = len(traces)
    wide = replace(base.psa, nu_min_n_per_v=1.0, nu_max_n_per_v=100.0)
    sets = []
    for tr in traces:
        inj = tr.injection
        prob = inj.problem()
        if prob:
            raise ValueError(f"calibration trace at {tr.temperature_c} degC: {prob}")
        k = min(inj.n, sample_count(window_s, inj.dt_s))
        sets.append((inj.current_a[:k], inj.voltage_v[:k], tr.s3_m[:k], inj.dt_s, trapezoid_weights(k, inj.dt_s)))
    evals = 0

    def residual_parts(theta: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        nonlocal evals
        kp, ks, rb, nu, r = _unpack(theta, base, m)
        p = InjectorParameters(replace(wide, kp_n_per_m=kp, ks_n_per_m=ks, rb_v2s_per_mn=rb), base.valve)
        out = []
        for j, (cur, u, s3, dt, w) in enumerate(sets):
            y, x5 = simulate_psa(p, nu[j], r[j], cur, dt)
            out.append((u - y, gamma_v_per_m * (s3 - x5), w))
            evals += 1
        return out

    def lsq(theta: np.ndarray) -> np.ndarray:
        return np.concatenate([np.concatenate([eu * np.sqrt(w), es * np.sqrt(w)]) for eu, es, w in residual_parts(theta)])

    def l1(theta: np.ndarray) -> float:
        return float(sum((np.abs(eu) + np.abs(es)) @ w for eu, es, w in residual_parts(theta)))

    theta0 = np.concatenate([[1.0, 1.0, 1.0], np.full(m, 1.0), np.zeros(m)])
    lo = np.concatenate([[0.3, 0.3, 0.05], np.full(m, 0.5), np.full(m, -8.0)])
    hi = np.concatenate([[3.0, 3.0, 20.0], np.full(m, 2.0), np.full(m, 3.0)])
    sol = least_squares(lsq, theta0, bounds=(lo, hi), x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12,
                        max_nfev=2000)
    theta = sol.x
    if polish_l1:
        pol = minimize(l1, theta, method="Powell", bounds=list(zip(lo, hi)),
                       options={"xtol": 1e-7, "ftol": 1e-10, "maxfev": 4000})
        if pol.fun <= l1(theta):
            theta = pol.x
    kp, ks, rb, nu, r = _unpack(theta, base, m)
    temps = np.array([t.temperature_c for t in traces], dtype=float)
    if np.ptp(temps) > 0:
        b, a = np.polyfit(temps, nu, 1)
        d, logc = np.polyfit(temps, np.log(r), 1)
    else:
        a, b, logc, d = float(np.mean(nu)), 0.0, float(np.mean(np.log(r))), 0.0
    r0a, r0b = base.psa.r0a_ohm, base.psa.r0b_v_per_n
    if np.ptp(nu) > 1e-9:
        slope, intercept = np.polyfit(nu, np.log(r), 1)
        if not (abs(intercept) < 700):
            raise ValueError(f"the traces do not determine R(N_u) (ln R0a = {intercept:.3g}); are they at "
                             "different temperatures of one injector?")
        r0a, r0b = math.exp(intercept), -slope
    return CalibrationResult(kp, ks, rb, nu, r, temps, l1(theta), (float(a), float(b)), (math.exp(logc), float(d)),
                             float(r0a), float(r0b), evals)


def to_toml(result: CalibrationResult, base: InjectorParameters) -> str:
    """The calibrated parameter set as a TOML file in the layout of ``parameters.toml``."""
    return result.params(base).to_toml(
        "PSA parameters calibrated with eq. 25 (python -m estimator calibrate); SI units.\n"
        f"N_u(T) = {result.nu_of_t[0]:.5f} + {result.nu_of_t[1]:.6f} * T [N/V, T in degC]\n"
        f"R(T) = {result.r_of_t[0]:.5f} * exp({result.r_of_t[1]:.6f} * T) [Ohm]")


def report(result: CalibrationResult) -> str:
    """Human-readable summary, like Table 1 plus the per-temperature values of Fig. 6."""
    lines = ["calibration (eq. 25)",
             f"  k_p = {result.kp_n_per_m / MEGA:.3f} 10^6 N/m   k_s = {result.ks_n_per_m / MEGA:.3f} 10^6 N/m   "
             f"R_b = {result.rb_v2s_per_mn:.4f} V^2 s/(m N)",
             f"  R(N_u) = {result.r0a_ohm:.2f} Ohm * exp(-{result.r0b_v_per_n:.4f} V/N * N_u)",
             f"  N_u(T) = {result.nu_of_t[0]:.4f} + {result.nu_of_t[1]:.5f} T   R(T) = {result.r_of_t[0]:.4f} exp({result.r_of_t[1]:.5f} T)",
             f"  cost {result.cost * PER_MICRO:.2f} µV·s over all traces, {result.evaluations} simulations",
             f"  {'T [degC]':>9} {'N_u [N/V]':>10} {'R [Ohm]':>9}"]
    for t, nu, r in zip(result.temperature_c, result.nu_n_per_v, result.r_ohm):
        lines.append(f"  {t:>9.1f} {nu:>10.4f} {r:>9.4f}")
    return "\n".join(lines)
