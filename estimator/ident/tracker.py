"""The recursive per-injection estimator: warm-started line searches + a random-walk Kalman filter.

Per injection (:func:`update`, pure: state in, state out):

1. Validity: a bad trace is rejected with its reason; the state is unchanged.
2. Raw estimate: from the filtered estimate of the previous injection, line searches along the two
   conjugate directions kept from the previous injection (the cost valley and across it), with
   step sizes of two standard deviations, then a Gauss–Newton check; one more cycle only if that
   check says the minimum is further away. Cold start (first injection, or re-acquisition): the
   coarse grid of :func:`estimator.ident.idle_stroke.identify`.
3. Filter: N_u may move with temperature between injections, L_h slowly with wear: a random walk
   with per-injection standard deviations ``q_nu``, ``q_lh_um``. The raw estimate's covariance is
   the Gauss–Newton one. An innovation beyond the chi-square gate is rejected as an outlier and does
   not move the estimate; after ``max_consecutive_outliers`` in a row the injector has really
   changed (e.g. refitted) and the estimator re-acquires from a cold start.
4. Model-error mode: the residual's energy in the nuisance span (see :mod:`estimator.ident.cost`)
   decides per injector, with hysteresis, whether to use the robust (projected) cost.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from estimator.errors import EstimatorError
from estimator.ident.cost import CostModel, model_error_statistic, nuisance_columns
from estimator.ident.idle_stroke import (STATUS_AT_BOUND, STATUS_NOT_CONVERGED, STATUS_OK, STATUS_REJECTED,
                                         Estimate, IdentConfig, effective_window_s, finish, identify,
                                         predict_valve, refine, rejected, search_box)
from estimator.ident.measurement import Injection
from estimator.model.fast_sim import FastSimulator

STATE_VERSION = 1


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of the recursive estimator (units in the names)."""

    ident: IdentConfig = field(default_factory=IdentConfig)
    q_nu_n_per_v: float = 0.01          # random walk of N_u per injection (temperature)
    q_lh_um: float = 0.003              # random walk of L_h per injection (wear)
    gate_chi2: float = 18.4             # 2 dof, P(false rejection) = 1e-4
    max_consecutive_outliers: int = 5
    warm_cycles: int = 3
    robust_on_after: int = 3            # consecutive injections with model error to switch robust on
    robust_off_after: int = 50          # consecutive clean injections to switch it off again
    robust_floor: tuple[float, float] = (0.02, 0.1)  # added raw sigma (N/V, µm) in robust mode: bias

    def __post_init__(self) -> None:
        for name in ("q_nu_n_per_v", "q_lh_um", "gate_chi2"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} = {v!r} must be a positive number")


@dataclass
class TrackerState:
    """Everything the estimator knows about one injector; JSON-serialisable via ``to_dict``.

    ``x`` = filtered [N_u N/V, L_h µm], ``p`` its covariance; ``directions`` (columns) and ``steps``
    the line-search state carried to the next injection.
    """

    initialized: bool = False
    x: list[float] = field(default_factory=lambda: [float("nan"), float("nan")])
    p: list[list[float]] = field(default_factory=lambda: [[1.0, 0.0], [0.0, 1.0]])
    directions: list[list[float]] = field(default_factory=lambda: [[1.0, 0.0], [0.0, 1.0]])
    steps: list[float] = field(default_factory=lambda: [0.05, 0.2])
    robust: bool = False
    model_error_run: int = 0
    clean_run: int = 0
    consecutive_outliers: int = 0
    accepted: int = 0
    rejected: int = 0
    updates: int = 0
    version: int = STATE_VERSION

    def to_dict(self) -> dict:
        """Plain dict for JSON."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrackerState":
        """Inverse of :meth:`to_dict`; raises ValueError for a foreign or corrupt dict."""
        if not isinstance(d, dict) or d.get("version") != STATE_VERSION:
            raise ValueError("not a tracker state of this version")
        known = {f for f in cls.__dataclass_fields__}
        st = cls(**{k: v for k, v in d.items() if k in known})
        arr = np.array(st.x + sum(st.p, []) + sum(st.directions, []) + st.steps, dtype=float)
        if arr.shape != (12,) or (st.initialized and not np.all(np.isfinite(arr))):
            raise ValueError("tracker state has wrong shapes or non-finite values")
        return st

    def with_prior(self, nu_n_per_v: float, lh_um: float, sigma: tuple[float, float] = (0.3, 1.0)) -> "TrackerState":
        """A state that starts from a given prior (used by EstimatorCommand 'set prior')."""
        return replace(TrackerState(), initialized=True, x=[float(nu_n_per_v), float(lh_um)],
                       p=[[sigma[0] ** 2, 0.0], [0.0, sigma[1] ** 2]])


@dataclass
class TrackResult:
    """Output of one update: the raw estimate, the filtered one, and what happened."""

    raw: Estimate
    nu_n_per_v: float
    lh_m: float
    sigma_nu: float
    sigma_lh_m: float
    status: str
    reason: str
    evaluations: int
    t_contact_s: float = float("nan")
    t_open_s: float = float("nan")
    stroke_m: float = float("nan")

    def filtered_dict(self) -> dict:
        """The filtered estimate with units in the keys."""
        f = lambda v, s=1.0: None if not math.isfinite(v) else round(v * s, 6)  # noqa: E731
        return {"nu_n_per_v": f(self.nu_n_per_v), "lh_um": f(self.lh_m, 1e6),
                "sigma_nu_n_per_v": f(self.sigma_nu), "sigma_lh_um": f(self.sigma_lh_m, 1e6),
                "status": self.status, "reason": self.reason, "t_contact_us": f(self.t_contact_s, 1e6),
                "t_open_us": f(self.t_open_s, 1e6), "stroke_um": f(self.stroke_m, 1e6)}


def _raw_cov_x(est: Estimate, robust: bool, config: TrackerConfig) -> np.ndarray:
    scale = np.array([1.0, 1e6])
    cov = est.cov * np.outer(scale, scale)
    if robust:
        cov = cov + np.diag(np.square(config.robust_floor))
    return cov


def _warm_estimate(state: TrackerState, inj: Injection, sim: FastSimulator, config: TrackerConfig,
                   box) -> Estimate:
    ic = config.ident
    model = CostModel(sim, inj, effective_window_s(ic, inj, state.robust), ic.norm, state.robust)
    x0 = box.clip(np.array(state.x, dtype=float))
    fit, converged, _ = refine(model, x0, np.array(state.directions), np.array(state.steps), box, ic,
                               max_cycles=config.warm_cycles, batched=True)
    stat = float("nan")
    if fit.success:   # the plain model's residual against the nuisance span (normal equations: no QR)
        stat = model_error_statistic(fit.residual[: model.n], nuisance_columns(model.current, model.dt),
                                     fit.sigma_v)
    # the published prediction is made once, with the filtered estimate (``_result``)
    return finish(sim, inj, fit, converged, model.evaluations, box, state.robust, stat, ic, predict=False)


def _cold_estimate(state: TrackerState, inj: Injection, sim: FastSimulator, config: TrackerConfig) -> Estimate:
    mode = "on" if state.robust else config.ident.robust
    return identify(inj, sim, replace(config.ident, robust=mode))


def update(state: TrackerState, inj: Injection, sim: FastSimulator, config: TrackerConfig) -> tuple[TrackerState, TrackResult]:
    """One injection through the recursive estimator (pure: ``state`` is not modified)."""
    st = replace(state, x=list(state.x), p=[list(r) for r in state.p])
    st.updates += 1
    problem = inj.problem()
    if problem is None and abs(sim.dt_s - inj.dt_s) > 1e-6 * inj.dt_s:
        problem = "sample period does not match the simulator"
    if problem is None and inj.duration_s < config.ident.window_s - 1e-12:
        problem = f"too short ({inj.duration_s * 1e6:.1f} µs < window {config.ident.window_s * 1e6:.0f} µs)"
    if problem:
        st.rejected += 1
        return st, _result(st, rejected(problem), STATUS_REJECTED, problem, sim, inj, predict=False)

    cold = not st.initialized or not np.all(np.isfinite(st.x))   # a prior counts as initialized
    restart = cold   # restart the filter from this raw estimate (first injection, mode switch)
    box = search_box(config.ident, sim, inj.f_open_n)
    raw = _cold_estimate(st, inj, sim, config) if cold else _warm_estimate(st, inj, sim, config, box)
    if raw.status == STATUS_REJECTED:
        st.rejected += 1
        return st, _result(st, raw, STATUS_REJECTED, raw.message, sim, inj, predict=False)
    if not cold and (raw.status == STATUS_NOT_CONVERGED or (raw.status == STATUS_AT_BOUND and not st.robust)):
        # the warm searches ran out of cycles (the injector moved more than expected), or the plain
        # model ran into a bound, which is how it absorbs a model error: decide afresh
        raw = _cold_estimate(st, inj, sim, config)

    # model-error mode with hysteresis
    if not st.robust:
        if math.isfinite(raw.model_error_stat) and raw.model_error_stat > config.ident.model_error_threshold:
            st.model_error_run += 1
        else:
            st.model_error_run = 0
        if raw.robust or st.model_error_run >= config.robust_on_after:
            st.robust, st.model_error_run, st.clean_run = True, 0, 0
            if not raw.robust:
                raw = _cold_estimate(st, inj, sim, config)
            restart = True   # estimates of the other cost are biased differently: restart the filter
    else:
        clean = math.isfinite(raw.model_error_stat) and raw.model_error_stat <= config.ident.model_error_threshold
        st.clean_run = st.clean_run + 1 if clean else 0
        if st.clean_run >= config.robust_off_after:
            st.robust, st.clean_run = False, 0

    z = np.array([raw.nu_n_per_v, raw.lh_m * 1e6])
    r_cov = _raw_cov_x(raw, raw.robust, config)
    if not np.all(np.isfinite(r_cov)):
        st.rejected += 1
        return st, _result(st, raw, STATUS_REJECTED, "no curvature at the optimum", sim, inj, predict=False)
    status, reason = STATUS_OK, ""
    if restart or not st.initialized:
        x, p = z, r_cov
        st.consecutive_outliers = 0
    else:
        x = np.array(st.x)
        p = np.array(st.p) + np.diag([config.q_nu_n_per_v ** 2, config.q_lh_um ** 2])
        s = p + r_cov
        innov = z - x
        d2 = float(innov @ np.linalg.solve(s, innov))
        if d2 > config.gate_chi2:
            st.consecutive_outliers += 1
            if st.consecutive_outliers < config.max_consecutive_outliers:
                st.rejected += 1
                st.p = p.tolist()
                reason = f"outlier (innovation chi2 {d2:.1f} > {config.gate_chi2:.1f})"
                return st, _result(st, raw, STATUS_REJECTED, reason, sim, inj, predict=True)
            # persistent disagreement: the injector changed; accept the new level
            x, p = z, r_cov
            reason = "re-acquired after consecutive outliers"
            st.consecutive_outliers = 0
        else:
            st.consecutive_outliers = 0
            k = p @ np.linalg.inv(s)
            x = x + k @ innov
            p = (np.eye(2) - k) @ p
            p = 0.5 * (p + p.T)
    # the filtered estimate stays inside the search box (projection of the constrained filter)
    x = box.clip(x)
    st.initialized = True
    st.x, st.p = x.tolist(), p.tolist()
    st.accepted += 1
    if np.all(np.isfinite(raw.jtj)) and np.linalg.det(raw.jtj) > 1e-14 * raw.jtj[0, 0] * raw.jtj[1, 1]:
        # directions: conjugate for the cost (eigenvectors of the Gauss–Newton matrix); steps: two
        # standard deviations of where the next injection's optimum is expected along each, i.e. of
        # the predicted covariance (filter + random walk) plus the raw estimate's own scatter
        v = raw.directions   # eigenvectors of raw.jtj, from finish()
        expected = p + np.diag([config.q_nu_n_per_v ** 2, config.q_lh_um ** 2]) + r_cov
        sd = np.sqrt(np.einsum("ji,jk,ki->i", v, expected, v))
        st.directions = v.tolist()
        st.steps = np.clip(2.0 * sd, 1e-3, 2.0).tolist()
    if raw.status == STATUS_AT_BOUND:
        status, reason = STATUS_AT_BOUND, raw.message
    return st, _result(st, raw, status, reason, sim, inj, predict=True)


def _result(st: TrackerState, raw: Estimate, status: str, reason: str, sim: FastSimulator, inj: Injection,
            predict: bool) -> TrackResult:
    nu, lh = st.x
    p = np.array(st.p)
    tc = to = stroke = float("nan")
    if predict and st.initialized and math.isfinite(nu) and math.isfinite(lh):
        try:
            tc, to, stroke = predict_valve(sim, inj, nu, lh * 1e-6)
        except EstimatorError:   # e.g. a prior outside the simulator's N_u range: no prediction
            pass
    sig = np.sqrt(np.abs(np.diag(p))) if st.initialized else np.array([np.nan, np.nan])
    return TrackResult(raw, float(nu), float(lh) * 1e-6, float(sig[0]), float(sig[1]) * 1e-6, status, reason,
                       raw.evaluations, tc, to, stroke)


class Tracker:
    """Thin stateful wrapper: one :class:`TrackerState` per injector id, simulators per sample period."""

    def __init__(self, config: TrackerConfig | None = None, sim: FastSimulator | None = None) -> None:
        self.config = config or TrackerConfig()
        self._sims: dict[float, FastSimulator] = {}
        if sim is not None:
            self._sims[round(sim.dt_s, 12)] = sim
        self.states: dict[int, TrackerState] = {}

    def simulator(self, dt_s: float) -> FastSimulator:
        """The fast simulator for a sample period (created on first use)."""
        key = round(dt_s, 12)
        if key not in self._sims:
            self._sims[key] = FastSimulator(dt_s=dt_s)
        return self._sims[key]

    def update(self, inj: Injection) -> TrackResult:
        """Feed one injection of ``inj.injector_id``; returns the result."""
        state = self.states.get(inj.injector_id, TrackerState())
        dt = inj.dt_s if (math.isfinite(inj.dt_s) and inj.dt_s > 0) else 0.5e-6
        new_state, result = update(state, inj, self.simulator(dt), self.config)
        self.states[inj.injector_id] = new_state
        return result

    def reset(self, injector_id: int) -> None:
        """Forget everything about one injector."""
        self.states.pop(injector_id, None)

    def set_prior(self, injector_id: int, nu_n_per_v: float, lh_um: float) -> None:
        """Start one injector from a prior (N/V, µm)."""
        self.states[injector_id] = TrackerState().with_prior(nu_n_per_v, lh_um)
