"""The preload table's rows carried to a moved estimate by their derivatives, in one compiled call
(every injection with a drive correction carries every row: fifteen rows in Python cost about as
much as a simulation)."""

from __future__ import annotations

import numpy as np

from estimator._compiled import njit

# columns of an injector's table grid (one line per preload row): its last correction's stroke (µm),
# scale and opening instant before the offset (µs), the estimate it was computed for (N/V, µm), and
# the derivatives of stroke and opening in N_u, L_h and the scale, and the σ of stroke and opening it
# stated (µm, µs: carried as they are until the row is computed again)
STROKE, SCALE, OPENING, NU, LH_UM, DS_DNU, DS_DLH, DS_DSCALE, DO_DNU, DO_DLH, DO_DSCALE, SIGMA_STROKE, SIGMA_OPENING \
    = range(13)
COLUMNS = 13


@njit(cache=True, nogil=True)
def carry_rows(grid: np.ndarray, nu: float, lh_um: float, target_stroke: float, target_opening: float,
               limits: tuple[float, float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(scale, the opening instant's move µs, offset µs) of every row of ``grid`` (rows ×
    :data:`COLUMNS`) carried to the estimate (``nu`` N/V, ``lh_um`` µm) by its derivatives from its
    last correction: the scale that brings the carried stroke to ``target_stroke`` (µm), the opening's
    move with it, and the offset that brings the opening to ``target_opening`` (µs), within
    ``limits`` (lowest and highest scale, earliest and latest offset µs); and the largest move
    (µs, absolute). The stroke is close to linear in N_u, L_h and the scale."""
    lo, hi, olo, ohi = limits
    n = grid.shape[0]
    scale = np.empty(n)
    moved = np.empty(n)
    offset = np.empty(n)
    farthest = 0.0
    for i in range(n):
        g = grid[i]
        dnu, dlh = nu - g[NU], lh_um - g[LH_UM]
        stroke = g[STROKE] + g[DS_DNU] * dnu + g[DS_DLH] * dlh
        s = min(max(g[SCALE] + (target_stroke - stroke) / g[DS_DSCALE], lo), hi)
        scale[i] = s
        moved[i] = g[DO_DNU] * dnu + g[DO_DLH] * dlh + g[DO_DSCALE] * (s - g[SCALE])
        offset[i] = min(max(target_opening - (g[OPENING] + moved[i]), olo), ohi)
        farthest = max(farthest, abs(moved[i]))
    return scale, moved, offset, farthest
