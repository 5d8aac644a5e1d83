"""Electrical calibration: an injector's own structural parameters from its own current and voltage.

Tables 1-2 describe one laboratory's injector; a series part's masses and stiffnesses differ by
5-15 %, which moves the idle-stroke estimate by micrometres. No displacement sensor is needed to learn
them: a batch of injections at different preload forces and coupling factors carries the
information in the voltage alone. This module fits, by bounded least squares
(:func:`~estimator.ident.fit.levenberg_marquardt.least_squares_lm`),

- the shared structural parameters ``theta`` as relative factors on the base parameter set (default
  the thirteen of :data:`~estimator.model.parameters.STRUCTURAL`), each with a Gaussian prior of
  relative standard deviation ``tolerance`` at its base value, so that what a batch does not excite
  stays near the tables instead of wandering, and
- each injection's own N_u (N/V) and L_h (µm),

to the voltage over each injection's first ``window_s``, each sample weighted by that injection's
noise level (estimated from the residual of a nominal fit). The Jacobian is built in batches: one
simulator per perturbed parameter set simulates every injection, and each injection's own two
columns are one batched simulation.

The simulated voltage is driven by the *measured* current, whose noise reaches it through the
actuator's direct feedthrough R(N_u) I (eq. 22): an errors-in-variables problem. The fit lowers
that noise's share of the residual by smoothing it, with a U filter and an equal I skew that cancel
in timing (about 0.1 µs each at 0.01 A of current noise: four to five of their noise-only standard
deviations). The share is known, ``n sigma_I^2 R(N_u)^2 G`` per injection (``G`` the chain's noise
gain, :func:`noise_gain`; ``sigma_I`` from the current's own second differences, :func:`current_noise_a`),
so is the pull of its gradient on every parameter (``(J'J)^-1`` times half of it): the reported
covariance includes that pull as a bias, ``b b'``. (Subtracting the share from the cost instead
moved some batches into another of its minima.)

The result reports each parameter with its standard deviation (from the Gauss-Newton matrix, prior
included), the pairs whose correlation exceeds 0.9, the parameters the batch hardly informs (posterior
standard deviation above 70 % of the prior's), and the RMS voltage residual before (nominal
parameters, each injection fitted alone) and after.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field, fields, replace

import numpy as np

from estimator.errors import EstimatorError
from estimator.ident.config import IdentConfig
from estimator.ident.fit.adequacy import current_noise_a, noise_level_v, structure_z
from estimator.ident.fit.idle_stroke import identify, predict_valve
from estimator.ident.fit.levenberg_marquardt import LeastSquaresResult, least_squares_lm
from estimator.ident.measurement import Injection
from estimator.model.chain import MeasurementChain, lowpass, shift
from estimator.model.fast_sim import FastSimulator
from estimator.model.hysteresis import Hysteresis, element_voltage
from estimator.model.parameters import STRUCTURAL, CalibrationUncertainty, InjectorParameters, load_nominal, scaled
from estimator.units import M_PER_UM, S_PER_US, UM_PER_M, US_PER_S

WINDOW_S = 200e-6          # the Fisher analysis behind this module used 0-200 µs of the charge
FD_THETA = 1e-3            # relative step of a structural factor's finite difference
FD_NU, FD_LH_UM = 2e-3, 2e-3
WEAK_FRACTION = 0.7        # posterior sd above this fraction of the prior sd: the batch hardly informs it
CORRELATED = 0.9
SIMULATORS_KEPT = 16
NU_STEP = 0.5              # N/V: a coarser table than the estimator's (voltage error ≤ 2e-4 V), 20x cheaper to build
RESTART_Z = 4.0            # an injection's smooth residual this many sd above noise: try another start
MISFIT_Z = 8.0             # ... and this many after the restarts: the model does not explain the batch. Measured on
                           # 120 seeded good batches (parts within ±10 %, with and without a chain, wandering preload,
                           # warm-up, wear): largest 5.2, 99th percentile 4.8; hysteresis parts 1,000-6,000
NU_EDGE_N_PER_V = 0.01     # a fitted N_u this close to its range's edge presses on it (:func:`_widened`)
RESTART_SEED = 20261124    # restarts from a local minimum are seeded: the same traces give the same parameters
STRUCTURAL_NAMES = tuple(f"{table}.{name}" for table, name in STRUCTURAL)   # what is fitted by default
BOUND_SDS = 4.0            # a structural factor is bounded to this many prior standard deviations
# the learned element's play half-widths (C), roughly geometric over a stack's charge: fewer plays leave a
# shape error that the structure absorbs into L_h (docs/design.md)
HYSTERESIS_THRESHOLDS_C = tuple(v * 1e-3 for v in (0.0, 0.005, 0.01, 0.015, 0.02, 0.03, 0.04, 0.05, 0.065, 0.08, 0.1,
                                                    0.13, 0.17, 0.23, 0.3))
WEIGHT_UNIT_V_PER_C = 1e3  # the element's weights are fitted in V/mC (the plant's: 2-110 V/mC)
WEIGHT_PRIOR_SD = 200.0    # V/mC: wide (a prior only to keep a weight the batch does not inform finite)
WEIGHT_BOUND = 2000.0      # V/mC
SERIES_PRIOR_SD_OHM, SERIES_BOUNDS_OHM = 1.0, (0.0, 5.0)
ELEMENT_START_ROUNDS = 2   # the element's least-squares start, each round with the injections identified again
CHAIN_NAMES = ("u_filter_tau_s", "i_skew_s")   # the measurement chain's parameters fitted with fit_chain
CHAIN_PRIOR_SD_US = 1.0    # prior standard deviation of each (µs), at the base chain's value
CHAIN_BOUNDS_US = {"u_filter_tau_s": (0.0, 3.0), "i_skew_s": (-2.0, 2.0)}
FD_CHAIN_US = 0.01
RESPONSE_THETA, RESPONSE_NU, RESPONSE_LH_UM = 0.01, 0.05, 0.02   # steps differentiating the valve's motion
                           # (log factor, N/V, µm): coarser than the fit's, as the motion is sampled in time
OUTLIER_FACTOR = 5.0       # an injection's motion σ counts at most this many times the batch's median
GAIN_TAPS = 64             # samples of the chain's impulse response summed by noise_gain (a 3 µs filter: 6)


@dataclass
class ElectricalCalibration:
    """What :func:`calibrate_electrical` found.

    Attributes
    ----------
    params : the calibrated parameter set.
    names : the fitted structural parameters ("psa.kp_n_per_m", ...).
    factors : each one's value over the base value.
    sigma_rel : each one's standard deviation, relative to its value.
    nu_n_per_v, lh_um : each injection's fitted N_u (N/V) and L_h (µm).
    rms_before_v, rms_after_v : RMS voltage residual (V) with the base parameters (each injection fitted
        alone) and with the calibrated ones.
    correlated : (name, name, correlation) of the pairs beyond 0.9 in magnitude.
    weak : parameters the batch hardly informs (they stay near the prior).
    warnings : readable lines about the batch (e.g. one preload force only).
    evaluations : simulations run.
    adequate : the calibrated model explains the batch (its residual is white noise within
        :data:`MISFIT_Z` standard deviations); a calibration that is not must not be used.
    misfit_z : that statistic.
    chain_sigma_us : standard deviation (µs) of each fitted measurement-chain parameter (its value is in
        ``params.chain``); empty if the chain was not fitted.
    sigma_nu_n_per_v, sigma_lh_um : each injection's standard deviation of N_u (N/V) and L_h (µm), the
        structure's uncertainty included.
    chi2 : the fit's cost, samples over their noise and the prior included (chi-square units).
    solution : the fitted unknowns (log factors, chain µs, the hysteresis element's, each injection's N_u
        and L_h), to start from.
    hysteresis : fitted with a hysteresis element in place of R(N_u)·I (its parameters in ``params``).
    refusal : why a calibration that fits is still not adequate ("" when the misfit says it, or it is).
    """

    params: InjectorParameters
    names: tuple[str, ...]
    factors: np.ndarray
    sigma_rel: np.ndarray
    nu_n_per_v: np.ndarray
    lh_um: np.ndarray
    rms_before_v: float
    rms_after_v: float
    correlated: list[tuple[str, str, float]] = field(default_factory=list)
    weak: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    evaluations: int = 0
    adequate: bool = True
    misfit_z: float = 0.0
    chain_sigma_us: dict[str, float] = field(default_factory=dict)
    sigma_nu_n_per_v: np.ndarray = field(default_factory=lambda: np.zeros(0))
    sigma_lh_um: np.ndarray = field(default_factory=lambda: np.zeros(0))
    chi2: float = float("nan")
    solution: np.ndarray = field(default_factory=lambda: np.zeros(0))
    hysteresis: bool = False
    refusal: str = ""

    def to_dict(self) -> dict[str, object]:
        """JSON-ready: each fitted parameter's factor and relative sigma, the chain, the residuals and
        the verdict (units in the keys)."""
        return {"adequate": self.adequate, "misfit_z": round(self.misfit_z, 3),
                "rms_before_v": self.rms_before_v, "rms_after_v": self.rms_after_v,
                "parameters": {n: {"factor": float(f), "sigma_rel": float(sd)}
                               for n, f, sd in zip(self.names, self.factors, self.sigma_rel)},
                "chain_us": {n: getattr(self.params.chain, n) * US_PER_S for n in self.chain_sigma_us},
                "chain_sigma_us": dict(self.chain_sigma_us), "weak": list(self.weak), "warnings": list(self.warnings),
                "hysteresis": self.params.hysteresis.to_mapping() if self.hysteresis else None,
                "injections": [{"nu_n_per_v": float(nu), "lh_um": float(lh)} for nu, lh in zip(self.nu_n_per_v, self.lh_um)]}

    def report(self) -> str:
        """A table of the parameters, the residual before and after, and the warnings."""
        lines = [f"electrical calibration of {len(self.nu_n_per_v)} injections: RMS voltage residual "
                 f"{self.rms_before_v * 1e3:.1f} mV with the base parameters, {self.rms_after_v * 1e3:.1f} mV after",
                 f"  {'parameter':<22} {'factor':>8} {'sd [%]':>7}"]
        for n, f, s in zip(self.names, self.factors, self.sigma_rel):
            lines.append(f"  {n:<22} {f:8.4f} {100 * s:7.2f}{'  (weakly informed: stays near the prior)' if n in self.weak else ''}")
        cal = self.params.calibration
        lines.append(f"  uncertainty left in every estimate with these parameters: N_u {100 * cal.nu_rel_sigma:.3f} %, "
                     f"L_h {cal.lh_sigma_m * UM_PER_M:.3f} µm (1 sigma; in the parameter file's [calibration])")
        lines.append(f"  ... and in the valve's predicted motion: stroke {100 * cal.stroke_rel_sigma:.3f} %, opening "
                     f"instant {cal.opening_sigma_s * US_PER_S:.3f} µs")
        for n, sd in self.chain_sigma_us.items():
            lines.append(f"  chain.{n:<16} {getattr(self.params.chain, n) * US_PER_S:8.3f} µs, sd {sd:.3f} µs")
        if self.hysteresis:
            h = self.params.hysteresis
            lines.append(f"  hysteresis element in place of R(N_u)·I: {len(h.thresholds_c)} plays up to "
                         f"{max(h.thresholds_c) * 1e3:.2f} mC, series resistance {h.series_ohm:.3f} Ohm "
                         "(in the parameter file's [hysteresis])")
        for a, b, c in self.correlated:
            lines.append(f"  correlation {a} / {b}: {c:+.2f}")
        lines += [f"  injection {k}: N_u {nu:.4f} N/V, L_h {lh:.3f} µm"
                  for k, (nu, lh) in enumerate(zip(self.nu_n_per_v, self.lh_um))]
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


class _Simulators:
    """Simulators per parameter vector (their tables cost ≈ 45 ms each), the most recent kept."""

    def __init__(self, base: InjectorParameters, names: tuple[str, ...], dt_s: float) -> None:
        self.base, self.names, self.dt_s = base, names, dt_s
        self._kept: OrderedDict[bytes, FastSimulator] = OrderedDict()

    def params(self, theta: np.ndarray) -> InjectorParameters:
        return scaled(self.base, {n: math.exp(t) for n, t in zip(self.names, theta)})

    def __call__(self, theta: np.ndarray) -> FastSimulator:
        key = np.asarray(theta, dtype=float).tobytes()
        sim = self._kept.get(key)
        if sim is None:
            sim = FastSimulator(self.params(theta), self.dt_s, nu_step=NU_STEP)
            self._kept[key] = sim
            if len(self._kept) > SIMULATORS_KEPT:
                self._kept.popitem(last=False)
        else:
            self._kept.move_to_end(key)
        return sim


@dataclass
class _Batch:
    """A calibration's batch as the fit sees it: the usable injections cut to the window, their sample
    period, and the measurement chain they are seen through (``fit_chain``: its parameters are fitted)."""

    injections: list[Injection]
    dt_s: float
    chain: MeasurementChain
    fit_chain: bool


def _batch(injections: list[Injection], base: InjectorParameters, names: tuple[str, ...], tolerance: float,
           window_s: float, fit_chain: bool) -> _Batch:
    """The batch checked (ValueError naming what is wrong) and cut to ``window_s``."""
    if not (isinstance(tolerance, (int, float)) and 0.0 < tolerance <= 1.0):
        raise ValueError(f"tolerance {tolerance!r} must be a relative standard deviation in (0, 1]")
    if not (20e-6 <= window_s <= 2e-3):
        raise ValueError(f"window {window_s * US_PER_S:.1f} µs must be within 20..2000 µs")
    known = {f"psa.{f.name}" for f in fields(base.psa)} | {f"valve.{f.name}" for f in fields(base.valve)}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ValueError(f"unknown structural parameter(s) {', '.join(unknown)}")
    usable, corrected = usable_injections(injections, base.chain)
    if len(usable) < 2:
        raise ValueError(f"an electrical calibration needs at least two usable injections, got {len(usable)}")
    if len({round(inj.dt_s, 12) for inj in usable}) > 1:
        raise ValueError("the injections of one calibration must share their sample period")
    chain = base.chain
    if corrected:   # the chain already undone: nothing left to model
        chain, fit_chain = MeasurementChain(), False
    return _Batch([inj.window(window_s) for inj in usable], usable[0].dt_s, chain, fit_chain)


def usable_injections(injections: list[Injection], chain: MeasurementChain) -> tuple[list[Injection], bool]:
    """The injections a calibration fits, in order: those without a problem, all put through ``chain``
    (the base's measurement chain) when any of them comes with the chain already undone; and whether
    that was so. A calibration's per-injection N_u and L_h are indexed by this list."""
    usable = [inj for inj in injections if not inj.problem()]
    corrected = any(inj.chain_corrected for inj in usable)
    return ([inj.through_chain(chain) for inj in usable] if corrected else usable), corrected


class _Problem:
    """The calibration's least-squares problem over one batch.

    The unknowns ``x``: the ``k`` structural log factors, the ``nc`` chain parameters (µs; up to ``q =
    k + nc``), with ``hysteresis`` the element's ``nh`` weights (V/mC) and series resistance (Ω; ``p =
    q + nh`` shared ones), then each injection's N_u (N/V) and L_h (µm). The residual is every sample's
    voltage error over its injection's noise level, then the shared parameters' prior. The element
    (:mod:`estimator.model.hysteresis`) adds to the voltage only, linearly in its parameters: its
    voltage is computed here from each injection's actuator current, the simulators carrying an element
    of zero weights so that they leave R(N_u)·I out.
    """

    def __init__(self, batch: _Batch, base: InjectorParameters, names: tuple[str, ...], tolerance: float,
                 limits: dict[str, tuple[float, float]] | None, thresholds_c: tuple[float, ...] = ()) -> None:
        self.batch, self.names = batch, names
        self.usable = batch.injections
        self.n_win = [inj.n for inj in self.usable]
        self.k, self.b = len(names), len(self.usable)
        self.chain_names = CHAIN_NAMES if batch.fit_chain else ()
        self.nc = len(self.chain_names)
        self.q = self.k + self.nc
        hysteresis = bool(thresholds_c)
        self.element = Hysteresis(thresholds_c, (0.0,) * len(thresholds_c)) if hysteresis \
            else base.hysteresis     # a configured element, if any, is the simulators' own
        self.nh = len(self.element.thresholds_c) + 1 if hysteresis else 0
        self.p = self.q + self.nh
        self.c_base = np.array([getattr(batch.chain, n) * US_PER_S for n in self.chain_names])
        # the element's start: no hysteresis and R(N_u) I at the reference N_u as the series resistance
        self.h_base = np.array([0.0] * (self.nh - 1) + [base.psa.resistance_ohm(self.element.nu_ref_n_per_v)]) \
            if hysteresis else np.zeros(0)
        self.sims = _Simulators(replace(base, chain=MeasurementChain(), hysteresis=self.element), names, batch.dt_s)
        self.ident = IdentConfig()
        self.sigma = np.ones(self.b)
        self.evaluations = 0        # simulations of the cold starts
        self.count = 0              # simulations of the residuals and Jacobians
        self._last: dict[bytes, np.ndarray] = {}   # the residual last computed (the solver asks for the Jacobian there)
        k, b = self.k, self.b
        nu_range = (base.psa.nu_min_n_per_v, base.psa.nu_max_n_per_v)
        prior_sd = math.log1p(tolerance)
        self.prior_sd = prior_sd
        nw = max(self.nh - 1, 0)
        h_sd = [WEIGHT_PRIOR_SD] * nw + [SERIES_PRIOR_SD_OHM] * (self.nh > 0)
        self.prior = np.concatenate([np.full(k, prior_sd), np.full(self.nc, CHAIN_PRIOR_SD_US), h_sd])
        self.prior_centre = np.concatenate([np.zeros(k), self.c_base, np.zeros(self.nh)])
        self.lo = np.concatenate([np.full(k, -BOUND_SDS * prior_sd), [CHAIN_BOUNDS_US[n][0] for n in self.chain_names],
                                  [-WEIGHT_BOUND] * nw + [SERIES_BOUNDS_OHM[0]] * (self.nh > 0),
                                  np.tile([nu_range[0] - 0.1, base.valve.lh_min_m * UM_PER_M], b)])
        self.hi = np.concatenate([np.full(k, BOUND_SDS * prior_sd), [CHAIN_BOUNDS_US[n][1] for n in self.chain_names],
                                  [WEIGHT_BOUND] * nw + [SERIES_BOUNDS_OHM[1]] * (self.nh > 0),
                                  np.tile([nu_range[1] + 0.1, base.valve.lh_max_m * UM_PER_M], b)])
        for name, (f_lo, f_hi) in (limits or {}).items():
            i = list(names).index(name)
            self.lo[i], self.hi[i] = max(self.lo[i], math.log(f_lo)), min(self.hi[i], math.log(f_hi))

    def chain_of(self, c: np.ndarray) -> MeasurementChain:
        """The measurement chain of the chain parameters ``c`` (µs)."""
        return replace(self.batch.chain, **{n: float(v) * S_PER_US for n, v in zip(self.chain_names, c)})

    def element_of(self, e: np.ndarray) -> Hysteresis:
        """The hysteresis element of its parameters ``e`` (weights V/mC, series resistance Ω)."""
        if not self.nh:
            return self.element
        return replace(self.element, weights_v_per_c=tuple(float(w) * WEIGHT_UNIT_V_PER_C for w in e[:-1]),
                       series_ohm=float(e[-1]))

    def element_voltage(self, j: int, nu: np.ndarray, e: np.ndarray, chain: MeasurementChain) -> np.ndarray:
        """The element's voltage (V) in injection ``j`` at each N_u of ``nu`` (B,), as the amplifier
        measures it (through ``chain``), shape (B, samples); zeros without the element."""
        inj = self.usable[j]
        out = np.zeros((nu.size, inj.n))
        if not self.nh:
            return out
        element, r0b = self.element_of(e), self.sims.base.psa.r0b_v_per_n
        cur = chain.actuator_current(inj.current_a, inj.dt_s)
        for b, n in enumerate(nu):
            out[b] = element_voltage(element, r0b, cur, inj.dt_s, float(n))
        return lowpass(out, chain.u_filter_tau_s, inj.dt_s) if chain.u_filter_tau_s > 0 else out

    def element_columns(self, j: int, nu: float, chain: MeasurementChain) -> np.ndarray:
        """d(voltage)/d(element parameters) of injection ``j`` at ``nu`` (V per V/mC, V per Ω), shape
        (samples, nh): the element is linear in them."""
        cols = np.stack([self.element_voltage(j, np.array([nu]), np.eye(self.nh)[i], chain)[0]
                         for i in range(self.nh)], axis=1)
        return cols

    def per_injection(self, theta: np.ndarray, chain: MeasurementChain,
                      e: np.ndarray | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
        """Each injection's (N_u, L_h) from its own cold start on the structure ``theta`` behind
        ``chain`` (with the element of ``e``, default its start), and its residual (V)."""
        e = self.h_base if e is None else e
        sim = self.sims(theta)
        start_sim = FastSimulator(replace(sim.params, chain=chain, hysteresis=self.element_of(e)), self.batch.dt_s,
                                  nu_step=NU_STEP) if not chain.identity or self.nh else sim
        out, resid = np.empty(2 * self.b), []
        for j, inj in enumerate(self.usable):
            est = identify(inj, start_sim, self.ident)
            self.evaluations += est.evaluations
            nu = est.nu_n_per_v if math.isfinite(est.nu_n_per_v) else self.ident.start_point[0]
            lh = est.lh_m * UM_PER_M if math.isfinite(est.lh_m) else self.ident.start_point[1]
            out[2 * j:2 * j + 2] = nu, lh
            u = measured_voltage(sim, inj, np.array([nu]), np.array([lh]), chain)[0] \
                + self.element_voltage(j, np.array([nu]), e, chain)[0]
            resid.append(u - inj.voltage_v)
        return out, resid

    def start(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """The start: each injection fitted alone with the base parameters, whose residual sets its
        noise level; and those residuals (V)."""
        x0 = np.zeros(self.p + 2 * self.b)
        x0[self.k:self.q] = self.c_base
        x0[self.q:self.p] = self.h_base
        x0[self.p:], before = self.per_injection(np.zeros(self.k), self.batch.chain)
        self.sigma = np.array([noise_level_v(r) for r in before])
        for _ in range(ELEMENT_START_ROUNDS if self.nh else 0):
            x0[self.q:self.p] = self.element_start(x0)
            x0[self.p:] = self.per_injection(np.zeros(self.k), self.batch.chain, x0[self.q:self.p])[0]
        return x0, before

    def element_start(self, x: np.ndarray) -> np.ndarray:
        """The element's parameters that best explain the batch at ``x``'s structure, chain and
        injections' (N_u, L_h): linear least squares, as the element is linear in them (within the
        bounds). From the element's neutral start the full fit wandered to a structure at its bounds
        (a misfit of 173 sd on a hysteresis part); from this one it does not."""
        k, q, p = self.k, self.q, self.p
        sim, chain = self.sims(x[:k]), self.chain_of(x[k:q])
        rows, rhs = [], []
        for j, inj in enumerate(self.usable):
            nu, lh = x[p + 2 * j], x[p + 2 * j + 1]
            u = measured_voltage(sim, inj, np.array([nu]), np.array([lh]), chain)[0]
            rows.append(self.element_columns(j, nu, chain) / self.sigma[j])
            rhs.append((inj.voltage_v - u) / self.sigma[j])
        e = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
        result: np.ndarray = np.clip(e, self.lo[q:p], self.hi[q:p])
        return result

    def start_at(self, params: InjectorParameters) -> np.ndarray:
        """A start at ``params`` (its structure and chain, within the bounds), each injection's (N_u,
        L_h) identified on it."""
        x0 = np.zeros(self.p + 2 * self.b)
        x0[:self.k] = log_factors(params, self.sims.base, self.names)
        x0[self.k:self.q] = [getattr(params.chain, n) * US_PER_S for n in self.chain_names]
        x0[self.q:self.p] = self.h_base
        if self.nh and params.hysteresis.thresholds_c == self.element.thresholds_c:   # the element learned before
            x0[self.q:self.p] = [*(w / WEIGHT_UNIT_V_PER_C for w in params.hysteresis.weights_v_per_c),
                                 params.hysteresis.series_ohm]
        x0[:self.p] = np.clip(x0[:self.p], self.lo[:self.p] + 1e-9, self.hi[:self.p] - 1e-9)
        x0[self.p:] = self.per_injection(x0[:self.k], self.chain_of(x0[self.k:self.q]), x0[self.q:self.p])[0]
        return x0

    def residual(self, x: np.ndarray) -> np.ndarray:
        """Every sample's voltage error over its noise level, then the shared parameters' prior."""
        k, q, p = self.k, self.q, self.p
        sim, chain = self.sims(x[:k]), self.chain_of(x[k:q])
        parts = []
        for j, inj in enumerate(self.usable):
            u = measured_voltage(sim, inj, x[p + 2 * j:p + 2 * j + 1], x[p + 2 * j + 1:p + 2 * j + 2], chain)[0]
            if self.nh:
                u = u + self.element_voltage(j, x[p + 2 * j:p + 2 * j + 1], x[q:p], chain)[0]
            parts.append((u - inj.voltage_v) / self.sigma[j])
        self.count += self.b
        parts.append((x[:p] - self.prior_centre) / self.prior)
        r = np.concatenate(parts)
        self._last.clear()
        self._last[x.tobytes()] = r
        return r

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Forward differences: one simulator per perturbed shared parameter, every injection on it;
        each injection's own (N_u, L_h) in one batched simulation."""
        k, q, p, hi = self.k, self.q, self.p, self.hi
        r0 = self._last.get(x.tobytes())
        if r0 is None:
            r0 = self.residual(x)
        jac = np.zeros((r0.size, x.size))
        for i in range(q):
            h = FD_THETA if i < k else (FD_CHAIN_US if x[i] + FD_CHAIN_US <= hi[i] else -FD_CHAIN_US)
            xp = x.copy()
            xp[i] += h
            jac[:, i] = (self.residual(xp) - r0) / h
        sim, chain = self.sims(x[:k]), self.chain_of(x[k:q])
        row = 0
        for j, inj in enumerate(self.usable):
            nu, lh = x[p + 2 * j], x[p + 2 * j + 1]
            h_nu = FD_NU if nu + FD_NU <= hi[p + 2 * j] else -FD_NU       # stay inside the simulator's range
            h_lh = FD_LH_UM if lh + FD_LH_UM <= hi[p + 2 * j + 1] else -FD_LH_UM
            u = measured_voltage(sim, inj, np.array([nu, nu + h_nu, nu]), np.array([lh, lh, lh + h_lh]), chain)
            if self.nh:
                u = u + self.element_voltage(j, np.array([nu, nu + h_nu, nu]), x[q:p], chain)
                jac[row:row + self.n_win[j], q:p] = self.element_columns(j, nu, chain) / self.sigma[j]
            self.count += 3
            jac[row:row + self.n_win[j], p + 2 * j] = (u[1] - u[0]) / h_nu / self.sigma[j]
            jac[row:row + self.n_win[j], p + 2 * j + 1] = (u[2] - u[0]) / h_lh / self.sigma[j]
            row += self.n_win[j]
        return jac

    def solve(self, start: np.ndarray, max_iterations: int) -> LeastSquaresResult:
        """The bounded Levenberg–Marquardt fit from ``start``."""
        return least_squares_lm(self.residual, self.jacobian, np.clip(start, self.lo + 1e-9, self.hi - 1e-9),
                                self.lo, self.hi, max_nfev=max_iterations, xtol=1e-8, ftol=1e-10)

    def voltage_residuals(self, f: LeastSquaresResult) -> list[np.ndarray]:
        """Each injection's voltage residual (V) at the solution ``f``."""
        edges = np.cumsum([0, *self.n_win])
        return [f.fun[edges[j]:edges[j + 1]] * self.sigma[j] for j in range(self.b)]

    def misfit_z(self, f: LeastSquaresResult) -> float:
        """The worst injection's smooth residual structure (chi-square of its lowest cosine components,
        :func:`~estimator.ident.fit.adequacy.assess`) in standard deviations above its expectation."""
        return max(structure_z(r, 2 + self.p // self.b) for r in self.voltage_residuals(f))

    def restarted(self, fit: LeastSquaresResult, max_restarts: int, max_iterations: int) -> tuple[LeastSquaresResult, int]:
        """The best of ``fit`` and up to ``max_restarts`` restarts while the residual is not white.

        A local minimum: the valve's stiffness and damping trade against each other and L_h, and an
        injection's (N_u, L_h) can sit in the wrong basin of its own cost. Start again with every
        injection re-identified from a cold start (a global search of its own two parameters), first
        on the structure found, then on structures redrawn within the prior (seeded)."""
        k, q, p = self.k, self.q, self.p
        rng = np.random.default_rng(RESTART_SEED)
        restarts = 0
        while self.misfit_z(fit) > RESTART_Z and restarts < max_restarts:
            start = fit.x.copy()
            if restarts > 0:
                start[:k] = np.clip(rng.normal(0.0, self.prior_sd, k), self.lo[:k] + 1e-9, self.hi[:k] - 1e-9)
                start[k:q] = self.c_base
            start[p:] = self.per_injection(start[:k], self.chain_of(start[k:q]), start[q:p])[0]
            trial = self.solve(start, max_iterations)
            restarts += 1
            if trial.cost < fit.cost:
                fit = trial
        return fit, restarts

    def gain_slope(self, c: np.ndarray) -> np.ndarray:
        """The derivative of the chain's noise gain in each chain parameter (per µs), central
        differences kept inside the bounds."""
        out = np.zeros(self.nc)
        for i, n in enumerate(self.chain_names):
            a, b_ = c.copy(), c.copy()
            a[i] = max(a[i] - FD_CHAIN_US, CHAIN_BOUNDS_US[n][0])
            b_[i] = min(b_[i] + FD_CHAIN_US, CHAIN_BOUNDS_US[n][1])
            ga, gb = (noise_gain(ch.u_filter_tau_s, ch.i_skew_s, self.batch.dt_s) for ch in (self.chain_of(a), self.chain_of(b_)))
            out[i] = (gb - ga) / (b_[i] - a[i])
        return out

    def covariance(self, fit: LeastSquaresResult) -> np.ndarray:
        """The unknowns' covariance: the Gauss–Newton matrix's inverse, plus the pull of the measured
        current's noise on the chain (and what correlates with it) as a bias ``b b'``."""
        x, k, q, p = fit.x, self.k, self.q, self.p
        cov = np.linalg.pinv(fit.jac.T @ fit.jac)
        if self.nc:
            params = replace(self.sims.params(x[:k]), hysteresis=self.element_of(x[q:p]))
            share = sum(inj.n * (current_noise_a(inj.current_a) / self.sigma[j]) ** 2
                        * params.feedthrough_ohm(float(x[p + 2 * j])) ** 2 for j, inj in enumerate(self.usable))
            pull = np.zeros(x.size)       # the gradient of half the share (the cost is half the squares)
            pull[k:q] = 0.5 * share * self.gain_slope(x[k:q])
            bias = cov @ pull
            cov = cov + np.outer(bias, bias)
        result: np.ndarray = cov
        return result

    def left_uncertainty(self, fit: LeastSquaresResult, cov: np.ndarray) -> CalibrationUncertainty:
        """What the shared parameters' uncertainty leaves in each injection's (N_u, L_h), RMS over the
        batch: its marginal covariance less the part its own samples explain (the inverse of its own
        two columns' J'J)."""
        nu_rel, lh_sd = [], []
        for j in range(self.b):
            own = self.own_part(fit, j)
            if own is None:
                continue
            idx = [self.p + 2 * j, self.p + 2 * j + 1]
            shared_part = cov[np.ix_(idx, idx)] - own
            nu_rel.append(math.sqrt(max(shared_part[0, 0], 0.0)) / fit.x[idx[0]])
            lh_sd.append(math.sqrt(max(shared_part[1, 1], 0.0)))
        return CalibrationUncertainty(_rms(nu_rel, 0.1), min(_rms(lh_sd, math.inf) * M_PER_UM, 10e-6))

    def own_part(self, fit: LeastSquaresResult, j: int) -> np.ndarray | None:
        """The covariance of injection ``j``'s (N_u, L_h) that its own samples explain: the inverse of
        its own two columns' J'J (None where that is singular)."""
        own = fit.jac[:, [self.p + 2 * j, self.p + 2 * j + 1]]
        try:
            result: np.ndarray = np.linalg.inv(own.T @ own)
        except np.linalg.LinAlgError:
            return None
        return result

    def left_response(self, fit: LeastSquaresResult, cov: np.ndarray) -> tuple[float, float]:
        """What the shared parameters' uncertainty leaves in the valve's predicted motion: the RMS
        over the batch of the plateau stroke's (relative) and the opening instant's (s) standard
        deviation, each injection's prediction differentiated in the structure, the measurement chain's
        current skew and its own (N_u, L_h) and taken through their covariance less the part its own
        samples explain. The valve
        answers to the structure and to (N_u, L_h) together: an error in one that the voltage
        compensates with the other moves the stroke by less than each alone would say."""
        x, k, p = fit.x, self.k, self.p
        sim = self.sims(x[:k])
        steps = np.concatenate([np.full(k, RESPONSE_THETA), [RESPONSE_NU, RESPONSE_LH_UM]])
        stroke_rel, opening = [], []
        for j, inj in enumerate(self.usable):
            nu, lh = float(x[p + 2 * j]), float(x[p + 2 * j + 1])
            h = steps.copy()
            if nu + h[k] > sim.params.psa.nu_max_n_per_v:     # stay inside the simulator's N_u range
                h[k] = -h[k]
            own = self.own_part(fit, j)
            try:
                y0 = np.array(predict_valve(sim, inj, nu, lh * M_PER_UM)[1:])     # opening (s), stroke (m)
                if own is None or not (np.all(np.isfinite(y0)) and y0[1] > 0):
                    continue
                g = np.empty((2, k + 2))
                for i in range(k):
                    theta = x[:k].copy()
                    theta[i] += h[i]
                    g[:, i] = predict_valve(self.sims(theta), inj, nu, lh * M_PER_UM)[1:]
                g[:, k] = predict_valve(sim, inj, nu + h[k], lh * M_PER_UM)[1:]
                g[:, k + 1] = predict_valve(sim, inj, nu, (lh + h[k + 1]) * M_PER_UM)[1:]
            except EstimatorError:     # e.g. an N_u at the edge of the simulator's range
                continue
            g = (g - y0[:, None]) / h
            if not np.all(np.isfinite(g)):
                continue
            # the chain's current skew (µs) moves the actuator's current, and so the opening instant, one to
            # one (earlier for a larger skew); its voltage filter acts through N_u and L_h only
            chain = np.zeros((2, p - k))
            for i, n in enumerate(self.chain_names):
                if n == "i_skew_s":
                    chain[0, i] = -S_PER_US
            g = np.concatenate([g[:, :k], chain, g[:, k:]], axis=1)
            idx = [*range(p), p + 2 * j, p + 2 * j + 1]
            c = cov[np.ix_(idx, idx)].copy()
            c[p:, p:] -= own
            v = g @ c @ g.T
            opening.append(math.sqrt(max(v[0, 0], 0.0)))
            stroke_rel.append(math.sqrt(max(v[1, 1], 0.0)) / y0[1])
        return _robust_rms(stroke_rel, 1.0), _robust_rms(opening, 100e-6)


def _rms(values: list[float], cap: float) -> float:
    """Root mean square of ``values`` (0 for none), at most ``cap``."""
    return min(float(np.sqrt(np.mean(np.square(values)))), cap) if values else 0.0


def _robust_rms(values: list[float], cap: float) -> float:
    """:func:`_rms` with each value at most ``OUTLIER_FACTOR`` times the median: a forward difference
    across a bend of the opening instant makes one injection's derivative, and so its σ, tens of times
    the others' (one relearned part stated 7.3 µs where its injections' σ were 0.1-0.2 µs)."""
    if not values:
        return 0.0
    return _rms(list(np.minimum(np.abs(values), OUTLIER_FACTOR * float(np.median(np.abs(values))))), cap)


def calibrate_electrical(injections: list[Injection], base: InjectorParameters | None = None,
                         names: tuple[str, ...] = STRUCTURAL_NAMES, tolerance: float = 0.10,
                         window_s: float = WINDOW_S, max_iterations: int = 30,
                         max_restarts: int = 4, fit_chain: bool = True,
                         limits: dict[str, tuple[float, float]] | None = None,
                         start: np.ndarray | None = None,
                         also_from: InjectorParameters | None = None,
                         hysteresis: bool = False,
                         thresholds_c: tuple[float, ...] = HYSTERESIS_THRESHOLDS_C) -> ElectricalCalibration:
    """Fit the structural parameters ``names`` (shared) and each injection's N_u and L_h to the
    voltage of a batch of injections of one injector (or of one lot, whose injectors share a
    structure). ``tolerance`` is the prior's relative standard deviation of each parameter. With
    ``fit_chain`` the measurement chain's U filter and I skew (:data:`CHAIN_NAMES`) are fitted too
    (prior at the base chain, :data:`CHAIN_PRIOR_SD_US`); the chain is modelled forwards (the simulated
    voltage filtered as the amplifier filters it), so the fit sees the measured noise unamplified.
    A fit whose residual is not white noise is restarted (up to ``max_restarts`` times) with every
    injection re-identified, on the structure found and on structures redrawn within the prior, and the
    best kept; if none explains the batch the result says so. Raises ValueError for a batch that cannot
    be fitted (fewer than two usable injections, mixed sample periods). ``limits`` narrows named
    parameters to (low, high) factors on their base values, and ``start`` (an earlier result's
    ``solution`` of the same batch) is where the fit starts: :func:`confirmed_out_of_tolerance` uses both.
    ``also_from`` (an earlier calibration of the same injector, e.g. the model in use) is a second
    start, every injection re-identified on it; the fit with the lower cost (prior included) is kept.
    ``hysteresis``: the model has a hysteresis element in place of R(N_u)·I, whose weights at the play
    half-widths ``thresholds_c`` (C) and series resistance are fitted too (:mod:`estimator.model.hysteresis`)."""
    base = base or load_nominal()
    if hysteresis:     # the element replaces R(N_u) I: R_0a no longer reaches the voltage
        names = tuple(n for n in names if n != "psa.r0a_ohm")
    problem = _Problem(_batch(injections, base, names, tolerance, window_s, fit_chain), base, names, tolerance, limits,
                       tuple(thresholds_c) if hysteresis else ())
    x0, before = problem.start()
    rms_before = float(np.sqrt(np.mean(np.concatenate(before) ** 2)))
    if start is not None and start.shape == x0.shape:
        x0 = np.clip(start, problem.lo + 1e-9, problem.hi - 1e-9)
    fit = problem.solve(x0, max_iterations)
    if also_from is not None:
        second = problem.solve(problem.start_at(also_from), max_iterations)
        fit = second if second.cost < fit.cost else fit
    fit, restarts = problem.restarted(fit, max_restarts, max_iterations)
    wide = _widened(problem, fit, base, tolerance)
    if wide is not None:    # the batch's N_u pressed on the range: fitted again with the range widened
        again = _Problem(problem.batch, wide, names, tolerance, limits, tuple(thresholds_c) if hysteresis else ())
        trial, more = again.restarted(again.solve(fit.x, max_iterations), max_restarts, max_iterations)
        if trial.cost < fit.cost:
            problem, fit, base, restarts = again, trial, wide, restarts + more
    return _result(problem, fit, restarts, base, rms_before)


def _widened(problem: _Problem, fit: LeastSquaresResult, base: InjectorParameters,
             tolerance: float) -> InjectorParameters | None:
    """``base`` with its N_u range widened on each side where an injection's fitted N_u lies on the
    range's edge (within :data:`NU_EDGE_N_PER_V`), by the part tolerance ``tolerance`` of that end; None
    where none does. Table 1's range (15-21 N/V, 0-100 °C) is the nominal part's: a series part's
    structure within its tolerance moves the N_u that explains the same voltage by about as much (the
    blocked capacitance is N_u²/k_s), and a learned model's N_u is in its own structure's terms. A hot
    part whose model was learned with N_u held at the edge was fitted with a structure bent to make up
    for it, and its estimates then sat on the tracker's search bound (``at_bound``, no correction)."""
    nu = fit.x[problem.p::2]
    lo, hi = problem.lo[problem.p], problem.hi[problem.p]
    psa = base.psa
    low, high = psa.nu_min_n_per_v, psa.nu_max_n_per_v
    if float(np.max(nu)) >= hi - NU_EDGE_N_PER_V:     # a batch holds two injections at least (_batch)
        high = psa.nu_max_n_per_v * (1.0 + tolerance)
    if float(np.min(nu)) <= lo + NU_EDGE_N_PER_V:
        low = psa.nu_min_n_per_v * (1.0 - tolerance)
    if (low, high) == (psa.nu_min_n_per_v, psa.nu_max_n_per_v):
        return None
    return replace(base, psa=psa.with_nu_range(low, high))


def _result(problem: _Problem, fit: LeastSquaresResult, restarts: int, base: InjectorParameters,
            rms_before: float) -> ElectricalCalibration:
    """The calibration's report of the fit ``fit``: parameters with their σ, correlations, the
    parameters the batch hardly informs, warnings, the verdict, the uncertainty left in estimates."""
    x, k, q, p, names = fit.x, problem.k, problem.q, problem.p, problem.names
    cov = problem.covariance(fit)
    sd = np.sqrt(np.clip(np.diag(cov)[:p], 0, None))
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / np.outer(d, d)
    shared = tuple(names) + tuple(f"chain.{n}" for n in problem.chain_names) \
        + tuple(f"hysteresis.w{i}" for i in range(problem.nh - 1)) + ("hysteresis.series_ohm",) * (problem.nh > 0)
    correlated = [(shared[i], shared[j], float(corr[i, j])) for i in range(p) for j in range(i + 1, p)
                  if abs(corr[i, j]) > CORRELATED]
    weak = [shared[i] for i in range(p) if sd[i] > WEAK_FRACTION * problem.prior[i]]
    warnings = []
    f_open = np.array([inj.f_open_n for inj in problem.usable])
    if np.ptp(f_open) < 0.2 * np.mean(f_open):
        warnings.append(f"the preload forces span only {np.min(f_open):.0f}-{np.max(f_open):.0f} N: the valve's "
                        "parameters are weakly determined (calibrate over rail pressures, e.g. 28-300 N)")
    z = problem.misfit_z(fit)
    if z > MISFIT_Z:
        warnings.append(f"the calibrated model does not explain the batch (residual {z:.0f} standard deviations "
                        f"above the noise after {restarts} restart(s)): do not use it; add injections or check "
                        "the traces' preload forces and measurement chain")
    if weak:
        warnings.append(f"{len(weak)} parameter(s) hardly informed by this batch (kept near the tables): "
                        + ", ".join(weak))
    chain = problem.chain_of(x[k:q])
    after = problem.voltage_residuals(fit)
    params = replace(problem.sims.params(x[:k]), hysteresis=problem.element_of(x[q:p]),
                     chain=replace(base.chain, **{n: getattr(chain, n) for n in problem.chain_names}),
                     calibration=replace(problem.left_uncertainty(fit, cov),
                                         **dict(zip(("stroke_rel_sigma", "opening_sigma_s"),
                                                    problem.left_response(fit, cov))),
                                         preload_lo_n=float(np.min(f_open)), preload_hi_n=float(np.max(f_open))))
    return ElectricalCalibration(
        params, tuple(names), np.exp(x[:k]), sd[:k], x[p::2].copy(), x[p + 1::2].copy(), rms_before,
        float(np.sqrt(np.mean(np.concatenate(after) ** 2))), correlated, weak, warnings,
        problem.evaluations + problem.count, z <= MISFIT_Z, z,
        {n: float(v) for n, v in zip(problem.chain_names, sd[k:q])}, d[p::2].copy(), d[p + 1::2].copy(),
        2.0 * float(fit.cost), x.copy(), problem.nh > 0)


def noise_gain(u_filter_tau_s: float, i_skew_s: float, dt_s: float) -> float:
    """Sum of squares of the chain's impulse response from the measured current's samples to the
    simulated voltage's direct term: the skew's linear interpolation, then the U filter (1 for none;
    0.5 for a half-sample skew). White noise of variance v in the current leaves v R^2 times this in
    each simulated sample."""
    if u_filter_tau_s == 0.0 and i_skew_s == 0.0:
        return 1.0
    e = np.zeros(GAIN_TAPS)
    e[GAIN_TAPS // 4] = 1.0
    h = shift(e, i_skew_s / dt_s) if i_skew_s else e
    h = lowpass(h, u_filter_tau_s, dt_s) if u_filter_tau_s > 0 else h
    return float(h @ h)


def out_of_tolerance(res: ElectricalCalibration, part_tolerance: float, sigmas: float = 3.0) -> list[str]:
    """The structural parameters ``res`` found beyond ``±part_tolerance`` (relative) of their base
    values by more than ``sigmas`` of their standard deviations: a part a tester rejects. A parameter
    the batch hardly informs cannot be flagged (its standard deviation is the prior's)."""
    hi, lo = math.log1p(part_tolerance), math.log1p(-min(part_tolerance, 0.99))
    out = []
    for name, f, sd in zip(res.names, res.factors, res.sigma_rel):
        x = math.log(float(f))
        if x - hi > sigmas * sd or lo - x > sigmas * sd:
            out.append(name)
    return out


def confirmed_out_of_tolerance(injections: list[Injection], base: InjectorParameters | None,
                               res: ElectricalCalibration, part_tolerance: float, sigmas: float = 3.0,
                               tolerance: float = 0.10, window_s: float = WINDOW_S) -> list[str]:
    """:func:`out_of_tolerance`, each candidate confirmed by its profile: the batch fitted again with
    that parameter held within the tolerance (from ``res``'s solution) must explain the samples worse
    by more than ``sigmas``² in chi-square. The linearised standard deviation alone flagged 4 of 108
    seeded parts within tolerance (a valve stiffness traded against its damping in a batch of ten)."""
    out = []
    for name in out_of_tolerance(res, part_tolerance, sigmas):
        held = calibrate_electrical(injections, base, tolerance=tolerance, window_s=window_s, max_restarts=0,
                                    limits={name: (1.0 - part_tolerance, 1.0 + part_tolerance)},
                                    start=res.solution, hysteresis=res.hysteresis,
                                    thresholds_c=res.params.hysteresis.thresholds_c or HYSTERESIS_THRESHOLDS_C)
        if held.chi2 - res.chi2 > sigmas ** 2:
            out.append(name)
    return out


def beyond_bounds(params: InjectorParameters, base: InjectorParameters, tolerance: float,
                  names: tuple[str, ...] = STRUCTURAL_NAMES) -> list[str]:
    """The structural parameters of ``params`` outside the bounds a calibration of ``base`` with this
    ``tolerance`` keeps them in (empty: ``params`` can be such a calibration)."""
    limit = BOUND_SDS * math.log1p(tolerance) + 1e-9
    return [n for n, x in zip(names, log_factors(params, base, names)) if abs(x) > limit]


def log_factors(params: InjectorParameters, base: InjectorParameters, names: tuple[str, ...]) -> np.ndarray:
    """The logarithm of each named parameter of ``params`` over its ``base`` value ("table.field"
    names): the calibration's own coordinates."""
    out = np.empty(len(names))
    for i, n in enumerate(names):
        table, field_name = n.split(".")
        out[i] = math.log(getattr(getattr(params, table), field_name) / getattr(getattr(base, table), field_name))
    return out


def measured_voltage(sim: FastSimulator, inj: Injection, nu: np.ndarray | float, lh_um: np.ndarray | float,
                     chain: MeasurementChain | None = None) -> np.ndarray:
    """The voltage (V) the amplifier would measure for ``inj``'s measured current at (N_u N/V, L_h µm),
    shape (candidates, samples): the actuator's current recovered through ``chain`` (default the
    simulator's own), simulated, and its voltage filtered as the chain filters it. NaN-free (an
    infeasible candidate gets a large constant, so that a search turns away from it)."""
    chain = sim.params.chain if chain is None else chain
    cur = chain.actuator_current(inj.current_a, inj.dt_s)
    u = sim.simulate(cur, np.atleast_1d(np.asarray(nu, dtype=float)),
                     np.atleast_1d(np.asarray(lh_um, dtype=float)) * M_PER_UM, inj.f_open_n).voltage_v
    u = np.where(np.isfinite(u), u, 1e3)
    return lowpass(u, chain.u_filter_tau_s, inj.dt_s) if chain.u_filter_tau_s > 0 else u
