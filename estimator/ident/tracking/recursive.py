"""The recursive per-injection estimator: warm-started line searches + a drift-aware Kalman filter.

Per injection (:func:`update`, pure: state in, state out):

1. Validity: a bad trace is rejected with its reason; the filter is unchanged.
2. Raw estimate: from the filter's prediction for this injection (drift rate and temperature slope
   included), line searches along the two conjugate directions kept from the previous injection,
   then a Gauss–Newton check. Cold start (first injection, or re-acquisition): the profile search
   of :mod:`estimator.ident.fit.cold_start`.
3. Filter (:mod:`estimator.ident.tracking.kalman`): time-aware process noise (per injection and per second
   since the injector's last accepted injection), a learned drift rate and temperature slope. An
   innovation inside the chi-square gate updates the filter. One outside it is *in doubt*:

   - a fit the plain model cannot explain (model-error statistic far above its threshold) is a
     glitch: rejected, counted, the published estimate is the filter's;
   - otherwise the injection is kept pending and published with status ``unconfirmed``: with its
     own raw estimate if the innovation is beyond anything noise does (``raw_publish_chi2``), else
     with the filter updated by it (published, not committed). If the next injection agrees with the filter, the pending one was an outlier
     (counted). If it disagrees too, and a jump of N_u, of L_h or of both at the pending injection
     (generalised likelihood ratio) followed by the filter's drift explains both, the jump is
     taken: the filter forgets the jumped components and processes both injections. A ramp or a
     step is thus followed from the second injection on, and nothing stale is published as ``ok``.
   - ``max_consecutive_outliers`` doubts in a row that agree with nothing: re-acquire (restart the
     filter at the latest raw estimate).
4. Model-error mode: the residual's energy in the nuisance span (see :mod:`estimator.ident.fit.cost`)
   decides per injector, with hysteresis, whether to use the robust (projected) cost.
5. Status: ``ok`` only for a converged estimate whose sigma(L_h) is within ``sigma_limit_lh_um``;
   ``uncertain`` above it.
"""

from __future__ import annotations

import contextlib
import math
import weakref
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from estimator.choices import Robust
from estimator.errors import EstimatorError
from estimator.ident.config import TrackerConfig
from estimator.ident.coords import NuLh
from estimator.ident.estimate import Estimate, rejected
from estimator.ident.fit.cold_start import bound_tolerance
from estimator.ident.fit.cost import CostModel, plain_model_error
from estimator.ident.fit.idle_stroke import (
    Evidence,
    Fitted,
    check_injection,
    complement_fit,
    effective_window_s,
    finish,
    identify,
    predict_valve,
    search_box,
)
from estimator.ident.fit.local_fit import next_steps, refine
from estimator.ident.fit.mismatch import model_error_cov, plain_adequacy
from estimator.ident.fit.model_selection import likelihood_ratio
from estimator.ident.fit.search import Box
from estimator.ident.measurement import Injection
from estimator.ident.status import Status
from estimator.ident.tracking import kalman
from estimator.ident.tracking.tracker_state import (
    CARRIED,
    Pending,
    TrackerState,
    process_noise,
    state_bounds,
    wear_variance,
)
from estimator.model.fast_sim import FastSimulator, remember
from estimator.units import UM_PER_M, US_PER_S

LOCAL_ACCEPT_MARGIN = 3.0      # a mismatched injector's re-acquisition keeps a local fit within 3x its usual residual excess
ROBUST_CHECK_EVERY = 8         # in robust mode, every 8th injection also fits the plain model (model-error test)
PRELOAD_CHECK_EVERY = 8        # every 8th warm update tests the header's preload force (four simulations)


@dataclass
class TrackResult:
    """Output of one update: the raw estimate, the published one, and what happened.

    ``outliers`` counts injections judged outliers by this update: the current one (status
    ``rejected``) or an earlier ``unconfirmed`` one that the current injection did not confirm;
    ``accepted`` those it took into the filter: this one, and an earlier ``unconfirmed`` one it
    confirmed. An ``unconfirmed`` injection is counted once, when the next one decides.
    """

    raw: Estimate
    nu_n_per_v: float
    lh_m: float
    sigma_nu: float
    sigma_lh_m: float
    status: Status
    reason: str
    evaluations: int
    t_contact_s: float = float("nan")
    t_open_s: float = float("nan")
    stroke_m: float = float("nan")
    outliers: int = 0
    rate_n_per_v_s: float = float("nan")
    slope_n_per_v_degc: float = float("nan")
    accepted: int = 0
    failed_probe: bool = False   # rejected: the model failed at a drive beyond the levels it was checked at

    def filtered_dict(self) -> dict[str, Any]:
        """The published estimate with units in the keys."""
        def f(v: float, s: float = 1.0) -> float | None:
            return None if not math.isfinite(v) else round(v * s, 6)

        return {"nu_n_per_v": f(self.nu_n_per_v), "lh_um": f(self.lh_m, UM_PER_M),
                "sigma_nu_n_per_v": f(self.sigma_nu), "sigma_lh_um": f(self.sigma_lh_m, UM_PER_M),
                "status": self.status.value, "reason": self.reason, "t_contact_us": f(self.t_contact_s, US_PER_S),
                "t_open_us": f(self.t_open_s, US_PER_S), "stroke_um": f(self.stroke_m, UM_PER_M),
                "rate_n_per_v_per_s": f(self.rate_n_per_v_s), "slope_n_per_v_per_degc": f(self.slope_n_per_v_degc)}


def _robust_cov(est: Estimate, config: TrackerConfig) -> np.ndarray:
    """The raw estimate's measurement covariance for the filter in (N/V, µm): its noise part, with the
    bias floor of robust mode. A mismatched estimate's model error is left out here: it is the same
    for every injection of the injector (a bias, not noise), so the filter follows changes as closely
    as on an adequate model, and the model error is added to what is published (:func:`_widen`)."""
    cov = est.cov_um - est.model_error_cov
    if est.robust:
        cov = cov + np.diag(np.square(config.robust_floor))
    result: np.ndarray = cov
    return result


def _warm_estimate(state: TrackerState, x0: np.ndarray, inj: Injection, sim: FastSimulator, config: TrackerConfig,
                   box: Box) -> Estimate:
    ic = config.ident
    model = CostModel(sim, inj, effective_window_s(ic, inj, state.robust), ic.norm, state.robust)
    fit, converged, _ = refine(model, x0, np.array(state.directions), np.array(state.steps), box, ic,   # refine clips x0
                               max_cycles=config.warm_cycles, batched=True)
    if not converged and state.robust and fit.success and not box.at_bound(fit.x, bound_tolerance(ic)):
        # a mismatched injector's optimum moves with the operating point (its model error does): the
        # search goes on from where it stopped, cheaper than a re-acquisition (≈ 3 ms)
        d, w = fit.directions
        fit, converged, _ = refine(model, fit.x, d, next_steps(fit.sigma_v, w, (float(ic.tol[0]), float(ic.tol[1]))),
                                   box, ic, max_cycles=config.warm_cycles, batched=True)
    stat = float("nan")
    adequacy, other, extra = None, None, 0
    if fit.success and not state.robust:   # the plain residual against the nuisance span (normal equations)
        stat = plain_model_error(fit.residual[: model.n], model.current, model.dt, fit.sigma_v)
        adequacy = plain_adequacy(model, fit, ic)
        if not adequacy.adequate:     # size the model error: the robust estimate of the same samples
            other, extra = complement_fit(sim, inj, ic, box, model, fit)
    elif fit.success and state.updates % ROBUST_CHECK_EVERY == 0:
        # is the model error still there? the likelihood ratio of a plain fit against the robust one,
        # as at a cold start (the plain residual at the robust estimate would overstate it)
        plain = CostModel(sim, inj, effective_window_s(ic, inj, False), ic.norm, False)
        plain.share_basis(model)
        fit_p, _, _ = refine(plain, x0, np.array(state.directions), np.array(state.steps), box, ic,
                             max_cycles=config.warm_cycles, batched=True)
        stat = likelihood_ratio(plain, fit_p, model, fit)
        extra = plain.evaluations
        if fit_p.success:
            adequacy, other = plain_adequacy(plain, fit_p, ic), fit_p.x
    elif fit.success:    # robust, untested this time: the model error as last sized
        other = fit.x - np.asarray(state.model_error_d)
    # the published prediction is made once, for the published estimate (``publish``); the header's
    # preload force is tested every PRELOAD_CHECK_EVERY-th update, an agreeing verdict held in between.
    # A disagreeing one is tested again at the next update: held, one crossing of the threshold (its
    # false-alarm rate, about 1 in 10,000 tests) would count as mismatch_on_after injections in a row
    check = not state.robust and (state.updates % PRELOAD_CHECK_EVERY == 0 or state.preload_wrong)
    held = None if check or state.preload_shift is None else np.array(state.preload_shift)
    held_current = None if check or state.current_noise_cov is None else np.array(state.current_noise_cov)
    return finish(Fitted(sim, inj, fit, converged, model.evaluations + extra, box, state.robust, stat, ic),
                  Evidence(adequacy=adequacy, other=other, model=model, structure=state.model_error_structure,
                           check_preload=check, preload_shift=held, preload_wrong=state.preload_wrong and not check,
                           current_cov=held_current), predict=False)


def _cold_estimate(state: TrackerState, inj: Injection, sim: FastSimulator, config: TrackerConfig) -> Estimate:
    """A fresh estimate of ``inj`` (no warm start). For an injector known to be mismatched, the
    local-first fit starts from the filter's point and is kept if its residual exceeds white noise by
    no more than :data:`LOCAL_ACCEPT_MARGIN` times the injector's usual excess (it never passes the
    white-noise check, so each re-acquisition would otherwise run the global search, ≈ 17 ms); the ring
    around it still guards against another valley."""
    mode = Robust.ON if state.robust else Robust(config.ident.robust)
    ident = config.ident if mode == config.ident.robust else replace(config.ident, robust=mode)
    start = None
    if state.mismatch and state.initialized and state.excess_z is not None and math.isfinite(state.x[0]) \
            and math.isfinite(state.x[1]) and ident.cold_start == "local-first":
        ident = replace(ident, local_accept_z=max(ident.local_accept_z, LOCAL_ACCEPT_MARGIN * state.excess_z))
        start = np.array(state.x[:2], dtype=float)
    return identify(inj, sim, ident, start)


_BOXES: weakref.WeakKeyDictionary[FastSimulator, dict[Any, Any]] = weakref.WeakKeyDictionary()
_BOXES_PER_SIMULATOR = 16


def box_and_noise(config: TrackerConfig, sim: FastSimulator, f_open_n: float) -> tuple[Box, kalman.ProcessNoise]:
    """:func:`search_box` and :func:`process_noise`, kept per simulator, configuration and F_open (N)
    (a few per injector; they went into every update: ≈ 8 µs). Weakly keyed: a simulator that leaves
    its pool is not held here; at most ``_BOXES_PER_SIMULATOR`` per simulator (oldest out)."""
    memo = _BOXES.get(sim)
    if memo is None:
        memo = _BOXES[sim] = {}
    key = (config, float(f_open_n))
    hit = memo.get(key)
    if hit is None:
        box = search_box(config.ident, sim, f_open_n)   # shared between updates (nothing writes a Box)
        hit = remember(memo, key, (box, process_noise(config, box)), _BOXES_PER_SIMULATOR)
    return hit


def _known(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _temperature(inj: Injection) -> float | None:
    t = inj.temperature_c
    return float(t) if math.isfinite(t) else None   # NaN: not measured (the codec's reading of the wire)


def _interval(config: TrackerConfig, t_from: float | None, t_to: float | None) -> float:
    """Seconds between two injections: measured when both times are known, else the default."""
    if t_from is None or t_to is None:
        return config.default_interval_s
    return min(max(t_to - t_from, 0.0), config.max_interval_s)


def _delta_temperature(t_from: float | None, t_to: float | None) -> float | None:
    """The temperature change in degC, None unless both ends were measured."""
    return None if t_from is None or t_to is None else t_to - t_from


def update(state: TrackerState, inj: Injection, sim: FastSimulator,
           config: TrackerConfig, unchecked_drive: bool = False) -> tuple[TrackerState, TrackResult]:
    """One injection through the recursive estimator (pure: ``state`` is not modified).
    ``unchecked_drive``: the injection was driven beyond the levels the injector's model was checked
    at (a drive correction's probe, see :meth:`~estimator.drive.correction.DriveCompensator.unchecked`);
    an injector its model explained that the model fails there is not mismatched: the injection is
    rejected (:func:`_failed_probe`) and the correction steps back."""
    st = object.__new__(TrackerState)    # copy.copy(state) in 0.45 instead of 1.9 µs: the fields as they are
    st.__dict__.update(state.__dict__)
    st.x, st.p = list(state.x), [list(r) for r in state.p]
    st.updates += 1
    box, noise = box_and_noise(config, sim, inj.f_open_n)
    now, temp = _known(inj.time_s), _temperature(inj)
    held = _held(st, now, temp, config, noise)
    problem = check_injection(inj, sim, config.ident)
    if problem:
        st.rejected += 1
        return st, publish(_widen(held, st, config, sim), rejected(problem), Status.REJECTED, problem, sim, inj, predict=False)
    inj = inj.through_chain(sim.params.chain)   # once: the cold start and the valve prediction see it too

    cold = not (st.initialized and math.isfinite(st.x[0]) and math.isfinite(st.x[1]))   # a prior counts
    if cold:
        raw = _cold_estimate(st, inj, sim, config)
    else:
        assert held is not None   # initialized: the filter holds a state
        raw = _warm_estimate(st, held[0][:2], inj, sim, config, box)
        if unchecked_drive and raw.mismatch and not (st.mismatch or st.robust):
            return _failed_probe(st, raw, held, inj, sim, config)
    if raw.status == Status.REJECTED:
        st.rejected += 1
        return st, publish(_widen(held, st, config, sim), raw, Status.REJECTED, raw.message, sim, inj, predict=False)
    if not cold and (raw.status == Status.NOT_CONVERGED or (raw.status == Status.AT_BOUND and not st.robust)):
        # the warm searches ran out of cycles (the injector moved more than expected), or the plain
        # model ran into a bound, which is how it absorbs a model error: decide afresh
        raw = _cold_estimate(st, inj, sim, config)
    # the hysteresis sees a cold estimate too: one that chose the robust cost switches the mode at once
    restart = _robust_hysteresis(st, raw, config, cold) or cold
    if restart and raw.robust != st.robust:
        raw = _cold_estimate(st, inj, sim, config)
    if raw.current_noise_cov is not None:
        st.current_noise_cov = raw.current_noise_cov.tolist()
    z = raw.point.array()
    r = _robust_cov(raw, config)
    if not all(map(math.isfinite, r.ravel().tolist() + z.tolist())):
        st.rejected += 1
        return st, publish(_widen(held, st, config, sim), raw, Status.REJECTED, "no curvature at the optimum", sim, inj, predict=False)
    if restart:
        _restart(st, z, r, now, temp, config)
        reason = "" if cold else "restarted (model-error mode changed)"
        return _accepted(st, raw, r, sim, inj, config, reason)
    assert held is not None   # not cold: the filter holds a state
    return _filtered(st, raw, z, r, held, Moment(now, temp), inj, sim, config, noise)


def _failed_probe(st: TrackerState, raw: Estimate, held: tuple[np.ndarray, np.ndarray], inj: Injection,
                  sim: FastSimulator, config: TrackerConfig) -> tuple[TrackerState, TrackResult]:
    """An injection at a drive level the model was never checked at, which the model cannot explain,
    of an injector it explains: what fails is the model's extrapolation to that level, not the part.
    The injection is rejected without counting toward a run of mismatched injections (nor the robust
    mode's), the filter's prediction is published, and ``failed_probe`` tells the drive correction to
    step back into the levels the model holds at (a model learned at the standard drive and first
    driven 5 % above it at 266 N failed there with structure chi2 64, and the same part at the
    standard drive did not)."""
    st.rejected += 1
    how = f" (structure chi2 {raw.structure_chi2:.0f})" if math.isfinite(raw.structure_chi2) else ""
    reason = (f"the model does not explain this injection at a drive beyond the levels it was checked "
              f"at{how}: the drive correction steps back")
    res = publish(_widen(held, st, config, sim), raw, Status.REJECTED, reason, sim, inj, predict=True)
    res.failed_probe = True
    return st, res


@dataclass(slots=True)
class Moment:
    """When an injection was (s, None if unknown) and at what fuel temperature (degC, None if unknown)."""

    time_s: float | None
    temperature_c: float | None


def _filtered(st: TrackerState, raw: Estimate, z: np.ndarray, r: np.ndarray, held: tuple[np.ndarray, np.ndarray],
              at: Moment, inj: Injection, sim: FastSimulator, config: TrackerConfig,
              noise: kalman.ProcessNoise) -> tuple[TrackerState, TrackResult]:
    """The raw estimate ``z`` (covariance ``r``) against the filter's prediction ``held``: inside the
    gate it updates the filter; outside, a glitch the model cannot explain is rejected, otherwise the
    injection is in doubt (:func:`_in_doubt`)."""
    now, temp = at.time_s, at.temperature_c
    x_pred, p_pred = held
    inn = kalman.innovation(x_pred, p_pred, z, r)
    if not (st.mismatch or st.robust) and raw.mismatch and inn.d2 > config.gate_chi2:
        # an injector the model explained, and an injection it cannot explain that disagrees: a glitch.
        # It counts towards the injector's run of mismatched injections: a part swapped under its id
        # looks like this first, and the fit that follows must not be published ok on its own
        st.rejected += 1
        st.mismatch_run += 1
        reason = (f"outlier (innovation chi2 {inn.d2:.1f} > {config.gate_chi2:.1f}, the model mismatched "
                  f"on this injection only)")
        return st, publish(_widen(held, st, config, sim), raw, Status.REJECTED, reason, sim, inj, predict=True,
                           outliers=1)
    if inn.d2 <= config.gate_chi2:
        outliers = 0
        if st.pending is not None:     # the injection in doubt was not confirmed: an outlier
            outliers, st.pending = 1, None
            st.rejected += 1
        st.doubts = 0
        x, p = kalman.update(x_pred, p_pred, z, r)
        _store(st, x, p, now, temp, config)
        return _accepted(st, raw, r, sim, inj, config, "", outliers)
    if not st.robust and (raw.robust or (math.isfinite(raw.model_error_stat) and
                                         raw.model_error_stat > config.ident.model_error_threshold)):
        # the plain model cannot explain this injection and it disagrees with the filter: a glitch
        st.rejected += 1
        st.mismatch_run += 1
        reason = (f"outlier (innovation chi2 {inn.d2:.1f} > {config.gate_chi2:.1f}, model error "
                  f"{raw.model_error_stat:.0f})")
        return st, publish(_widen(held, st, config, sim), raw, Status.REJECTED, reason, sim, inj, predict=True, outliers=1)
    return _in_doubt(st, raw, z, r, held, inn.d2, at, inj, sim, config, noise)


def _in_doubt(st: TrackerState, raw: Estimate, z: np.ndarray, r: np.ndarray, held: tuple[np.ndarray, np.ndarray],
              d2: float, at: Moment, inj: Injection, sim: FastSimulator, config: TrackerConfig,
              noise: kalman.ProcessNoise) -> tuple[TrackerState, TrackResult]:
    """An injection outside the gate (innovation chi-square ``d2``) that the model explains: with an
    earlier one in doubt, a jump both confirm is taken (or the earlier one was an outlier); too many
    doubts in a row re-acquire; otherwise it is kept pending and published ``unconfirmed``."""
    now, temp = at.time_s, at.temperature_c
    x_pred, p_pred = held
    if st.pending is not None:
        taken = _confirm_jump(st, z, r, now, temp, config, noise)
        if taken is not None:
            comps = " and ".join({kalman.NU: "N_u", kalman.LH: "L_h"}[c] for c in taken)
            return _accepted(st, raw, r, sim, inj, config, f"change of {comps} confirmed by two injections",
                             confirmed=1)
        st.rejected += 1          # the earlier doubt agrees with nothing: an outlier
        outliers = 1
    else:
        outliers = 0
    st.doubts += 1
    if st.doubts >= config.max_consecutive_outliers:
        _restart(st, z, r, now, temp, config)
        return _accepted(st, raw, r, sim, inj, config, f"re-acquired after {st.doubts} injections in doubt",
                         outliers)
    st.pending = Pending(z.tolist(), r.tolist(), now, temp, inj.counter)
    if d2 > config.raw_publish_chi2:
        # beyond anything noise does: a change (or a glitch the model fits); its own estimate is the best guess
        best, whose = (np.concatenate([z, x_pred[2:]]), _embed(r, p_pred)), "this injection's own estimate"
    else:   # marginal: as likely a noise tail as a small change: the filter updated with it (not committed)
        best, whose = kalman.update(x_pred, p_pred, z, r), "the filter's estimate with it"
    reason = f"in doubt (innovation chi2 {d2:.1f} > {config.gate_chi2:.1f}): {whose}"
    return st, publish(_widen(best, st, config, sim), raw, Status.UNCONFIRMED, reason, sim, inj, predict=True, outliers=outliers)


def _robust_hysteresis(st: TrackerState, raw: Estimate, config: TrackerConfig, cold: bool) -> bool:
    """Update the model-error mode; True if it switched (the filter must restart).

    Only the very first estimate switches at once (nothing to compare it with); later, a single
    injection with model error (a glitch, or a cold re-estimate that chose the robust cost) counts
    toward ``robust_on_after`` like any other. In robust mode every ``ROBUST_CHECK_EVERY``-th
    injection is tested; a clean test counts for that many injections toward ``robust_off_after``.
    """
    stat = raw.model_error_stat
    if not st.robust:
        st.model_error_run = st.model_error_run + 1 if (raw.robust or (math.isfinite(stat) and
                                                        stat > config.ident.model_error_threshold)) else 0
        if (cold and raw.robust) or st.model_error_run >= config.robust_on_after:
            st.robust, st.model_error_run, st.clean_run = True, 0, 0
            return True   # estimates of the other cost are biased differently: restart the filter
        return False
    if not math.isfinite(stat):
        return False                    # not tested on this injection
    clean = stat <= config.ident.model_error_threshold
    st.clean_run = st.clean_run + ROBUST_CHECK_EVERY if clean else 0
    if st.clean_run >= config.robust_off_after:
        st.robust, st.clean_run = False, 0
        return True
    return False


def _held(st: TrackerState, now: float | None, temp: float | None, config: TrackerConfig,
          noise: kalman.ProcessNoise) -> tuple[np.ndarray, np.ndarray] | None:
    """The filter predicted to this injection (None before the first estimate)."""
    if not st.initialized or not all(map(math.isfinite, st.x)):
        return None
    return kalman.predict(np.array(st.x), np.array(st.p), _interval(config, st.time_s, now),
                          _delta_temperature(st.temperature_c, temp), noise)


def _store(st: TrackerState, x: np.ndarray, p: np.ndarray, now: float | None, temp: float | None,
           config: TrackerConfig) -> None:
    """Keep the filter's state (the drift rate, temperature slope and wear rate held within
    :func:`state_bounds`)."""
    rate_max, slope_lo, slope_hi, wear_max = state_bounds(config)
    x = np.array(x, dtype=float)
    x[kalman.RATE] = min(max(x[kalman.RATE], -rate_max), rate_max)
    x[kalman.SLOPE] = min(max(x[kalman.SLOPE], slope_lo), slope_hi)
    x[kalman.WEAR] = min(max(x[kalman.WEAR], -wear_max), wear_max)
    st.x, st.p = x.tolist(), p.tolist()
    if now is not None:
        st.time_s = now
    if temp is not None:
        st.temperature_c = temp
    st.initialized = True


def _restart(st: TrackerState, z: np.ndarray, r: np.ndarray, now: float | None, temp: float | None,
             config: TrackerConfig) -> None:
    x, p = kalman.initial(z, r, (config.max_rate_n_per_v_s / 3.0) ** 2, config.slope_n_per_v_degc,
                          config.slope_sigma ** 2, wear_variance(config))
    if st.initialized and np.all(np.isfinite(st.x)):   # keep what was learned of the temperature slope
        x[kalman.SLOPE], p[kalman.SLOPE, kalman.SLOPE] = st.x[kalman.SLOPE], st.p[kalman.SLOPE][kalman.SLOPE]
    elif not st.initialized:   # a state carried over to a refined model: its slope and wear rate
        for k in CARRIED:
            if math.isfinite(st.x[k]):
                x[k], p[k, k] = st.x[k], st.p[k][k]
    st.pending, st.doubts = None, 0
    st.time_s = st.temperature_c = None
    _store(st, x, p, now, temp, config)


def _confirm_jump(st: TrackerState, z: np.ndarray, r: np.ndarray, now: float | None, temp: float | None,
                  config: TrackerConfig, noise: kalman.ProcessNoise) -> tuple[int, ...] | None:
    """Take a jump at the pending injection if it and this one agree on it; the components, or None."""
    pend = st.pending
    assert pend is not None
    x, p = kalman.predict(np.array(st.x), np.array(st.p), _interval(config, st.time_s, pend.time_s),
                          _delta_temperature(st.temperature_c, pend.temperature_c), noise)
    zp, rp = np.array(pend.z), np.array(pend.r)
    comps = kalman.jump_components(kalman.innovation(x, p, zp, rp))
    for candidate in dict.fromkeys([comps, (kalman.NU, kalman.LH)]):
        xj, pj = kalman.update(x, kalman.release(p, candidate, noise.max_var), zp, rp)
        xc, pc = kalman.predict(xj, pj, _interval(config, pend.time_s, now),
                                _delta_temperature(pend.temperature_c, temp), noise)
        xc, pc, _, ok = kalman.gated_update(xc, pc, z, r, config.gate_chi2)
        if ok:
            st.pending, st.doubts = None, 0
            _store(st, xc, pc, now if now is not None else pend.time_s, temp, config)
            return candidate
    return None


def _embed(r: np.ndarray, p: np.ndarray) -> np.ndarray:
    """A full-state covariance with ``r`` for (N_u, L_h) and ``p``'s drift and slope blocks."""
    q = np.array(p, copy=True)
    q[:2, :] = 0.0
    q[:, :2] = 0.0
    q[:2, :2] = r
    return q


MODEL_ERROR_WEIGHT = 0.2   # weight of the newest injection in an injector's model-error sizing


def _note_mismatch(st: TrackerState, raw: Estimate, config: TrackerConfig) -> None:
    """Keep the injector's model-mismatch flag: set by its first estimate if that is mismatched, else by
    ``mismatch_on_after`` mismatched accepted injections in a row; cleared after ``mismatch_clear_after``
    adequate ones in a row. A test of the header's preload force, where one was made, replaces the
    last one's verdict."""
    if math.isfinite(raw.preload_chi2):
        st.preload_shift = None if raw.preload_shift is None else [float(v) for v in raw.preload_shift]
        st.preload_wrong = raw.preload_wrong
    if raw.mismatch:
        # the injector's model error is the same from one injection to the next, but each injection
        # sizes it with its own noise: a running mean square of the sizings (the first one alone at first)
        first = not st.mismatch
        st.mismatch_run += 1
        # the first estimate of an injector decides at once; later, one inadequate injection among
        # adequate ones is the test's false-alarm rate (about 1 in 1000), not this injector's model
        if st.mismatch or st.accepted <= 1 or st.mismatch_run >= config.mismatch_on_after:
            st.mismatch = True
        st.mismatch_clean = 0
        d = raw.model_error_d
        if np.any(d):
            old = np.zeros(2) if first else np.asarray(st.model_error_d)
            w = 1.0 if first else MODEL_ERROR_WEIGHT
            st.model_error_d = [float(v) for v in np.sign(d) * np.sqrt((1 - w) * old ** 2 + w * np.square(d))]
        if math.isfinite(raw.structure_chi2):
            prev = st.model_error_structure
            st.model_error_structure = float(raw.structure_chi2 if first or prev is None else
                                             (1 - MODEL_ERROR_WEIGHT) * prev + MODEL_ERROR_WEIGHT * raw.structure_chi2)
        if math.isfinite(raw.excess_z):
            prev = st.excess_z
            st.excess_z = float(raw.excess_z if first or prev is None else
                                (1 - MODEL_ERROR_WEIGHT) * prev + MODEL_ERROR_WEIGHT * raw.excess_z)
        return
    st.mismatch_run = 0
    if st.mismatch:
        st.mismatch_clean += 1
        if st.mismatch_clean >= config.mismatch_clear_after:
            st.mismatch, st.mismatch_clean, st.model_error_d = False, 0, [0.0, 0.0]
            st.model_error_structure = st.excess_z = None


def _widen(filt: tuple[np.ndarray, np.ndarray] | None, st: TrackerState,
           config: TrackerConfig, sim: FastSimulator) -> tuple[np.ndarray, np.ndarray] | None:
    """The filtered (state, covariance) to publish: while the injector's model is mismatched, its
    model-error covariance is added, for a calibrated parameter set the uncertainty the calibration
    leaves, and where the header's preload force is suspect the move the samples' own force implies.
    Each is the same for every injection of the injector, so averaging injections does not shrink
    them: the filter's own covariance would claim it did."""
    calibration = sim.params.calibration
    if filt is None or (not st.mismatch and calibration.zero and st.preload_shift is None):
        return filt
    x, p = filt
    q = np.array(p, copy=True)
    xi = x[:2]
    if st.mismatch:
        structure = st.model_error_structure if st.model_error_structure is not None else float("nan")
        q[:2, :2] += model_error_cov(xi, xi - np.asarray(st.model_error_d), config.ident, structure)
    if not calibration.zero:
        q[:2, :2] += calibration.cov(float(xi[0]))
    if st.preload_shift is not None:   # the move the samples' own preload force implies
        q[:2, :2] += np.outer(st.preload_shift, st.preload_shift)
    return x, q


def _accepted(st: TrackerState, raw: Estimate, r: np.ndarray, sim: FastSimulator, inj: Injection,
              config: TrackerConfig, reason: str, outliers: int = 0,
              confirmed: int = 0) -> tuple[TrackerState, TrackResult]:
    st.accepted += 1 + confirmed
    _note_mismatch(st, raw, config)
    _carry_search(st, raw, r, config)
    x, p = _widen((np.array(st.x), np.array(st.p)), st, config, sim)   # type: ignore[misc]
    status: Status
    if raw.status in (Status.AT_BOUND, Status.NOT_CONVERGED):
        status, reason = raw.status, reason or raw.message
    elif st.mismatch:
        status = Status.MODEL_MISMATCH
        reason = reason or raw.message or (f"model mismatch on this injector (the last {st.mismatch_clean} "
                                           f"injection(s) adequate, {config.mismatch_clear_after} clear it)")
    elif math.sqrt(max(p[1, 1], 0.0)) > config.ident.sigma_limit_lh_um:
        status = Status.UNCERTAIN   # judged on the filtered sigma: averaging can make a noisy injector ok
        reason = reason or (f"sigma(L_h) {math.sqrt(p[1, 1]):.2f} µm above the limit "
                            f"{config.ident.sigma_limit_lh_um:.2f} µm")
    else:
        status = Status.OK
    res = publish((x, p), raw, status, reason, sim, inj, predict=True, outliers=outliers)
    res.accepted = 1 + confirmed
    return st, res


def _carry_search(st: TrackerState, raw: Estimate, r: np.ndarray, config: TrackerConfig) -> None:
    """Directions and step sizes for the next injection's warm line searches.

    Directions: conjugate for the cost (eigenvectors of the Gauss–Newton matrix). Steps: two
    standard deviations of where the next optimum is expected along each: the filter's covariance,
    one injection's process noise and the raw estimate's own scatter.
    """
    (a, b), (c, d) = raw.jtj.tolist()
    if not (all(map(math.isfinite, (a, b, c, d))) and a * d - b * c > 1e-14 * a * d):
        return
    v = raw.directions.tolist()
    (e00, e01), (e10, e11) = r.tolist()
    e00 += st.p[0][0] + config.q_nu_n_per_v ** 2       # the filter's covariance, one injection's
    e01 += st.p[0][1]                                   # process noise, the raw estimate's scatter
    e10 += st.p[1][0]
    e11 += st.p[1][1] + config.q_lh_um ** 2
    steps = []
    for i in range(2):
        v0, v1 = v[0][i], v[1][i]
        var = v0 * (e00 * v0 + e01 * v1) + v1 * (e10 * v0 + e11 * v1)
        steps.append(min(max(2.0 * math.sqrt(max(var, 0.0)), 1e-3), 2.0))
    st.directions = v
    st.steps = steps


def publish(filt: tuple[np.ndarray, np.ndarray] | None, raw: Estimate, status: Status, reason: str,
             sim: FastSimulator | None, inj: Injection, predict: bool, outliers: int = 0) -> TrackResult:
    """The published result: ``filt`` = (state, covariance) to publish, None if nothing is known."""
    nan = float("nan")
    if filt is None:
        return TrackResult(raw, nan, nan, nan, nan, status, reason, raw.evaluations, outliers=outliers)
    x, p = filt
    pt, sig = NuLh.of(x), NuLh(math.sqrt(abs(float(p[0, 0]))), math.sqrt(abs(float(p[1, 1]))))
    tc = to = stroke = nan
    if (predict and pt.nu_n_per_v == raw.nu_n_per_v and pt.lh_m == raw.lh_m and math.isfinite(raw.stroke_m)):
        # a cold start's own prediction (only a predicted Estimate has a finite stroke), at this very point
        tc, to, stroke = raw.t_contact_s, raw.t_open_s, raw.stroke_m
    elif predict and sim is not None and math.isfinite(pt.nu_n_per_v) and math.isfinite(pt.lh_um):
        with contextlib.suppress(EstimatorError):   # e.g. a prior outside the simulator's N_u range: no prediction
            tc, to, stroke = predict_valve(sim, inj, pt.nu_n_per_v, pt.lh_m)
    return TrackResult(raw, pt.nu_n_per_v, pt.lh_m, sig.nu_n_per_v, sig.lh_m, status, reason,
                       raw.evaluations, tc, to, stroke, outliers, float(x[kalman.RATE]), float(x[kalman.SLOPE]))
