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
3. conjugate-direction refinement (:func:`estimator.ident.local_fit.refine`) from the best point.

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
from estimator.ident.cost import CostModel
from estimator.ident.local_fit import LocalFit, cost_fn, refine
from estimator.ident.search import Box, CostFn

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
    """Per column (axis 0 = N_u) the parabola-refined minimum of J over the L_h rows and its L_h."""
    k = np.clip(np.argmin(j, axis=1), 1, lh.size - 2)
    cols = np.arange(j.shape[0])
    j0, j1, j2 = j[cols, k - 1], j[cols, k], j[cols, k + 1]
    h = lh[1] - lh[0]
    c2 = j0 - 2 * j1 + j2
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(c2 > 0, 0.5 * (j0 - j2) / c2, 0.0)
    shift = np.clip(shift, -1.0, 1.0)
    jmin = np.where(c2 > 0, j1 - 0.25 * (j0 - j2) * shift, j1)
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
