"""Idle-stroke detection (eq. 28): N_u and L_h together from one injection's current and voltage.

The pieces live in their own modules: settings (:mod:`.config`), the result (:mod:`.estimate`), the
local Gauss–Newton fit and refinement (:mod:`.local_fit`), the cold-start optimiser
(:mod:`.cold_start`) and the choice between the plain and the robust cost
(:mod:`.model_selection`). This module puts them together: the search box, the cost window,
:func:`identify` (cold start) and :func:`finish` (status, covariance, valve prediction).

Model-error handling (``robust="auto"``): the plain fit and the robust fit (nuisance span of
current, charge and Prandtl–Ishlinskii ramps of the charge projected out, see
:mod:`estimator.ident.fit.cost`) are both made; if the plain model's residual is worse than the robust
one's by far more than chance allows, the model is wrong in a smooth way and the robust estimate is
used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator.ident.config import IdentConfig
from estimator.ident.coords import UM_PER_M, cov_to_si
from estimator.ident.estimate import Estimate, rejected
from estimator.ident.fit.adequacy import Adequacy
from estimator.ident.fit.cold_start import (
    SharedGrid,
    bound_tolerance,
    cold_fit,
    excess_residual_z,
    local_first_fit,
    ring_checked,
    sd_radius,
    unchecked_fit,
    usable,
)
from estimator.ident.fit.cost import CostModel
from estimator.ident.fit.local_fit import LocalFit
from estimator.ident.fit.mismatch import (
    PreloadCheck,
    model_error_cov,
    plain_adequacy,
    preload_check,
    preload_cov,
    sensitivities,
)
from estimator.ident.fit.model_selection import likelihood_ratio, prefers_robust
from estimator.ident.fit.search import Box
from estimator.ident.measurement import Injection
from estimator.ident.status import Status
from estimator.model import dynamics as dyn
from estimator.model.drive import SAMPLE_PERIOD_REL_TOL, sampled_samples
from estimator.model.fast_sim import PLATEAU_WINDOW_S, FastSimulator
from estimator.units import US_PER_S

ROBUST_START_SD = 4.0   # the automatic cold start's robust fit: first trust region in standard deviations
FLIP_MARGIN = 16.0      # chi-square units: the fit not chosen is ringed too where the statistic is this close to the threshold


def search_box(config: IdentConfig, sim: FastSimulator, f_open_n: float) -> Box:
    """The search bounds in (N/V, µm): the configured bounds, the simulator's N_u range, and the
    feasibility limit of L_h (no start in Σ3) with a small margin."""
    nu, lh = config.nu_range(sim.params), config.lh_range(sim.params)
    lo_nu = max(nu[0], sim.nu_range[0])
    hi_nu = min(nu[1], sim.nu_range[1])
    lh_feasible = dyn.min_feasible_lh_m(sim.params, f_open_n) * UM_PER_M + 0.02
    lo_lh = max(lh[0], lh_feasible)
    return Box(np.array([lo_nu, lo_lh]), np.array([hi_nu, lh[1]]))


def effective_window_s(config: IdentConfig, injection: Injection, robust: bool) -> float:
    """The cost window: ``window_s``, or in robust mode up to ``robust_window_s`` as far as the trace goes.

    With smooth model errors projected out, the contact signature is what is left to fit; late
    contacts (large L_h) leave too little of it in 100 µs, so robust mode looks further when it can.
    """
    if robust and config.robust_window_s > config.window_s:
        return max(config.window_s, min(config.robust_window_s, injection.duration_s))
    return config.window_s


MIN_WINDOW_SAMPLES = 40   # samples in the identification window below which the charge is not resolved


def screen(injection: Injection, config: IdentConfig) -> str | None:
    """Why this injection cannot be identified whatever the simulator (a phrase), or None: the checks
    that need no simulation (values, length, enough samples in the window), made before a simulator
    is built for a new sample period."""
    problem = injection.problem()
    if problem:
        return problem
    if injection.duration_s < config.window_s - 1e-12:
        return f"too short ({injection.duration_s * US_PER_S:.1f} µs < window {config.window_s * US_PER_S:.0f} µs)"
    if config.window_s / injection.dt_s < MIN_WINDOW_SAMPLES - 1e-9:
        return (f"sampled too coarsely ({injection.dt_s * US_PER_S:.2f} µs: fewer than {MIN_WINDOW_SAMPLES} samples in "
                f"the {config.window_s * US_PER_S:.0f} µs window)")
    return None


def check_injection(injection: Injection, sim: FastSimulator, config: IdentConfig) -> str | None:
    """Why this injection cannot be identified with this simulator and window (a phrase), or None."""
    problem = screen(injection, config)
    if problem:
        return problem
    if abs(sim.dt_s - injection.dt_s) > SAMPLE_PERIOD_REL_TOL * injection.dt_s:
        return (f"sample period {injection.dt_s * US_PER_S:.3f} µs does not match the simulator's "
                f"{sim.dt_s * US_PER_S:.3f} µs")
    return None


def predict_valve(sim: FastSimulator, injection: Injection, nu: float, lh_m: float) -> tuple[float, float, float]:
    """Contact time, opening time (s) and plateau stroke (m) for this injection's current.

    The measured current is used as it is, followed by zero current (the amplifier holding the
    charge) until the end of the plateau window (490 µs); the stroke is the mean plunger stroke over
    215–490 µs as in Table 3. NaN when the valve does not open with that charge.
    """
    # injection.drive().samples(...), without building the drive
    cur = sampled_samples(injection.current_a, injection.dt_s, max(PLATEAU_WINDOW_S[1], injection.duration_s), sim.dt_s)
    return sim.valve_prediction(cur, nu, lh_m, injection.f_open_n)


def _cost_model(sim: FastSimulator, inj: Injection, config: IdentConfig, robust: bool) -> CostModel:
    return CostModel(sim, inj, effective_window_s(config, inj, robust), config.norm, robust)


def identify(injection: Injection, sim: FastSimulator | None = None, config: IdentConfig | None = None,
             start: np.ndarray | None = None) -> Estimate:
    """Identify (N_u, L_h) of one injection from a cold start (eq. 28). Never raises for bad data.

    With ``config.cold_start == "local-first"`` a checked local fit from ``start`` (N/V, µm; default
    ``config.start_point``) comes first and the global search runs only where it fails the check
    (:mod:`estimator.ident.fit.cold_start`); ``evaluations`` counts the simulations of both."""
    config = config or IdentConfig()
    problem = injection.problem()
    if problem:
        return rejected(problem)
    sim = sim or FastSimulator(dt_s=injection.dt_s)
    injection = injection.through_chain(sim.params.chain)
    problem = check_injection(injection, sim, config)
    if problem:
        return rejected(problem)
    box = search_box(config, sim, injection.f_open_n)
    x0 = np.asarray(config.start_point if start is None else start, dtype=float)
    local = config.cold_start == "local-first" and bool(np.all(np.isfinite(x0)))
    if config.robust != "auto":
        robust = config.robust == "on"
        model = _cost_model(sim, injection, config, robust)
        fit = local_first_fit(model, x0, box, config) if local else None
        converged = True
        if fit is None or excess_residual_z(model, fit) > config.local_accept_z:
            fit, converged = cold_fit(model, box, config, SharedGrid([model]))
        adequacy = plain_adequacy(model, fit, config) if fit.success else None
        other, extra = None, 0
        if fit.success and (robust or not adequacy.adequate):   # type: ignore[union-attr]
            other, extra = complement_fit(sim, injection, config, box, model, fit)
        return finish(Fitted(sim, injection, fit, converged, model.evaluations + extra, box, robust, float("nan"), config),
                      Evidence(adequacy=adequacy, other=other, model=model, check_preload=True))
    m_plain, m_rob = _cost_model(sim, injection, config, False), _cost_model(sim, injection, config, True)
    m_plain.share_basis(m_rob)
    if local:
        est = _local_first_auto(sim, injection, m_plain, m_rob, x0, box, config)
        if est is not None:
            return est
    # both costs search the same first grid (and the same zooms where their valleys share a column)
    shared = SharedGrid([m_plain, m_rob])
    f_plain, c_plain = cold_fit(m_plain, box, config, shared)
    f_rob, c_rob = cold_fit(m_rob, box, config, shared)
    evaluations = m_plain.evaluations + m_rob.evaluations
    stat = likelihood_ratio(m_plain, f_plain, m_rob, f_rob)
    adequacy = plain_adequacy(m_plain, f_plain, config) if f_plain.success else None
    if prefers_robust(stat, config.model_error_threshold):
        return finish(Fitted(sim, injection, f_rob, c_rob, evaluations, box, True, stat, config),
                      Evidence(adequacy=adequacy, other=f_plain.x if f_plain.success else None, model=m_rob))
    return finish(Fitted(sim, injection, f_plain, c_plain, evaluations, box, False, stat, config),
                  Evidence(adequacy=adequacy, other=f_rob.x if f_rob.success else None, model=m_plain, check_preload=True))


def _local_first_auto(sim: FastSimulator, injection: Injection, m_plain: CostModel, m_rob: CostModel,
                      x0: np.ndarray, box: Box, config: IdentConfig) -> Estimate | None:
    """The automatic cold start's choice made from local fits: the plain fit from ``x0``, the robust
    fit from the plain optimum (its first trust region :data:`ROBUST_START_SD` standard deviations: the
    plain fit's, or the robust cost's own at that point where larger, as they are by 30-40 times where
    the nuisance span is projected out; four of the plain fit's alone took 4-7 steps to cross them),
    the same likelihood-ratio rule as the global search; the chosen fit kept only if its residual
    passes :func:`excess_residual_z`.

    The ring (:func:`ring_checked`, 16 simulations) checks the fit that is published; the other one
    only enters the statistic, and is ringed too where the statistic lies within :data:`FLIP_MARGIN`
    of the threshold (a fit stopped a few standard deviations short moves it by about that much).
    The choice is made again after each ring, so it is the one the ringed fits give. A fit at a
    search bound is ringed in any case (a lower point may lead it off the bound; else it fails)."""
    f_plain, c_plain = unchecked_fit(m_plain, x0, box, config)
    if not (f_plain.success and c_plain):
        return None
    f_rob, c_rob = unchecked_fit(m_rob, f_plain.x, box, config, sd_radius(f_plain, ROBUST_START_SD), ROBUST_START_SD)
    if not (f_rob.success and c_rob):
        return None
    models, fits, ringed = (m_plain, m_rob), [f_plain, f_rob], [False, False]
    while True:
        stat = likelihood_ratio(m_plain, fits[0], m_rob, fits[1])
        robust = prefers_robust(stat, config.model_error_threshold)
        close = abs(stat - config.model_error_threshold) <= FLIP_MARGIN
        todo = [i for i in (int(robust), int(not robust))
                if not ringed[i] and (i == int(robust) or close or not usable(fits[i], True, box, config))]
        if not todo:
            break
        for i in todo:
            fit = ring_checked(models[i], fits[i], True, box, config)
            if fit is None:
                return None
            fits[i], ringed[i] = fit, True
    model, fit = models[int(robust)], fits[int(robust)]
    if not excess_residual_z(model, fit) <= config.local_accept_z:
        return None
    return finish(Fitted(sim, injection, fit, True, m_plain.evaluations + m_rob.evaluations, box, robust, stat, config),
                  Evidence(adequacy=plain_adequacy(m_plain, fits[0], config), other=fits[1 - int(robust)].x,
                           model=model, check_preload=True))


def complement_fit(sim: FastSimulator, injection: Injection, config: IdentConfig, box: Box, model: CostModel,
                   fit: LocalFit) -> tuple[np.ndarray | None, int]:
    """The estimate (N/V, µm) of the other cost (robust for a plain ``model``, plain for a robust one)
    on the same samples, by a local fit from ``fit``, and its simulations; None where it fails. The
    two differ by about as much as a model error moves them (:mod:`estimator.ident.fit.mismatch`)."""
    other = _cost_model(sim, injection, config, not model.robust)
    if other.n == model.n:
        other.share_basis(model)
    start_sd = ROBUST_START_SD if other.robust else 0.0
    radius = sd_radius(fit, ROBUST_START_SD) if other.robust else None
    f, _converged = unchecked_fit(other, fit.x, box, config, radius, start_sd)
    return (f.x if f.success else None), other.evaluations


@dataclass(slots=True)
class Fitted:
    """A local fit of one injection (N/V, µm) and how it was reached: on ``sim``, within ``box``,
    ``converged`` or not, after ``evaluations`` simulations, with the ``robust`` or the plain cost;
    ``stat`` the likelihood ratio of the two costs (NaN where not computed)."""

    sim: FastSimulator
    injection: Injection
    fit: LocalFit
    converged: bool
    evaluations: int
    box: Box
    robust: bool
    stat: float
    config: IdentConfig


@dataclass(slots=True)
class Evidence:
    """What else is known about a fit.

    ``adequacy`` is the plain model's test on these samples; ``other`` the other cost's estimate
    (see :mod:`estimator.ident.fit.mismatch`); ``structure`` the plain residual's statistic where
    ``adequacy`` was not tested now. ``model``: the fit's cost model, for the preload force's
    uncertainty and (``check_preload``) the test of the header's preload force
    (:func:`~estimator.ident.fit.mismatch.preload_check`); ``preload_shift`` (N/V, µm) and
    ``preload_wrong`` are that move and verdict as a recent test of this injector found them, where it
    was not tested now; ``current_cov`` (N/V, µm) the measured current's noise as a recent estimate of
    this injector sized it."""

    adequacy: Adequacy | None = None
    other: np.ndarray | None = None
    model: CostModel | None = None
    structure: float | None = None
    check_preload: bool = False
    preload_shift: np.ndarray | None = None
    preload_wrong: bool = False
    current_cov: np.ndarray | None = None


@dataclass(slots=True)
class _Judged:
    """What :func:`finish` works out before the status: mismatch and its kinds, the preload test, the
    covariance (N/V, µm) with the bias part on its own."""

    mismatch: bool
    disagrees: bool
    wrong_preload: bool
    check: PreloadCheck | None
    preload_shift: np.ndarray | None
    structure: float
    bias: np.ndarray
    cov_x: np.ndarray
    current_cov: np.ndarray | None
    evaluations: int


def finish(f: Fitted, ev: Evidence | None = None, predict: bool = True) -> Estimate:
    """Turn a local fit into an Estimate with status and (``predict``) the plateau stroke.

    A robust fit, or a plain one that fails the adequacy test, is a ``model_mismatch`` whose covariance
    includes the model error; so is a plain fit whose samples point to another preload force, its
    covariance widened by the move that force implies (also where the force is only suspect, without
    the status). Where the preload force's sensitivity is simulated, the measured current's noise is
    sized too (:func:`~estimator.ident.fit.mismatch.sensitivities`) and enters the covariance; elsewhere
    ``ev.current_cov`` does. Contact and opening times are those of the fitted window; the stroke needs
    one more, longer simulation (see :func:`predict_valve`)."""
    if not f.fit.success:
        return rejected("simulation failed at the optimum", f.evaluations)
    ev = ev if ev is not None else Evidence()
    j = _judge(f, ev)
    status, msg, cov_x = _verdict(f, ev, j)
    fit, x = f.fit, f.fit.x
    tc, to, stroke = fit.t_contact_s, fit.t_open_s, float("nan")
    if predict:
        tc, to, stroke = predict_valve(f.sim, f.injection, x[0], x[1] / UM_PER_M)
    d, _ = fit.directions
    other = ev.other
    diff = x - other if j.mismatch and other is not None and np.all(np.isfinite(other)) else np.zeros(2)
    excess = excess_residual_z(ev.model, fit) if j.mismatch and ev.model is not None else float("nan")
    check = j.check
    return Estimate(float(x[0]), float(x[1] / UM_PER_M), cov_to_si(cov_x), fit.paper_cost_vs, fit.criterion,
                    j.evaluations + 1, status, msg, f.robust, f.stat, fit.sigma_v, tc, to, stroke, fit.jtj, d,
                    j.structure, j.bias, diff, j.mismatch, excess, check.chi2 if check is not None else float("nan"),
                    check.delta_f_n if check is not None else float("nan"),
                    None if j.preload_shift is None else np.array(j.preload_shift, dtype=float), j.wrong_preload,
                    j.current_cov)


def _judge(f: Fitted, ev: Evidence) -> _Judged:
    """Mismatch, the preload force's test and the covariance of a successful fit."""
    config, model, x, evaluations = f.config, ev.model, f.fit.x, f.evaluations
    mismatch = f.robust or (ev.adequacy is not None and not ev.adequacy.adequate)
    # the robust fit of the longer window explains the plain window much worse than the plain fit: the
    # samples after the plain window pull the estimate elsewhere, which no noise does
    disagrees = (not f.robust and model is not None and config.window_disagreement_chi2 > 0 and math.isfinite(f.stat)
                 and f.stat < -config.window_disagreement_chi2)
    mismatch = mismatch or disagrees
    check = None
    preload_shift, preload_wrong, current_cov = ev.preload_shift, ev.preload_wrong, ev.current_cov
    # the preload force's sensitivity (four simulations) serves its uncertainty and its test alike
    checking = ev.check_preload and not mismatch and model is not None and config.preload_check_chi2 > 0
    sens = None
    if model is not None and (checking or config.preload_rel_sigma > 0):
        sens, fresh = sensitivities(model, f.fit)
        evaluations += 4
        if fresh is not None:
            current_cov, evaluations = fresh, evaluations + 1
    if checking and model is not None:
        check = preload_check(sens, f.fit, model.n, config.preload_check_chi2)
        preload_shift = check.shift if check is not None and check.suspect else None
        preload_wrong = check is not None and check.inconsistent
    if f.robust:        # the robust cost's own model error covers it
        preload_shift, preload_wrong = None, False
    wrong_preload = preload_wrong and preload_shift is not None
    mismatch = mismatch or wrong_preload
    structure = ev.adequacy.structure if ev.adequacy is not None else ev.structure
    structure = float("nan") if structure is None else structure
    bias = model_error_cov(x, ev.other, config, structure) if mismatch else np.zeros((2, 2))
    if preload_shift is not None:    # the move the samples' own preload force implies: a bias
        bias = bias + np.outer(preload_shift, preload_shift)
    if not f.sim.params.calibration.zero:   # what a calibrated parameter set leaves uncertain: a bias too
        bias = bias + f.sim.params.calibration.cov(float(x[0]))
    cov_x = f.fit.cov_x + bias
    if current_cov is not None:   # the measured current's noise: noise, not a bias
        cov_x = cov_x + current_cov
    if config.preload_rel_sigma > 0:
        cov_x = cov_x + preload_cov(sens, f.injection.f_open_n, config.preload_rel_sigma)
    return _Judged(mismatch, disagrees, wrong_preload, check, preload_shift, structure, bias, cov_x, current_cov,
                   evaluations)


def _verdict(f: Fitted, ev: Evidence, j: _Judged) -> tuple[Status, str, np.ndarray]:
    """The status, its message and the covariance (widened over the box for a mismatch at a bound)."""
    config, cov_x = f.config, j.cov_x
    if f.box.at_bound(f.fit.x, bound_tolerance(config)):
        status, msg = Status.AT_BOUND, "estimate at a search bound"
        if j.mismatch:   # the truth may lie anywhere beyond the bound: sigma of a uniform over the range
            cov_x = cov_x + np.diag(np.square(f.box.hi - f.box.lo) / 12.0)
    elif not f.converged:
        status, msg = Status.NOT_CONVERGED, "line searches did not converge"
    elif j.mismatch:
        status = Status.MODEL_MISMATCH
        if ev.adequacy is not None and not ev.adequacy.adequate:
            msg = ev.adequacy.reason
        elif j.disagrees and ev.model is not None:
            msg = (f"the samples after the {US_PER_S * ev.model.window_s:.0f} µs window disagree with the fit (likelihood "
                   f"ratio {f.stat:.0f}): model cannot explain the whole trace")
        elif j.wrong_preload:
            msg = j.check.reason(f.injection.f_open_n) if j.check is not None else (
                "the header's preload force disagrees with this injector's samples (as last tested)")
        else:
            msg = "model cannot explain the samples (robust cost: model error in the nuisance span)"
    elif cov_x[1, 1] > config.sigma_limit_lh_um ** 2:
        status, msg = Status.UNCERTAIN, (f"sigma(L_h) {np.sqrt(cov_x[1, 1]):.2f} µm above the limit "
                                         f"{config.sigma_limit_lh_um:.2f} µm")
    else:
        status, msg = Status.OK, ""
    return status, msg, cov_x
