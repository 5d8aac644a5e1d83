"""When the model cannot explain an injection: the verdict and the uncertainty it implies.

An estimate is ``ok`` only when the model explains the samples. The verdict of one fit:

- a fit of the robust cost is a mismatch by itself: the robust cost is used because the plain model
  left significant structure in the nuisance span (likelihood ratio), and absorbing it keeps the
  estimate near the truth on some model errors (hysteresis, series resistance) but not on others (a
  mounting stiffness 10 % off moves L_h by micrometres with a clean projected residual);
- a plain fit is a mismatch where its residual fails :func:`estimator.ident.adequacy.assess`.

The bias of a mismatched fit is unknown; its covariance is estimated from what the data show about
it: the plain and the robust estimate of the same samples differ by about as much as the model error
moves them (``d``); and the more structure the plain residual holds (``structure``, chi-square
units over 24 columns), the larger the error: ``g = sqrt(max(1, structure / 24))``. The covariance

    outer(d, d) + diag(floor^2 + g^2 scale^2)

(``mismatch_floor`` 1 % of N_u and 0.6 µm, ``mismatch_scale`` 0.2 % and 0.18 µm by default) is added
to the fit's covariance. The four numbers were measured on seeded series parts with every structural
parameter within ±10 % of Tables 1-2 and with a measurement chain
(``python -m sim_bench accuracy --sweep spread``): RMS(error/sigma) about 1 there, where the fit's
own sigma understated the error by 30-70 times.

The header's preload force may be off the true one (an ECU computes it from rail pressure): with a
relative uncertainty ``preload_rel_sigma`` its effect on (N_u, L_h) enters the covariance through
the linearised sensitivity of the fit (three simulations).
"""

from __future__ import annotations

import math

import numpy as np

from estimator.ident.adequacy import SMOOTH_COLUMNS, Adequacy, assess
from estimator.ident.config import IdentConfig
from estimator.ident.coords import UM_PER_M
from estimator.ident.cost import CostModel
from estimator.ident.local_fit import LocalFit

PRELOAD_STEP = 0.01          # relative step of F_open for its sensitivity
FD_NU, FD_LH_UM = 2e-3, 2e-3  # finite-difference steps of the Jacobian (N/V, µm)


def plain_adequacy(model: CostModel, fit: LocalFit, config: IdentConfig) -> Adequacy:
    """The adequacy test of a fit's residual over its model's window (projected in robust mode)."""
    r = fit.residual[: model.n]
    fitted = 2
    if model.robust:
        r = model.without_nuisance(r)
        fitted += model.basis.shape[1]
    return assess(r, fitted, config.adequacy_structure, config.adequacy_excess_z)


def model_error_cov(x: np.ndarray, other: np.ndarray | None, config: IdentConfig,
                    structure: float = float("nan")) -> np.ndarray:
    """The model-error covariance (N/V, µm) of a mismatched estimate ``x`` (N/V, µm), ``other`` the
    estimate of the other cost (plain or robust) on the same samples if it was made, ``structure``
    the plain residual's smooth energy (chi-square units; NaN if not tested)."""
    g2 = max(1.0, structure / SMOOTH_COLUMNS) if math.isfinite(structure) else 1.0
    nu = abs(float(x[0]))
    var = [(config.mismatch_floor[0] * nu) ** 2 + g2 * (config.mismatch_scale[0] * nu) ** 2,
           config.mismatch_floor[1] ** 2 + g2 * config.mismatch_scale[1] ** 2]
    cov = np.diag(var)
    if other is not None and np.all(np.isfinite(other)):
        d = np.asarray(x, dtype=float) - np.asarray(other, dtype=float)
        cov = cov + np.outer(d, d)
    return cov


def preload_cov(model: CostModel, fit: LocalFit, rel_sigma: float) -> np.ndarray:
    """The covariance (N/V, µm) a relative preload-force uncertainty ``rel_sigma`` adds to the fit:
    ``s s'`` with ``s = (J'J)^-1 J' dU/dF * sigma_F`` (zero where a simulation fails)."""
    x = fit.x
    fo = model.injection.f_open_n
    if rel_sigma <= 0 or not fit.success or fo <= 0:
        return np.zeros((2, 2))
    box_nu = model.sim.nu_range
    h_nu = FD_NU if x[0] + FD_NU <= box_nu[1] else -FD_NU
    nu = np.array([x[0], x[0] + h_nu, x[0], x[0]])
    lh = np.array([x[1], x[1], x[1] + FD_LH_UM, x[1]]) / UM_PER_M
    res = model.sim.simulate(model.current, nu, lh, np.array([fo, fo, fo, fo * (1 + PRELOAD_STEP)]))
    if not res.success.all():
        return np.zeros((2, 2))
    u = res.voltage_v[:, : model.n]
    jac = np.stack([(u[1] - u[0]) / h_nu, (u[2] - u[0]) / FD_LH_UM])   # (2, N): dU/dx
    du = (u[3] - u[0]) / PRELOAD_STEP * rel_sigma                       # dU per sigma of F_open
    if model.robust:
        jac = np.stack([model.without_nuisance(j) for j in jac])
        du = model.without_nuisance(du)
    jtj = jac @ jac.T
    if not np.all(np.isfinite(jtj)) or abs(np.linalg.det(jtj)) <= 1e-14 * jtj[0, 0] * jtj[1, 1]:
        return np.zeros((2, 2))
    s = np.linalg.solve(jtj, jac @ du)   # how far the fit moves for one sigma of F_open
    return np.outer(s, s)
