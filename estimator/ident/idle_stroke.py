"""Idle-stroke detection (eq. 28): N_u and L_h together from one injection's current and voltage.

The search (``identify``): a coarse grid over the bounds, then cycles of line searches along the
conjugate directions of the local Gauss–Newton model (the first is the long diagonal valley where
higher N_u trades against lower L_h), until a cycle moves less than a tolerance. The same pieces
serve the recursive estimator, which starts from the previous injection instead of the grid.

Model-error handling (``robust="auto"``): the plain fit and the robust fit (nuisance span of
current, charge and Prandtl–Ishlinskii ramps of the charge projected out, see
:mod:`estimator.ident.cost`) are both made; if the plain model's residual is worse than the robust
one's by far more than chance allows (likelihood ratio, chi-square with 6 dof, noise level from
the residual's differences), the model is wrong in a smooth way and the robust estimate is used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from estimator.ident.cost import CostModel, noise_sigma_v
from estimator.ident.measurement import Injection
from estimator.ident.search import (Box, conjugate_directions, conjugate_stencil, conjugate_vertex, grid_search,
                                   line_search)
from estimator.model import dynamics as dyn
from estimator.model.fast_sim import PLATEAU_WINDOW_S, FastSimulator

STATUS_OK = "ok"
STATUS_AT_BOUND = "at_bound"
STATUS_NOT_CONVERGED = "not_converged"
STATUS_REJECTED = "rejected"
FD_STEP = np.array([2e-3, 2e-3])   # finite-difference steps: N/V, µm


@dataclass(frozen=True)
class IdentConfig:
    """Settings of the identification (units in the names)."""

    window_s: float = 100e-6
    robust_window_s: float = 150e-6        # window in robust mode, if the trace is that long
    norm: str = "l2"
    robust: str = "auto"                   # "auto", "on" or "off"
    model_error_threshold: float = 40.0    # chi-square(6) statistic; P(>40 | correct model) < 1e-6
    nu_bounds_n_per_v: tuple[float, float] = (15.0, 21.0)
    lh_bounds_um: tuple[float, float] = (-2.0, 10.0)
    grid: tuple[int, int] = (13, 25)       # N_u x L_h points of the cold-start grid
    tol: tuple[float, float] = (2e-4, 2e-3)  # convergence: N/V, µm
    max_cycles: int = 10

    def __post_init__(self) -> None:
        if self.robust not in ("auto", "on", "off"):
            raise ValueError(f"robust must be auto, on or off, not {self.robust!r}")
        if not (20e-6 <= self.window_s <= 2e-3):
            raise ValueError(f"window {self.window_s * 1e6:.1f} µs must be within 20..2000 µs")
        lo, hi = self.nu_bounds_n_per_v
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
            raise ValueError(f"N_u bounds {self.nu_bounds_n_per_v} N/V are not an interval")
        lo, hi = self.lh_bounds_um
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"L_h bounds {self.lh_bounds_um} µm are not an interval")


@dataclass
class Estimate:
    """Result of one identification (raw, single injection). SI units except where named.

    ``cov`` is the covariance of (N_u [N/V], L_h [m]) from the Gauss–Newton model and the noise
    level estimated from the residual; ``jtj`` and ``directions`` are in (N/V, µm) coordinates.
    """

    nu_n_per_v: float
    lh_m: float
    cov: np.ndarray
    cost_vs: float
    criterion: float
    evaluations: int
    status: str
    message: str = ""
    robust: bool = False
    model_error_stat: float = float("nan")
    noise_sigma_v: float = float("nan")
    t_contact_s: float = float("nan")
    t_open_s: float = float("nan")
    stroke_m: float = float("nan")
    jtj: np.ndarray = field(default_factory=lambda: np.eye(2))
    directions: np.ndarray = field(default_factory=lambda: np.eye(2))

    @property
    def sigma_nu(self) -> float:
        """1-sigma uncertainty of N_u in N/V."""
        return float(math.sqrt(max(self.cov[0, 0], 0.0)))

    @property
    def sigma_lh_m(self) -> float:
        """1-sigma uncertainty of L_h in m."""
        return float(math.sqrt(max(self.cov[1, 1], 0.0)))

    def to_dict(self) -> dict:
        """JSON-ready summary with units in the keys (µm, µs, µV·s)."""
        def num(v: float, scale: float = 1.0, nd: int = 6) -> float | None:
            return None if not math.isfinite(v) else round(v * scale, nd)
        return {
            "nu_n_per_v": num(self.nu_n_per_v), "lh_um": num(self.lh_m, 1e6),
            "sigma_nu_n_per_v": num(self.sigma_nu), "sigma_lh_um": num(self.sigma_lh_m, 1e6),
            "cost_uvs": num(self.cost_vs, 1e6, 3), "t_contact_us": num(self.t_contact_s, 1e6, 3),
            "t_open_us": num(self.t_open_s, 1e6, 3), "stroke_um": num(self.stroke_m, 1e6, 4),
            "status": self.status, "message": self.message, "evaluations": self.evaluations,
            "robust": self.robust, "model_error_stat": num(self.model_error_stat, 1.0, 2),
            "noise_sigma_v": num(self.noise_sigma_v, 1.0, 4),
        }


def rejected(reason: str, evaluations: int = 0) -> Estimate:
    """An Estimate that carries only a rejection reason."""
    nan = float("nan")
    return Estimate(nan, nan, np.full((2, 2), np.nan), nan, nan, evaluations, STATUS_REJECTED, reason)


def search_box(config: IdentConfig, sim: FastSimulator, f_open_n: float) -> Box:
    """The search bounds in (N/V, µm): the configured bounds, the parameter range of N_u, and the
    feasibility limit of L_h (no start in Σ3) with a small margin."""
    psa = sim.params.psa
    lo_nu = max(config.nu_bounds_n_per_v[0], psa.nu_min_n_per_v)
    hi_nu = min(config.nu_bounds_n_per_v[1], psa.nu_max_n_per_v)
    lh_feasible = dyn.min_feasible_lh_m(sim.params, f_open_n) * 1e6 + 0.02
    lo_lh = max(config.lh_bounds_um[0], lh_feasible)
    return Box(np.array([lo_nu, lo_lh]), np.array([hi_nu, config.lh_bounds_um[1]]))


def effective_window_s(config: IdentConfig, injection: Injection, robust: bool) -> float:
    """The cost window: ``window_s``, or in robust mode up to ``robust_window_s`` as far as the trace goes.

    With smooth model errors projected out, the contact signature is what is left to fit; late
    contacts (large L_h) leave too little of it in 100 µs, so robust mode looks further when it can.
    """
    if robust and config.robust_window_s > config.window_s:
        return max(config.window_s, min(config.robust_window_s, injection.duration_s))
    return config.window_s


def cost_fn(model: CostModel):
    """The cost model as a function of (B, 2) points in (N/V, µm)."""
    def f(x: np.ndarray) -> np.ndarray:
        return model(x[:, 0], x[:, 1] * 1e-6)
    return f


@dataclass(frozen=True)
class LocalFit:
    """Gauss–Newton model of the cost at a point: residual, Jacobian, noise and covariance."""

    x: np.ndarray
    criterion: float
    paper_cost_vs: float
    jtj: np.ndarray            # (2, 2) in (N/V, µm), V^2 per unit^2 (sum over samples)
    gn_step: np.ndarray        # Gauss–Newton step in (N/V, µm)
    sigma_v: float
    cov_x: np.ndarray          # covariance in (N/V, µm)
    residual: np.ndarray       # unprojected residual at x (V)
    t_contact_s: float
    t_open_s: float
    success: bool

    @cached_property
    def directions(self) -> tuple[np.ndarray, np.ndarray]:
        """Conjugate directions (columns) and eigenvalues of ``jtj``, weakest first (computed once)."""
        return conjugate_directions(self.jtj)


def local_fit(model: CostModel, x: np.ndarray, box: Box) -> LocalFit:
    """Simulate x and two forward-difference neighbours in one batch (steps toward the box inside)."""
    steps = np.where(x + FD_STEP <= box.hi, FD_STEP, -FD_STEP)
    pts = np.array([x, x + [steps[0], 0.0], x + [0.0, steps[1]]])
    res = model.simulate(pts[:, 0], pts[:, 1] * 1e-6)
    r = model.residuals(res)
    jac = -(r[1:] - r[0]) / steps[:, None]            # dU_sim/dx, (2, N)
    return _fit_from(model, x, res, r[0], jac, bool(res.success.all()))


def fit_with_jacobian(model: CostModel, x: np.ndarray, jac: np.ndarray) -> LocalFit:
    """Local fit at x with a Jacobian known from elsewhere (the conjugate stencil): one simulation."""
    res = model.simulate(np.array([x[0]]), np.array([x[1] * 1e-6]))
    return _fit_from(model, x, res, model.residuals(res)[0], jac, bool(res.success[0]))


def _fit_from(model: CostModel, x: np.ndarray, res, r0: np.ndarray, jac: np.ndarray, ok: bool) -> LocalFit:
    """Gauss–Newton model from the residual r0 at x (candidate 0 of ``res``) and dU/dx ``jac`` (2, N)."""
    crit = model.from_result(res)
    raw = model.measured - res.voltage_v[0]
    jtj = jac @ jac.T
    ok = ok and bool(np.isfinite(jtj).all())
    sigma = noise_sigma_v(r0) if ok else float("nan")
    det = float(jtj[0, 0] * jtj[1, 1] - jtj[0, 1] * jtj[1, 0]) if ok else 0.0
    if ok and det > 1e-14 * float(jtj[0, 0] * jtj[1, 1]):
        inv = np.array([[jtj[1, 1], -jtj[0, 1]], [-jtj[1, 0], jtj[0, 0]]]) / det
        cov = sigma ** 2 * inv
        step = inv @ (jac @ r0)
    else:
        cov, step = np.full((2, 2), np.inf), np.zeros(2)
    return LocalFit(x.copy(), float(crit[0]), float(model.paper_cost_vs(res)[0]), jtj, step, sigma, cov,
                    raw, float(res.t_contact_s[0]), float(res.t_open_s[0]), ok)


def refine(model: CostModel, x0: np.ndarray, directions: np.ndarray, steps: np.ndarray, box: Box,
           config: IdentConfig, max_cycles: int | None = None, j0: float | None = None,
           batched: bool = False) -> tuple[LocalFit, bool, int]:
    """Cycles of line searches along conjugate directions; returns (fit, converged, cycles).

    ``batched``: the directions are already conjugate (warm start), so both line searches of a
    cycle are evaluated in one batch (:func:`conjugate_stencil`, :func:`conjugate_vertex`); a direction whose parabola is not
    convex or leaves the trust region falls back to the bracketing line search.
    """
    x, j = box.clip(x0.astype(float)), j0
    d, st = directions, steps
    tol = np.array(config.tol)
    converged = False
    cycles = 0
    f = cost_fn(model)
    for cycles in range(1, (max_cycles or config.max_cycles) + 1):
        start = x.copy()
        todo = [0, 1]
        jac = None
        if batched:
            pts, inside = conjugate_stencil(x, d, st, box)
            res = model.simulate(pts[:, 0], pts[:, 1] * 1e-6)
            x, ok = conjugate_vertex(pts, model.from_result(res), start, d, st, box)
            todo = [i for i in range(2) if not ok[i]]
            j = None
            if inside and not todo and res.success.all():
                # the stencil's central differences along d1, d2 are the Gauss–Newton Jacobian:
                # dU/dx = D (dU/dalpha), with alpha the coordinates along the directions
                r = model.residuals(res)
                jac_a = np.stack([-(r[2] - r[1]) / (2 * st[0]), -(r[4] - r[3]) / (2 * st[1])])
                jac = d @ jac_a
        for i in todo:
            # the vertex of the first search is the centre of the second, and the vertex of the
            # second is the centre of the local fit: both are evaluated there, not twice
            lr = line_search(f, x, d[:, i], float(st[i]), box, j0=j if i == 0 else None, evaluate_vertex=False)
            x, j = lr.x, None
        fit = fit_with_jacobian(model, x, jac) if jac is not None else local_fit(model, x, box)
        if not fit.success:
            return fit, False, cycles
        move = np.abs(x - start)
        d, w = fit.directions
        # next steps: two standard deviations along each direction, at least the tolerance
        sd = np.sqrt(np.maximum(fit.sigma_v ** 2 / np.maximum(w, 1e-300), 0.0))
        st = np.clip(2.0 * sd, 4 * np.min(tol), 2.0)
        j = fit.criterion
        # converged when the last cycle hardly moved, or when the Gauss–Newton model puts the
        # minimum within a quarter standard deviation (or the tolerance) of where we are
        sigma_x = np.sqrt(np.abs(np.diag(fit.cov_x)))
        close = np.maximum(tol, 0.25 * sigma_x)
        if np.all(move <= tol) or np.all(np.abs(fit.gn_step) <= close):
            converged = True
            break
        if batched and np.all(np.abs(fit.gn_step) <= 4.0 * np.maximum(sigma_x, tol)):
            # near the minimum already: one Gauss–Newton step is cheaper than another cycle
            x_gn = box.clip(x + fit.gn_step)
            fit_gn = local_fit(model, x_gn, box)
            if fit_gn.success and fit_gn.criterion <= fit.criterion:
                fit, x = fit_gn, x_gn
                sigma_x = np.sqrt(np.abs(np.diag(fit.cov_x)))
                if np.all(np.abs(fit.gn_step) <= np.maximum(tol, 0.25 * sigma_x)):
                    converged = True
                    break
            j = fit.criterion
    return fit, converged, cycles


def predict_valve(sim: FastSimulator, injection: Injection, nu: float, lh_m: float) -> tuple[float, float, float]:
    """Contact time, opening time (s) and plateau stroke (m) for this injection's current.

    The measured current is used as it is, followed by zero current (the amplifier holding the
    charge) until the end of the plateau window (490 µs); the stroke is the mean plunger stroke over
    215–490 µs as in Table 3. NaN when the valve does not open with that charge.
    """
    n_total = int(round(PLATEAU_WINDOW_S[1] / injection.dt_s)) + 1
    cur = np.zeros(max(n_total, injection.n))
    cur[: injection.n] = injection.current_a
    res = sim.simulate(cur, nu, lh_m, injection.f_open_n)
    return float(res.t_contact_s[0]), float(res.t_open_s[0]), float(res.plateau_stroke_m()[0])


def _fit_mode(sim: FastSimulator, inj: Injection, config: IdentConfig, robust: bool, box: Box):
    model = CostModel(sim, inj, effective_window_s(config, inj, robust), config.norm, robust)
    f = cost_fn(model)
    _, _, x = grid_search(f, box, *config.grid)
    # start along the axes with the grid spacing; the first local fit provides the valley directions
    spacing = (box.hi - box.lo) / (np.array(config.grid) - 1)
    fit, converged, _ = refine(model, x, np.eye(2), spacing, box, config)
    return model, fit, converged


def identify(injection: Injection, sim: FastSimulator | None = None, config: IdentConfig | None = None) -> Estimate:
    """Identify (N_u, L_h) of one injection from a cold start (eq. 28). Never raises for bad data."""
    config = config or IdentConfig()
    problem = injection.problem()
    if problem:
        return rejected(problem)
    sim = sim or FastSimulator(dt_s=injection.dt_s)
    if abs(sim.dt_s - injection.dt_s) > 1e-6 * injection.dt_s:
        return rejected(f"sample period {injection.dt_s * 1e6:.3f} µs does not match the simulator's "
                        f"{sim.dt_s * 1e6:.3f} µs")
    if injection.duration_s < config.window_s - 1e-12:
        return rejected(f"too short ({injection.duration_s * 1e6:.1f} µs < window {config.window_s * 1e6:.0f} µs)")
    box = search_box(config, sim, injection.f_open_n)
    if config.robust != "auto":
        robust = config.robust == "on"
        model, fit, converged = _fit_mode(sim, injection, config, robust, box)
        return finish(sim, injection, fit, converged, model.evaluations, box, robust, float("nan"), config)
    # auto: fit both models and test the plain one against the robust one (nested: the robust cost
    # adds the nuisance span). Likelihood ratio (RSS_plain - RSS_robust) / sigma^2 ~ chi2(6) under a
    # correct model; far beyond that, the plain fit is absorbing a model error in its (N_u, L_h).
    m_plain, f_plain, c_plain = _fit_mode(sim, injection, config, False, box)
    m_rob, f_rob, c_rob = _fit_mode(sim, injection, config, True, box)
    evaluations = m_plain.evaluations + m_rob.evaluations
    stat = likelihood_ratio(m_plain, f_plain, m_rob, f_rob)
    if math.isfinite(stat) and stat > config.model_error_threshold:
        return finish(sim, injection, f_rob, c_rob, evaluations, box, True, stat, config)
    return finish(sim, injection, f_plain, c_plain, evaluations, box, False, stat, config)


def likelihood_ratio(m_plain: CostModel, f_plain: LocalFit, m_rob: CostModel, f_rob: LocalFit) -> float:
    """(RSS_plain − RSS_robust) / sigma^2 over the plain model's window (NaN if a fit failed).

    The robust fit's residual over the plain window is projected with the plain window's basis,
    so both sums are over the same samples; sigma is the noise level of the robust residual.
    """
    if not (f_plain.success and f_rob.success):
        return float("nan")
    n = m_plain.n
    r_plain = f_plain.residual[:n]
    r_rob = f_rob.residual[:n]
    r_rob = r_rob - m_plain.basis @ (m_plain.basis.T @ r_rob)
    sigma = noise_sigma_v(r_rob)
    return float(r_plain @ r_plain - r_rob @ r_rob) / sigma ** 2


def finish(sim: FastSimulator, injection: Injection, fit: LocalFit, converged: bool, evaluations: int, box: Box,
           robust: bool, stat: float, config: IdentConfig, predict: bool = True) -> Estimate:
    """Turn a local fit into an Estimate with status and (``predict``) the plateau stroke.

    Contact and opening times are those of the fitted window; the stroke needs one more, longer
    simulation (see :func:`predict_valve`)."""
    if not fit.success:
        return rejected("simulation failed at the optimum", evaluations)
    x = fit.x
    scale = np.array([1.0, 1e-6])
    cov = fit.cov_x * np.outer(scale, scale)
    tol = np.array(config.tol) * 5
    if box.at_bound(x, tol):
        status, msg = STATUS_AT_BOUND, "estimate at a search bound"
    elif not converged:
        status, msg = STATUS_NOT_CONVERGED, "line searches did not converge"
    else:
        status, msg = STATUS_OK, ""
    tc, to, stroke = fit.t_contact_s, fit.t_open_s, float("nan")
    if predict:
        tc, to, stroke = predict_valve(sim, injection, x[0], x[1] * 1e-6)
    d, _ = fit.directions
    return Estimate(float(x[0]), float(x[1] * 1e-6), cov, fit.paper_cost_vs, fit.criterion, evaluations + 1,
                    status, msg, robust, stat, fit.sigma_v, tc, to, stroke, fit.jtj, d)
