"""Batched searches in the (N_u, L_h) plane: coarse grid, line searches, local quadratic models.

Coordinates are ``x = [N_u in N/V, L_h in µm]``. Every search evaluates its candidates in one
batch per step (the fast simulator is ~5x cheaper per candidate in batches than one by one).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from estimator._compiled import njit

CostFn = Callable[[np.ndarray], np.ndarray]   # (B, 2) -> (B,)
TRUST_STEPS = 2.5   # a conjugate vertex further than this many steps from the centre is not trusted


@dataclass(frozen=True)
class Box:
    """Bounds of the search: lo, hi as [N_u N/V, L_h µm]."""

    lo: np.ndarray
    hi: np.ndarray

    def clip(self, x: np.ndarray) -> np.ndarray:
        """Points moved into the box."""
        result: np.ndarray = np.minimum(np.maximum(x, self.lo), self.hi)
        return result

    def alpha_range(self, x: np.ndarray, d: np.ndarray) -> tuple[float, float]:
        """The range of alpha for which x + alpha d stays inside the box."""
        lo, hi = -np.inf, np.inf
        for i in range(2):
            if abs(d[i]) < 1e-15:
                continue
            a, b = (self.lo[i] - x[i]) / d[i], (self.hi[i] - x[i]) / d[i]
            lo, hi = max(lo, min(a, b)), min(hi, max(a, b))
        return lo, hi

    def at_bound(self, x: np.ndarray, tol: np.ndarray | tuple[float, float]) -> bool:
        """True if x lies within tol (two numbers: N/V, µm) of a bound."""
        return any(x[i] <= self.lo[i] + tol[i] or x[i] >= self.hi[i] - tol[i] for i in range(2))


@dataclass(frozen=True)
class LineResult:
    """Outcome of a line search: the best point, its cost, the curvature along d (cost/alpha^2)."""

    x: np.ndarray
    j: float
    alpha: float
    curvature: float
    evaluations: int
    bracketed: bool


@njit(cache=True, nogil=True)
def parabola_vertex(a0: float, a1: float, a2: float, j0: float, j1: float, j2: float) -> tuple[float, float]:
    """Vertex and curvature (2nd derivative) of the parabola through (a_i, j_i); (nan, nan) unless it
    is convex and the three costs are finite (compiled: the warm cycle calls it too)."""
    den = (a0 - a1) * (a0 - a2) * (a1 - a2)
    if den == 0.0 or not (np.isfinite(j0) and np.isfinite(j1) and np.isfinite(j2)):
        return np.nan, np.nan
    c2 = (a2 * (j1 - j0) + a1 * (j0 - j2) + a0 * (j2 - j1)) / den
    c1 = (a2 * a2 * (j0 - j1) + a1 * a1 * (j2 - j0) + a0 * a0 * (j1 - j2)) / den
    if not c2 > 0.0:
        return np.nan, np.nan
    return -c1 / (2 * c2), 2 * c2


def _parabola(a: np.ndarray, j: np.ndarray) -> tuple[float, float] | None:
    """:func:`parabola_vertex` of three points ``a`` and their costs ``j``; None unless convex."""
    vertex, curvature = parabola_vertex(float(a[0]), float(a[1]), float(a[2]), float(j[0]), float(j[1]), float(j[2]))
    return None if np.isnan(curvature) else (vertex, curvature)


def line_search(f: CostFn, x0: np.ndarray, d: np.ndarray, step: float, box: Box, j0: float | None = None,
                max_shifts: int = 8, evaluate_vertex: bool = True) -> LineResult:
    """Minimise f along x0 + alpha d (alpha in units of |d|, d a unit vector).

    Evaluates alpha in {-step, 0, +step} (0 is skipped if ``j0`` is given), moves the triple
    downhill until the middle point is lowest (bracketing, at most ``max_shifts`` moves, doubling
    the step after two moves), then takes the vertex of the parabola through the bracket and
    evaluates it. With ``evaluate_vertex=False`` the vertex is returned with the parabola's value
    instead (for a caller whose next step evaluates that point anyway). Stays inside the box.
    """
    amin, amax = box.alpha_range(x0, d)
    evals = 0
    known: dict[float, float] = {}
    if j0 is not None:
        known[0.0] = float(j0)

    def clip(a: float) -> float:
        return amin if a < amin else amax if a > amax else a

    def ev(alphas: list[float]) -> None:
        nonlocal evals
        todo = sorted({clip(a) for a in alphas} - known.keys())
        if todo:
            jj = f(x0[None, :] + np.array(todo)[:, None] * d[None, :])
            evals += len(todo)
            known.update(zip(todo, jj.tolist()))

    centre = clip(0.0)
    ev([centre - step, centre, centre + step])
    bracketed = False
    for shift in range(max_shifts + 1):
        trip = [clip(centre - step), centre, clip(centre + step)]
        jt = [known[a] for a in trip]
        best = jt.index(min(jt))
        if best == 1 or (best == 0 and trip[0] <= amin) or (best == 2 and trip[2] >= amax):
            bracketed = best == 1
            break
        centre = trip[best]
        if shift >= 1:
            step *= 2.0
        ev([centre - step, centre + step])
    a_pts = sorted(known)
    j_pts = [known[a] for a in a_pts]
    k = j_pts.index(min(j_pts))
    curvature = float("nan")
    if 0 < k < len(a_pts) - 1:
        pv = _parabola(np.array(a_pts[k - 1:k + 2]), np.array(j_pts[k - 1:k + 2]))
        if pv is not None:
            vertex, curvature = pv
            vertex = min(max(vertex, a_pts[k - 1]), a_pts[k + 1])
            if not evaluate_vertex:
                jv = j_pts[k] - 0.5 * curvature * (a_pts[k] - vertex) ** 2
                return LineResult(x0 + vertex * d, float(jv), float(vertex), float(curvature), evals, bracketed)
            if all(abs(vertex - a) > 1e-9 * (abs(step) + 1e-12) for a in a_pts):
                ev([vertex])
                a_pts = sorted(known)
                j_pts = [known[a] for a in a_pts]
                k = j_pts.index(min(j_pts))
    alpha = a_pts[k]
    return LineResult(x0 + alpha * d, float(j_pts[k]), float(alpha), float(curvature), evals, bracketed)


def grid_search(f: CostFn, box: Box, n_nu: int, n_lh: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Evaluate f on an n_nu x n_lh grid over the box; returns (grid points (n_lh, n_nu, 2), costs, best x)."""
    nu = np.linspace(box.lo[0], box.hi[0], n_nu)
    lh = np.linspace(box.lo[1], box.hi[1], n_lh)
    g = np.stack(np.meshgrid(nu, lh), axis=-1)
    j = f(g.reshape(-1, 2)).reshape(n_lh, n_nu)
    k = np.unravel_index(int(np.argmin(j)), j.shape)
    return g, j, g[k].copy()
