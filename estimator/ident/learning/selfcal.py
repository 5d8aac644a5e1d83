"""Self-calibration: an injector whose model is mismatched learns its own structural parameters from
the injections it makes anyway.

While an injector is ``model_mismatch``, the recursive estimator keeps a bounded window of its
accepted injections (:class:`CalibrationWindow`), chosen to span its operating points (preload force,
coupling factor): when the window is full, the injection whose operating point is closest to another
one's makes room. Once the window holds enough injections over a wide enough range of preload forces
(or, at one rail pressure, has been full for ``narrow_after`` more injections without reaching it),
:func:`self_calibrate` fits the structural parameters to all but the newest ``held_out`` of them
(:func:`~estimator.ident.learning.electrical.calibrate_electrical`) and tests the result on those held out:
each is identified with the current and with the calibrated parameters, and the calibrated set is
adopted only if the calibration explains its own batch and it explains them better by more than
``adopt_chi2`` (chi-square units, the sum over the held-out injections of the drop in their residual
energy over their noise variance), or no worse by that much while it moves their N_u by more than
``adopt_shift_sigmas`` of its standard deviations; a refinement of a model in service, unless it
explains them worse (:func:`_adoptable`). A rejected calibration starts a new window.

The calibration itself (seconds of computing) is handed to a *calibrator*: :class:`InlineCalibrator`
runs it at once (offline tracking: deterministic), the daemon's background calibrator
(:mod:`estimator.service.calibration_worker`) in a process of its own at low priority, so that the
injection worker never waits for it. Either hands back :class:`CalibrationOutcome` objects that the
tracker collects at its next update.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from estimator.ident.config import IdentConfig
from estimator.ident.fit.adequacy import noise_level_v, structure_z
from estimator.ident.fit.idle_stroke import identify
from estimator.ident.learning.electrical import WINDOW_S, confirmed_out_of_tolerance, measured_voltage
from estimator.ident.learning.element import calibrate_with_hysteresis_if_needed, valve_spread
from estimator.ident.measurement import Injection
from estimator.ident.status import CALIBRATION_STATES, Learning
from estimator.model.fast_sim import FastSimulator
from estimator.model.parameters import InjectorParameters
from estimator.units import UM_PER_M

Fit = tuple[float, float]   # one injection's (N_u N/V, L_h m) as a model identifies it

STATES = CALIBRATION_STATES
NU_SCALE_N_PER_V = 1.0       # operating-point distance: 1 N/V of N_u ...
PRELOAD_SCALE_N = 50.0       # ... counts as much as 50 N of preload force


@dataclass(frozen=True)
class SelfCalConfig:
    """Settings of the self-calibration (counts of injections; ``min_preload_spread`` relative)."""

    window: int = 12               # injections kept per injector (bounded memory: ≈ 6 kB each)
    held_out: int = 2              # the newest ones, kept out of the fit to test it
    min_preload_spread: float = 0.5   # (max - min) / mean of the preload forces before a calibration is tried
    narrow_after: int = 0          # ... or once a full window has waited this many more injections (0: never)
    adopt_chi2: float = 25.0       # held-out improvement needed to adopt (chi-square units)
    tolerance: float = 0.10        # prior relative standard deviation of each structural parameter
    part_tolerance: float = 0.10   # the datasheet tolerance: a parameter beyond ±this of the tables ...
    tolerance_sigmas: float = 3.0  # ... by more than this many of its standard deviations is out_of_tolerance
    monitor_drift: float = 0.5     # the monitor's allowance: a cumulative sum of (mismatched - this) per injection
    monitor_limit: float = 4.0     # ... whose reaching this starts re-learning (8 mismatched injections in a row)
    confirm: int = 5               # injections an adopted model serves before it is monitoring
    retry_after: int = 12          # injections after a refused calibration before the next window (doubling, x8 at most)
    refine_window: int = 24        # once monitoring: one more calibration over this many injections (0: none)
    refine_again: int = 60         # once refined: one more over this many (0: none); the valve's motion sharpens
    adopt_shift_sigmas: float = 3.0   # ... or adopted if it moves the held-out N_u by more than this many sd
    hysteresis: bool = True        # where the tables' R(N_u) I is refused, try a hysteresis element (adopted where
                                   # two grids of plays both explain the batch; element.py, docs/design.md)

    def __post_init__(self) -> None:
        if not (isinstance(self.window, int) and isinstance(self.held_out, int) and self.held_out >= 1
                and self.window >= self.held_out + 3):
            raise ValueError(f"self-calibration window {self.window!r} must hold held_out {self.held_out!r} "
                             "injections and at least three more")
        for name in ("refine_window", "refine_again"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and (v == 0 or v >= self.held_out + 3)):
                raise ValueError(f"self-calibration {name} {v!r} must be 0 or hold held_out "
                                 f"{self.held_out!r} injections and at least three more")
        if not isinstance(self.hysteresis, bool):
            raise ValueError(f"self-calibration hysteresis = {self.hysteresis!r} must be true or false")
        for name in ("confirm", "retry_after", "narrow_after"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"self-calibration {name} = {v!r} must be a non-negative whole number")
        for name in ("min_preload_spread", "adopt_chi2", "tolerance", "part_tolerance", "tolerance_sigmas",
                     "monitor_drift", "monitor_limit", "adopt_shift_sigmas"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"self-calibration {name} = {v!r} must be a positive number")


@dataclass
class CalibrationStatus:
    """Where an injector's learning stands (``state`` a :class:`~estimator.ident.status.Learning`).

    ``batch`` and ``preload_span`` are the progress of a window being collected (injections, and the
    (max - min) / mean of their preload forces); ``rms_before_v``/``rms_after_v``/``held_out_chi2``
    the last calibration's figures; ``out_of_tolerance`` the structural parameters it found beyond the
    part's tolerance; ``evidence`` the monitor's cumulative sum (re-learning at the configured limit);
    ``served`` the injections the model in use has served since its adoption; ``refusals`` the
    calibrations refused in a row and ``retry_in`` the injections left before the next window;
    ``source`` where the model in use comes from (``tables``, ``learned`` or ``seeded``);
    ``refined`` whether the model in use has had its refinement over a larger window, ``refinements``
    how many (the first over ``refine_window``, a second over ``refine_again``); ``nu_shift_z``
    how far the last calibration moved the held-out injections' N_u, in its standard deviations;
    ``learned_lo_n``..``learned_hi_n`` the preload forces (N) of a model learned over a narrow span
    (0: none), which serves them and those within ``min_preload_spread / 2`` of them.
    """

    state: str = Learning.IDLE
    batch: int = 0
    rms_before_v: float = float("nan")
    rms_after_v: float = float("nan")
    held_out_chi2: float = float("nan")
    message: str = ""
    calibrations: int = 0          # calibrations run for this injector so far
    preload_span: float = 0.0
    out_of_tolerance: tuple[str, ...] = ()
    evidence: float = 0.0
    served: int = 0
    refusals: int = 0
    retry_in: int = 0
    source: str = "tables"
    refined: bool = False
    refinements: int = 0           # refinements the model in use has had (refine_window, then refine_again)
    nu_shift_z: float = float("nan")
    learned_lo_n: float = 0.0      # a model learned over a narrow span of preload forces: that span (N);
    learned_hi_n: float = 0.0      # 0: the model in use serves every preload force

    def serves(self, f_open_n: float, config: SelfCalConfig) -> bool:
        """Whether the model in use serves an injection at the preload force ``f_open_n`` (N): any
        model but one learned over a narrow span, that one within ``min_preload_spread / 2`` of it."""
        if self.learned_hi_n <= 0.0:
            return True
        margin = config.min_preload_spread / 2
        return self.learned_lo_n * (1 - margin) <= f_open_n <= self.learned_hi_n * (1 + margin)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN as None)."""
        def num(v: float) -> float | None:
            return round(v, 4) if math.isfinite(v) else None
        return {"state": str(self.state), "batch": self.batch, "preload_span": round(self.preload_span, 3),
                "rms_before_v": num(self.rms_before_v), "rms_after_v": num(self.rms_after_v),
                "held_out_chi2": num(self.held_out_chi2), "nu_shift_z": num(self.nu_shift_z), "message": self.message,
                "calibrations": self.calibrations, "out_of_tolerance": list(self.out_of_tolerance),
                "evidence": round(self.evidence, 3), "served": self.served, "refusals": self.refusals,
                "retry_in": self.retry_in, "source": self.source, "refined": self.refined, "refinements": self.refinements,
                "learned_lo_n": round(self.learned_lo_n, 2), "learned_hi_n": round(self.learned_hi_n, 2)}

    @classmethod
    def from_dict(cls, d: Any) -> CalibrationStatus:
        """Inverse of :meth:`to_dict`, validating every field; ValueError names the first bad one."""
        if not isinstance(d, dict):
            raise ValueError("a learning status must be an object")
        st = cls()
        if d.get("state") not in CALIBRATION_STATES:
            raise ValueError(f"state = {d.get('state')!r} is not a learning state")
        st.state = Learning(d["state"])
        for name in ("batch", "calibrations", "served", "refusals", "retry_in", "refinements"):
            v = d.get(name, 0)
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < 2 ** 31:
                raise ValueError(f"{name} = {v!r} must be a non-negative whole number")
            setattr(st, name, v)
        for name in ("rms_before_v", "rms_after_v", "held_out_chi2", "nu_shift_z", "preload_span", "evidence",
                     "learned_lo_n", "learned_hi_n"):
            v = d.get(name)
            if v is None:
                continue
            signed = name in ("held_out_chi2", "nu_shift_z")    # a calibration may explain the held-out worse
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (v < 0 and not signed):
                raise ValueError(f"{name} = {v!r} must be a {'' if signed else 'non-negative '}number or null")
            setattr(st, name, float(v))
        msg, source, oot = d.get("message", ""), d.get("source", "tables"), d.get("out_of_tolerance", [])
        if not isinstance(msg, str) or len(msg) > 1000:
            raise ValueError("message must be a short string")
        if source not in ("tables", "learned", "seeded"):
            raise ValueError(f"source = {source!r} must be tables, learned or seeded")
        if not (isinstance(oot, list) and len(oot) <= 64 and all(isinstance(n, str) and len(n) < 64 for n in oot)):
            raise ValueError("out_of_tolerance must be a list of parameter names")
        refined = d.get("refined", False)
        if not isinstance(refined, bool):
            raise ValueError("refined must be true or false")
        st.message, st.source, st.out_of_tolerance, st.refined = msg, source, tuple(oot), refined
        return st


@dataclass
class CalibrationWindow:
    """A bounded set of one injector's injections spanning its operating points."""

    capacity: int
    items: list[tuple[Injection, float]] = field(default_factory=list)   # (injection, its N_u estimate)
    waited: int = 0       # injections added while full (each made room for itself)
    added: int = 0        # injections added to it (those it was started with not counted)
    refining: bool = False   # a model in service refined on it (set by the learner; :func:`_adoptable`)
    probed: bool = False     # ... and its newest injections are drive levels that model failed at (set by the
                             # learner): they must not be another part's (:data:`ANOTHER_PART_Z`)

    def add(self, inj: Injection, nu_n_per_v: float) -> None:
        """Keep ``inj`` (its first :data:`~estimator.ident.learning.electrical.WINDOW_S`); when full, drop the
        older of the two injections whose operating points are closest."""
        w = inj.window(WINDOW_S)   # copied: a view would keep the whole trace alive
        self.items.append((replace(w, current_a=w.current_a.copy(), voltage_v=w.voltage_v.copy()), float(nu_n_per_v)))
        self.added += 1
        if len(self.items) > self.capacity:
            pts = np.array([[i.f_open_n / PRELOAD_SCALE_N, nu / NU_SCALE_N_PER_V] for i, nu in self.items])
            d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2) + np.eye(len(pts)) * 1e9
            a, b = np.unravel_index(int(np.argmin(d)), d.shape)
            del self.items[min(a, b)]
            self.waited += 1

    def preload_spread(self) -> float:
        """(max - min) / mean of the preload forces held."""
        f = np.array([i.f_open_n for i, _ in self.items])
        return float(np.ptp(f) / np.mean(f)) if f.size else 0.0

    def ready(self, config: SelfCalConfig) -> bool:
        """Full, and over a wide enough range of preload forces, or full for ``narrow_after`` more
        injections without reaching that range (an injector at one rail pressure)."""
        return len(self.items) >= config.window and (self.preload_spread() >= config.min_preload_spread
                                                     or 0 < config.narrow_after <= self.waited)

    def narrow(self, config: SelfCalConfig) -> str:
        """What it says of itself when its preload forces span less than ``min_preload_spread``
        ("" when they do not)."""
        if not self.items or self.preload_spread() >= config.min_preload_spread:
            return ""
        lo, hi = self.preload_range()
        return (f"preload forces {lo:.0f}-{hi:.0f} N only (span {self.preload_spread():.2f} < "
                f"{config.min_preload_spread:g})")

    def preload_range(self) -> tuple[float, float]:
        """The lowest and the highest preload force held (N)."""
        f = [inj.f_open_n for inj, _ in self.items]
        return min(f), max(f)


def self_calibrate(window: CalibrationWindow, base: InjectorParameters, config: SelfCalConfig,
                   current: InjectorParameters | None = None) -> tuple[CalibrationStatus, InjectorParameters | None]:
    """Calibrate on the window but its newest ``held_out`` injections, test on those against the model
    in use (``current``, default ``base``: the configured tables, which are the calibration's prior);
    the status and the parameters to adopt (None if the calibration is refused)."""
    status, sim = _calibrate(window, base, config, current)
    return status, (sim.params if sim is not None else None)


def _calibrate(window: CalibrationWindow, base: InjectorParameters, config: SelfCalConfig,
               current: InjectorParameters | None = None) -> tuple[CalibrationStatus, FastSimulator | None]:
    """:func:`self_calibrate`, with the simulator of the adopted parameters it tested them on."""
    injections = [i for i, _ in window.items]
    batch, held = injections[:-config.held_out], injections[-config.held_out:]
    try:
        res = calibrate_with_hysteresis_if_needed(batch, base, tolerance=config.tolerance, also_from=current,
                                                  hysteresis=config.hysteresis)
    except ValueError as exc:
        return CalibrationStatus(Learning.REFUSED, len(batch), message=str(exc)), None
    status = CalibrationStatus(Learning.REFUSED, len(batch), res.rms_before_v, res.rms_after_v)
    if not res.adequate:
        tried = ", with a hysteresis element either" if config.hysteresis else ""
        status.message = res.refusal or (f"the calibrated model does not explain the batch{tried} (residual "
                                         f"{res.misfit_z:.0f} sd above the noise)")
        return status, None
    status.out_of_tolerance = tuple(confirmed_out_of_tolerance(batch, base, res, config.part_tolerance,
                                                               config.tolerance_sigmas, config.tolerance))
    dt = held[0].dt_s
    old, new = FastSimulator(current if current is not None else base, dt), FastSimulator(res.params, dt)
    chi2 = 0.0
    samples = 0
    shifts, nus, fits = [], [], []
    worst_z = 0.0
    for inj in held:
        (r_old, fit_old), (r_new, fit_new) = _held_out_residual(old, inj), _held_out_residual(new, inj)
        sigma = noise_level_v(r_new)
        if window.probed:
            worst_z = max(worst_z, structure_z(r_new))
        chi2 += float((r_old @ r_old - r_new @ r_new) / sigma ** 2)
        shifts.append(fit_new[0] - fit_old[0])
        nus.append(fit_new[0])
        fits.append((inj, fit_old, fit_new))
        samples += r_new.size
    status.held_out_chi2 = chi2
    if worst_z >= ANOTHER_PART_Z:
        status.message = (f"the refinement leaves a held-out drive level the model failed at {worst_z:.0f} sd above "
                          f"the noise (>= {ANOTHER_PART_Z:g}: another part's injections)")
        return status, None
    sd = float(np.median(res.sigma_nu_n_per_v)) if res.sigma_nu_n_per_v.size else 0.0
    status.nu_shift_z = float(np.mean(shifts)) / sd if sd > 0 else float("nan")   # NaN: no shift to judge
    if not _adoptable(chi2, status.nu_shift_z, config, window.refining):
        status.message = (f"the refinement explains the held-out injections worse (chi-square gain {chi2:.1f} "
                          f"<= {-config.adopt_chi2:g})" if window.refining else
                          f"the calibrated model explains the held-out injections no better (chi-square gain "
                          f"{chi2:.1f} <= {config.adopt_chi2:g}) and moves their N_u by {status.nu_shift_z:+.1f} sd")
        return status, None
    if current is not None and chi2 <= ALIKE_EXCESS * samples:
        # two learned models that both explain the held-out voltage within the noise (a swapped part's
        # old model leaves thousands of times the noise) yet disagree on N_u: the voltage does not
        # decide between them, and the valve's stroke follows N_u; nor do they predict the same valve
        params = disagreement(res.params, float(np.mean(shifts)) / float(np.mean(nus)),
                              *_valve_spread(old, new, fits))
        if params is not res.params:
            new = FastSimulator(params, dt)
    narrow = window.narrow(config)
    with_element = "; with a hysteresis element in place of R(N_u) I" if res.params.hysteresis.present else ""
    status.state, status.message = Learning.ADOPTED, (f"held-out chi-square gain {chi2:.0f}, N_u moved "
                                                     f"{status.nu_shift_z:+.1f} sd" + with_element
                                                     + (f"; {narrow}" if narrow else ""))
    if narrow:
        status.learned_lo_n, status.learned_hi_n = window.preload_range()
    return status, new


ALIKE_EXCESS = 0.5   # held-out chi-square gain per sample below which two models explain the voltage alike
ANOTHER_PART_Z = 1000.0   # a refinement over failed probes that leaves one of them this far above the noise (its
# smooth residual structure, sd) was calibrated mostly on another part: a part swapped under its predecessor's
# correction fails as probes. Measured on refinements over ten injections of one part and two newest held out:
# those two of the same part 3 sd at most, a Prandtl-Ishlinskii part's own probes 27 sd; a second part drawn
# from the lot (±10 %) the worse of its two 8,400-884,000 sd over 13 pairs, 6 of which the refinement explained
# better than the model in use did (adopted, a swapped part went model_mismatch 8 injections later)


def disagreement(params: InjectorParameters, shift_rel: float, stroke_rel: float = 0.0,
                 opening_s: float = 0.0) -> InjectorParameters:
    """``params`` whose statement of the valve's predicted uncertainty covers what it and the model it
    replaces say differently on the same injections when the voltage cannot tell them apart (each is
    as likely): ``shift_rel``, the relative N_u by which they disagree, and ``stroke_rel`` (relative)
    and ``opening_s`` (s), by which their predicted plateau stroke and opening instant do. A
    refinement's own covariance can state 0.3 % where the two are 2 % apart, or an opening instant to
    0.21 µs where the two predictions are 1.2 µs apart. ``params`` itself when its statement covers
    them already."""
    cal = params.calibration
    stroke = max((min(abs(v), 1.0) for v in (shift_rel, stroke_rel) if math.isfinite(v)), default=0.0)
    opening = min(abs(opening_s), 100e-6) if math.isfinite(opening_s) else 0.0
    if stroke <= cal.stroke_rel_sigma and opening <= cal.opening_sigma_s:
        return params
    return replace(params, calibration=replace(cal, stroke_rel_sigma=max(stroke, cal.stroke_rel_sigma),
                                               opening_sigma_s=max(opening, cal.opening_sigma_s)))


def _valve_spread(old: FastSimulator, new: FastSimulator,
                  fits: list[tuple[Injection, Fit, Fit]]) -> tuple[float, float]:
    """The RMS over the held-out injections, each at its own fit on either model, of the two models'
    difference in the predicted plateau stroke (relative) and opening instant (s). An injection the
    valve does not open on under either, or that either could not identify, is left out."""
    return valve_spread(new, old, [(inj, fit_new, fit_old) for inj, fit_old, fit_new in fits])


def _adoptable(chi2: float, shift_z: float, config: SelfCalConfig, refining: bool = False) -> bool:
    """Whether a calibration replaces the model in use: it explains the held-out injections better by
    more than ``adopt_chi2``, or it explains them no worse by that much and moves their N_u by more than
    ``adopt_shift_sigmas`` of its standard deviations. The held-out voltage alone hardly tells two models
    apart whose structure scales with N_u; the one calibrated on more injections is the better when
    they disagree on N_u beyond its uncertainty. A refinement of the model in service (``refining``),
    calibrated on a larger window of the same part, is adopted unless it explains them worse: the
    voltage constrains the valve's motion least, and a refinement that moves the predicted opening
    toward the truth can leave the held-out voltage as it was (a Prandtl-Ishlinskii part's refinement
    over 60 injections moved its opening 0.4 µs and gained 14 in chi-square, below ``adopt_chi2``)."""
    if chi2 > config.adopt_chi2:
        return True
    return chi2 > -config.adopt_chi2 and (refining or abs(shift_z) > config.adopt_shift_sigmas)


def _held_out_residual(sim: FastSimulator, inj: Injection) -> tuple[np.ndarray, Fit]:
    """The residual (V) of ``inj`` over its kept samples at its own cold-start estimate on ``sim``, the
    measurement chain of ``sim``'s parameters included (a calibrated set carries its own), and that
    estimate (N_u N/V, L_h m)."""
    est = identify(inj, sim, IdentConfig())
    if not (math.isfinite(est.nu_n_per_v) and math.isfinite(est.lh_m)):
        return np.full(inj.voltage_v.size, 1e3), (float("nan"), float("nan"))
    result: np.ndarray = measured_voltage(sim, inj, est.nu_n_per_v, est.lh_m * UM_PER_M)[0] - inj.voltage_v
    return result, (est.nu_n_per_v, est.lh_m)


@dataclass
class CalibrationOutcome:
    """A finished calibration: the injector, its status, the parameters to adopt (None: rejected) and,
    when the calibrator prepared it, the simulator pool for them (so that no table is built on the
    injection worker)."""

    injector_id: int
    status: CalibrationStatus
    params: InjectorParameters | None
    prepared: Any = None


class Calibrator(Protocol):
    """Where self-calibrations run (see the module docstring). ``prepare`` turns adopted parameters
    and their tables (sample period s -> table) into what the tracker swaps in; the tracker sets it."""

    prepare: Callable[[InjectorParameters, dict[float, np.ndarray]], Any] | None

    def submit(self, injector_id: int, window: CalibrationWindow, base: InjectorParameters,
               config: SelfCalConfig, current: InjectorParameters | None = None) -> None: ...

    def poll(self) -> list[CalibrationOutcome]: ...

    def close(self) -> None: ...


def calibrate_and_tabulate(window: CalibrationWindow, base: InjectorParameters, config: SelfCalConfig,
                           current: InjectorParameters | None = None
                           ) -> tuple[CalibrationStatus, InjectorParameters | None, dict[float, np.ndarray]]:
    """:func:`self_calibrate`, and for adopted parameters the simulator table of the window's sample
    period (the one the held-out test built, handed over so that the estimating process only takes it)."""
    status, sim = _calibrate(window, base, config, current)
    if sim is None:
        return status, None, {}
    return status, sim.params, {sim.dt_s: sim.transition_table()}


class InlineCalibrator:
    """Runs each calibration when it is submitted, in the caller's thread; :meth:`poll` hands it back."""

    def __init__(self, prepare: Callable[[InjectorParameters, dict[float, np.ndarray]], Any] | None = None) -> None:
        self._done: list[CalibrationOutcome] = []
        self.prepare = prepare

    def submit(self, injector_id: int, window: CalibrationWindow, base: InjectorParameters,
               config: SelfCalConfig, current: InjectorParameters | None = None) -> None:
        status, params, tables = calibrate_and_tabulate(window, base, config, current)
        prepared = self.prepare(params, tables) if params is not None and self.prepare is not None else None
        self._done.append(CalibrationOutcome(injector_id, status, params, prepared))

    def poll(self) -> list[CalibrationOutcome]:
        done, self._done = self._done, []
        return done

    def close(self) -> None:
        self._done.clear()
