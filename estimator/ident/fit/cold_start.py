"""Cold start of eq. 28: find the cost valley without a previous estimate, then refine.

The valley is long and narrow: at N_u near 15 N/V a change of 0.05 N/V moves the best L_h by about
1 µm, and the cost 0.05 N/V off the valley is fifteen times its minimum. A coarse grid (0.5 N/V
columns) can therefore miss it, and a descent from the grid's best point ends in a box corner. The
structure helps: for each N_u the best L_h is a 1-D problem, and the *profile* ``min_L J(N_u, L)``
is a smooth, unimodal function of N_u. So the search is

1. the coarse grid (columns of N_u, rows of L_h), each column's minimum refined by a parabola;
2. ``zooms`` times: ``zoom_points`` columns between the neighbours of the best column (the span
   shrinks by ``(zoom_points - 1) / 2`` per zoom), each simulating only the L_h rows between its
   neighbours' minima and a margin (:func:`_window_profile`; 20–45 % fewer simulations per cold start,
   the same start point where a column's cost has one minimum near the valley);
3. conjugate-direction refinement (:func:`estimator.ident.fit.local_fit.refine`) from the best point.

That global search costs 450–630 simulations. A *local-first* cold start (the default,
``IdentConfig.cold_start``) first fits from a start point (``start_point``, the type's nominal
values, or the caller's) by Gauss–Newton steps in a trust region (:func:`gauss_newton_fit`; the line
searches of :func:`~estimator.ident.fit.local_fit.refine` where those stall) and keeps that fit only if it
passes a check (:func:`local_first_fit`, :func:`probe_ring`, :func:`excess_residual_z`): converged,
inside the box, no lower point on a ring around it, and a residual no larger than white noise allows;
a median of 38-41 simulations for both costs of an automatic start on matched plants (60 on the
hysteresis plant; the ring checks the fit published, see :func:`idle_stroke._local_first_auto`). A fit
in another valley, or one whose model error the cost does not absorb, fails the check and the global
search runs as before (the same estimate, bit for bit). In the accuracy bench's 400 injections the
kept fit's cost was never more than 0.09 (in chi-square units) above the global search's.

A :class:`SharedGrid` simulates each grid point once per injection: the plain and the robust cost
of an automatic cold start search the same first grid (and the same zooms where their valleys share
a column), and a zoom's outer columns are columns of the grid before. Points are simulated over the
longest window asked for: the first ``n`` samples of a simulation do not depend on later ones, so each
model's cost is the one it would have computed alone. The points of one N_u column share their free
run until contact (:meth:`FastSimulator.grid_voltages`, bit for bit what each would give alone).
"""

from __future__ import annotations

import numpy as np

from estimator.ident.config import IdentConfig
from estimator.ident.coords import UM_PER_M
from estimator.ident.fit.cost import CostModel, noise_sigma_v
from estimator.ident.fit.fit_kernel import GaussNewtonRules, run_gauss_newton, run_point_costs
from estimator.ident.fit.local_fit import FD_STEP, LocalFit, cost_fn, from_kernel_fit, refine
from estimator.ident.fit.search import Box, CostFn

START_STEPS = (0.3, 0.5)   # N/V, µm: first line-search steps where Gauss–Newton stalls (about a lot's series spread)
START_RADIUS = (1.0, 2.0)   # N/V, µm: first trust region of a local-first fit (a few times a lot's series spread)
SHRINK = 0.3       # a Gauss–Newton step that did not lower the cost: the next trust region, times that step
GN_MAX_STEPS = 12  # Gauss–Newton steps of a local-first fit at most (then the global search)
GN_CONVERGED_SD = 0.1   # converged: the Gauss–Newton step within this many standard deviations (or the tolerance)
GN_CLOSE_SD = 0.25      # ... or within this many and taking it did not lower the cost (refine's criterion)
RING_MIN_SD = np.array([0.002, 0.02])   # N/V, µm: the smallest standard deviations probe_ring scales by
_COMPASS = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [-1, -1], [1, -1], [-1, 1]], dtype=float)
RESCANS = 3   # refinements from a lower ring point at most
RING = np.concatenate([_COMPASS, 2 * _COMPASS])   # probes of probe_ring, in standard deviations (N_u, L_h)
ZOOM_ROW_MARGIN = 2   # rows (of the first grid's L_h spacing) a zoom column simulates either side of its predicted minimum


class SharedGrid:
    """Grid simulations shared by the cost models of one injection: a candidate (N_u, L_h) simulated
    for one grid is reused by any later grid that holds it (the other model's, and a zoom's outer
    columns, which are columns of the grid before). Kept until this object goes (a few MB)."""

    def __init__(self, models: list[CostModel]) -> None:
        self.longest = max(models, key=lambda m: m.n)
        self._row: dict[tuple[float, float], int] = {}   # point -> its row of _voltage
        self._voltage = np.empty((0, self.longest.n))     # over the longest window; NaN rows: failed

    def cost_fn(self, model: CostModel) -> CostFn:
        """``model``'s cost of (B, 2) points in (N/V, µm), each point simulated once over the longest window."""
        def f(x: np.ndarray) -> np.ndarray:
            keys = [tuple(p) for p in x.tolist()]
            todo = [i for i, k in enumerate(keys) if k not in self._row]
            if todo:
                pts = x[todo]
                src = self.longest
                u, _ = src.sim.grid_voltages(src.current, pts[:, 0], pts[:, 1] / UM_PER_M, src.injection.f_open_n)
                model.evaluations += len(todo)   # counted where simulated: evaluations are simulations run
                base = self._voltage.shape[0]
                self._voltage = np.concatenate([self._voltage, u])
                for n, i in enumerate(todo):
                    self._row.setdefault(keys[i], base + n)
            return model.cost_of(self._voltage[[self._row[k] for k in keys]])
        return f


def _column_minima(j: np.ndarray, lh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column (axis 0 = N_u) the parabola-refined minimum of J over the L_h rows and its L_h. A
    point no simulation explains (NaN) counts as infinitely far: argmin would take it as the minimum."""
    j = np.where(np.isnan(j), np.inf, j)
    k = np.clip(np.argmin(j, axis=1), 1, lh.size - 2)
    cols = np.arange(j.shape[0])
    j0, j1, j2 = j[cols, k - 1], j[cols, k], j[cols, k + 1]
    h = lh[1] - lh[0]
    with np.errstate(divide="ignore", invalid="ignore"):   # inf - inf beside a point that failed
        c2 = j0 - 2 * j1 + j2
        curved = np.isfinite(c2) & (c2 > 0)       # a parabola through three finite points
        shift = np.where(curved, 0.5 * (j0 - j2) / c2, 0.0)
        shift = np.clip(shift, -1.0, 1.0)
        jmin = np.where(curved, j1 - 0.25 * (j0 - j2) * shift, j1)
    best = np.minimum(jmin, j.min(axis=1))
    return best, lh[k] + shift * h


def _window_profile(f: CostFn, nu: np.ndarray, lh: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                    margin: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_column_minima` of the columns ``nu`` over the rows ``lh``, simulating only the rows
    ``lo..hi`` (indices, per column), widened by ``margin`` rows at a time where a column's lowest cost
    lies on its window's edge. Where the column's cost over the rows has one minimum in the window,
    this is the full grid's answer bit for bit: the lowest row and both its neighbours are simulated,
    and the rows left out are higher."""
    n = lh.size
    lo, hi = np.clip(lo, 0, n - 1), np.clip(hi, 0, n - 1)
    j = np.full((nu.size, n), np.inf)
    todo = [(c, r) for c in range(nu.size) for r in range(lo[c], hi[c] + 1)]
    while todo:
        cols, rows = np.array(todo).T
        j[cols, rows] = f(np.column_stack([nu[cols], lh[rows]]))
        k = np.argmin(j, axis=1)
        todo = []
        for c in range(nu.size):
            if k[c] == lo[c] and lo[c] > 0:
                new_lo = max(lo[c] - margin, 0)
                todo += [(c, r) for r in range(new_lo, lo[c])]
                lo[c] = new_lo
            if k[c] == hi[c] and hi[c] < n - 1:
                new_hi = min(hi[c] + margin, n - 1)
                todo += [(c, r) for r in range(hi[c] + 1, new_hi + 1)]
                hi[c] = new_hi
    return _column_minima(j, lh)


def profile_start(f: CostFn, box: Box, config: IdentConfig) -> tuple[np.ndarray, np.ndarray]:
    """A start point in the valley and the step sizes to refine from, both in (N/V, µm).

    The first grid simulates every row; a zoom's columns lie between columns already searched, so
    each simulates the rows between its two neighbours' minima and :data:`ZOOM_ROW_MARGIN` rows either
    side, widened where its minimum lands on the window's edge."""
    n_nu, n_lh = config.grid
    nu = np.linspace(box.lo[0], box.hi[0], n_nu)
    lh = np.linspace(box.lo[1], box.hi[1], n_lh)
    pts = np.stack(np.meshgrid(nu, lh, indexing="ij"), axis=-1).reshape(-1, 2)
    prof, lh_best = _column_minima(f(pts).reshape(nu.size, lh.size), lh)
    i = int(np.argmin(prof))
    for _ in range(config.zooms):
        lo, hi = nu[max(i - 1, 0)], nu[min(i + 1, nu.size - 1)]
        known_nu, known_row = nu, (lh_best - lh[0]) / (lh[1] - lh[0])
        nu = np.linspace(lo, hi, config.zoom_points)
        b = np.clip(np.searchsorted(known_nu, nu), 1, known_nu.size - 1)   # known columns b - 1 and b bracket nu
        rows_lo = np.floor(np.minimum(known_row[b - 1], known_row[b])).astype(np.int64) - ZOOM_ROW_MARGIN
        rows_hi = np.ceil(np.maximum(known_row[b - 1], known_row[b])).astype(np.int64) + ZOOM_ROW_MARGIN
        prof, lh_best = _window_profile(f, nu, lh, rows_lo, rows_hi, ZOOM_ROW_MARGIN)
        i = int(np.argmin(prof))
    x = box.clip(np.array([nu[i], lh_best[i]]))
    steps = np.array([max(nu[1] - nu[0], config.tol[0]), lh[1] - lh[0]])
    return x, steps


def cold_fit(model: CostModel, box: Box, config: IdentConfig,
             shared: SharedGrid | None = None) -> tuple[LocalFit, bool]:
    """The optimiser behind a cold start: profile search (its grids from ``shared`` where given) then
    refinement; (fit, converged)."""
    x, steps = profile_start(shared.cost_fn(model) if shared else cost_fn(model), box, config)
    fit, converged, _ = refine(model, x, np.eye(2), steps, box, config)
    return fit, converged


def bound_tolerance(config: IdentConfig) -> tuple[float, float]:
    """How close (N/V, µm) to a search bound an estimate counts as at the bound."""
    return config.tol[0] * 5, config.tol[1] * 5


def gauss_newton_fit(model: CostModel, start: np.ndarray, box: Box, config: IdentConfig,
                     radius: np.ndarray | None = None, radius_sd: float = 0.0) -> tuple[LocalFit, bool]:
    """Gauss–Newton steps from ``start`` (N/V, µm; clipped into the box) in a trust region; (fit, converged).

    Each step is one :func:`~estimator.ident.fit.local_fit.local_fit` (the point and its two
    forward-difference neighbours): the step is the Gauss–Newton step, shortened to fit ``radius``
    (N/V, µm; default :data:`START_RADIUS`), each radius at least ``radius_sd`` of the first fit's own
    standard deviations (0: as given). A step that lowers the cost is taken and the radius doubles;
    one that does not shrinks the radius to :data:`SHRINK` times that step. Converged when the
    Gauss–Newton step is within :data:`GN_CONVERGED_SD` standard deviations (or the tolerance) of the
    point, or within :data:`GN_CLOSE_SD` (:func:`refine`'s criterion) and taking it did not lower the
    cost; not converged after :data:`GN_MAX_STEPS` steps, when a step no longer moves the point (a
    bound), or when a simulation fails. In the narrow valley of eq. 28 the residual's Jacobian knows
    the valley's direction where the cost's one-dimensional sections do not: from the nominal start a
    lot's injector converges in 2–5 steps (6–15 simulations) where the line searches took 40. The loop
    is one compiled call (:func:`fit_kernel.gauss_newton`)."""
    x = box.clip(np.asarray(start, dtype=float))
    rad = np.array(START_RADIUS if radius is None else radius, dtype=float)
    rules = GaussNewtonRules(float(radius_sd), RING_MIN_SD, np.asarray(config.tol, dtype=float), GN_MAX_STEPS,
                             GN_CONVERGED_SD, GN_CLOSE_SD, SHRINK)
    run = run_gauss_newton(model, x, FD_STEP, box, rad, rules)
    return from_kernel_fit(run.fit), run.converged


def sd_radius(fit: LocalFit, k: float) -> np.ndarray:
    """A trust region of ``k`` of the fit's standard deviations (N/V, µm), each at least :data:`RING_MIN_SD`."""
    result: np.ndarray = k * np.maximum(fit.sd_x, RING_MIN_SD)
    return result


def unchecked_fit(model: CostModel, start: np.ndarray, box: Box, config: IdentConfig,
                  radius: np.ndarray | None = None, radius_sd: float = 0.0) -> tuple[LocalFit, bool]:
    """:func:`gauss_newton_fit` from ``start`` (N/V, µm) in a trust region of ``radius`` (at least
    ``radius_sd`` of the first fit's standard deviations), then, where it stalled, the line searches;
    (fit, converged), not yet checked by :func:`ring_checked`."""
    fit, converged = gauss_newton_fit(model, start, box, config, radius, radius_sd=radius_sd)
    if fit.success and not converged:
        # Gauss–Newton stalled (a Jacobian the cost's kinks or a model error mislead): the line searches,
        # which need no Jacobian, from the best point it reached
        fit, converged, _ = refine(model, fit.x, np.eye(2), np.array(START_STEPS), box, config)
    return fit, converged


def ring_checked(model: CostModel, fit: LocalFit, converged: bool, box: Box, config: IdentConfig) -> LocalFit | None:
    """:func:`probe_ring` around the fit (fitted again from a lower point it finds, at most
    :data:`RESCANS` times); the fit if it converged inside the box, else None."""
    for _ in range(RESCANS):
        lower = probe_ring(model, fit, box) if fit.success and converged else None
        if lower is None:
            break
        fit2, converged2 = gauss_newton_fit(model, lower, box, config, sd_radius(fit, 2.0))
        if not (fit2.success and fit2.criterion < fit.criterion):
            break
        fit, converged = fit2, converged2
    return fit if usable(fit, converged, box, config) else None


def usable(fit: LocalFit, converged: bool, box: Box, config: IdentConfig) -> bool:
    """A local fit that may be kept: successful, converged and not at a search bound."""
    return fit.success and converged and not box.at_bound(fit.x, bound_tolerance(config))


def local_first_fit(model: CostModel, start: np.ndarray, box: Box, config: IdentConfig,
                    radius: np.ndarray | None = None, radius_sd: float = 0.0) -> LocalFit | None:
    """:func:`unchecked_fit` then :func:`ring_checked`: the fit if it converged inside the box with no
    lower point on the ring, else None. Whether its residual is that of the minimum is the caller's
    check (:func:`excess_residual_z`)."""
    return ring_checked(model, *unchecked_fit(model, start, box, config, radius, radius_sd), box, config)


def probe_ring(model: CostModel, fit: LocalFit, box: Box) -> np.ndarray | None:
    """The lowest of :data:`RING` points around the fit (its standard deviations of N_u and L_h as
    the units, at least 0.002 N/V and 0.02 µm) if it is lower than the fit: the fit stopped short.

    Near L_h = 0 (contact with the first samples) the cost has kinks: the forward-difference
    Jacobian there can put the valley a few degrees off, and the refinement stops a standard
    deviation or two short of the minimum with its Gauss–Newton step small. Probing the axes and
    the diagonals does not rely on that Jacobian."""
    if not np.all(np.isfinite(fit.sd_x)):
        return None
    pts = box.clip(fit.x[None, :] + RING * sd_radius(fit, 1.0)[None, :])
    j = run_point_costs(model, pts)   # one compiled call (the fit's own cost is summed the same way)
    k = int(np.argmin(j))
    return pts[k] if j[k] < fit.criterion else None


def excess_residual_z(model: CostModel, fit: LocalFit) -> float:
    """How far the fit's residual energy lies above white noise, in standard deviations (chi-square).

    ``(RSS / sigma^2 - dof) / sqrt(2 dof)`` over the model's window: the residual projected off the
    nuisance span in robust mode, ``sigma`` the residual's own noise level from its first differences
    (:func:`noise_sigma_v`, which a smooth misfit hardly raises), ``dof`` the samples less the two
    parameters and the nuisance columns. At the minimum of a correct model it scatters by about 2 (the
    noise estimate's own scatter included); a fit in a wrong valley, or a model error the cost does not
    absorb, leaves a residual far above the noise (0.05 N/V off the valley is fifteen times the minimum).
    """
    n = model.n
    r = fit.residual[:n]
    k = 2
    if model.robust:
        r = model.without_nuisance(r)
        k += model.basis.shape[1]
    dof = max(n - k, 1)
    sigma = noise_sigma_v(r)
    return float((r @ r / sigma ** 2 - dof) / np.sqrt(2.0 * dof))
