"""When the model cannot explain an injection: the verdict and the uncertainty it implies.

An estimate is ``ok`` only when the model explains the samples. The verdict of one fit:

- a fit of the robust cost is a mismatch by itself: the robust cost is used because the plain model
  left significant structure in the nuisance span (likelihood ratio), and absorbing it keeps the
  estimate near the truth on some model errors (hysteresis, series resistance) but not on others (a
  mounting stiffness 10 % off moves L_h by micrometres with a clean projected residual);
- a plain fit is a mismatch where its residual fails :func:`estimator.ident.fit.adequacy.assess`.

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

The header's preload force may be off the true one (an ECU computes it from rail pressure). One
injection carries F_open itself to about ±0.6 N: :func:`preload_check` tests the header's value
against the samples (a score test, chi-square with one degree of freedom), and a fit whose samples
point to another preload force is a mismatch too, its covariance widened by the move that force
implies. Below that threshold, where the samples' force is still two standard deviations off the
header's, the move enters the covariance without the status. With a relative uncertainty
``preload_rel_sigma`` the header's uncertainty enters every covariance through the linearised
sensitivity of the fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator._compiled.direct_call import DirectCall
from estimator.ident.config import IdentConfig
from estimator.ident.fit import sensitivity_kernel
from estimator.ident.fit.adequacy import SMOOTH_COLUMNS, Adequacy, assess
from estimator.ident.fit.cost import CostModel
from estimator.ident.fit.local_fit import LocalFit
from estimator.ident.fit.sensitivity_kernel import NOISE_NONE, SENS_FAILED, SENS_OK

PRELOAD_STEP = 0.01          # relative step of F_open for its sensitivity
PRELOAD_SUSPECT_CHI2 = 4.0   # the samples' own preload force two standard deviations off the header's
FD_NU, FD_LH_UM = 2e-3, 2e-3  # finite-difference steps of the Jacobian (N/V, µm)
CURRENT_PROBE = 1e-3         # current step of the current-noise probe simulation, relative to the current's peak
_SENSITIVITIES = DirectCall(sensitivity_kernel.sensitivities)


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


@dataclass(frozen=True)
class PreloadSensitivity:
    """How a fit's samples and point depend on F_open (:func:`sensitivities`): the fit's Jacobian
    ``jac`` (2, N) in V per (N/V, µm), the voltage's derivative ``du`` (N,) in V/N, ``s``, how far
    the fit's point moves per N of F_open (N/V, µm per N: ``(J'J)^-1 J' dU/dF``), and ``u0`` (N,), the
    simulated voltage at the fit's point (V)."""

    jac: np.ndarray
    du: np.ndarray
    s: np.ndarray
    u0: np.ndarray


def sensitivities(model: CostModel, fit: LocalFit) -> tuple[PreloadSensitivity | None, np.ndarray | None]:
    """How a fit's samples and point depend on F_open (:class:`PreloadSensitivity`), and the
    covariance (N/V, µm) the measured current's noise adds to the fit, from five simulations at its
    point in one compiled call (:func:`~estimator.ident.fit.sensitivity_kernel.sensitivities`).

    The sensitivity is None where a simulation fails or the problem is degenerate (projected off the
    nuisance span in robust mode); the covariance is None where the sensitivity is, or its probe
    cannot be simulated, and zero for a current without noise.

    The simulation is driven by the *measured* current, so its noise (``sigma_I``, from the current's
    own second differences, :func:`~estimator.ident.fit.adequacy.current_noise_a`) passes through the
    model into the simulated voltage. Its direct part, R(N_u) times white noise, is white and already
    in the residual's noise level; its dynamic part (the charge integrating the noise, and the stack's
    answer to it) is a slow random walk the noise level does not see, yet it moves the fit: at 0.02 A
    the fits' N_u errors were 1.8 times their noise-only sigma. The model's response to a current
    step (one simulation with the current offset by :data:`CURRENT_PROBE` of its peak) gives that
    dynamic part's impulse response ``h``; with ``G = J' H`` (H the lower-triangular Toeplitz matrix of
    ``h``) the covariance is ``sigma_I^2 (J'J)^-1 G G' (J'J)^-1``."""
    x = fit.x
    fo = model.injection.f_open_n
    if not fit.success or fo <= 0:
        return None, None
    p = model.problem     # the window as the compiled fit reads it: kernel, current, preload force, basis
    h_nu = FD_NU if x[0] + FD_NU <= p.nu_hi else -FD_NU
    n = model.n
    jac, du, s, u0, cov = np.empty((2, n)), np.empty(n), np.empty(2), np.empty(n), np.empty((2, 2))
    code = _SENSITIVITIES(p.model, p.automaton, p.table, p.h_us, p.current, float(x[0]), float(x[1]), p.f_open_n,
                          h_nu, FD_LH_UM, PRELOAD_STEP, CURRENT_PROBE, p.basis, p.robust, jac, du, s, u0, cov)
    if code == SENS_FAILED:
        return None, None
    return PreloadSensitivity(jac, du, s, u0), (cov if code in (SENS_OK, NOISE_NONE) else None)


def preload_cov(sens: PreloadSensitivity | None, f_open_n: float, rel_sigma: float) -> np.ndarray:
    """The covariance (N/V, µm) a relative preload-force uncertainty ``rel_sigma`` of the header's
    ``f_open_n`` (N) adds to the fit: ``s s'`` for the move per sigma of F_open (zero where the
    sensitivity could not be simulated)."""
    if rel_sigma <= 0 or sens is None:
        return np.zeros((2, 2))
    s = sens.s * f_open_n * rel_sigma
    return np.outer(s, s)


@dataclass(frozen=True)
class PreloadCheck:
    """Does the header's preload force agree with the samples? (:func:`preload_check`)

    Attributes
    ----------
    chi2 : the score statistic of F_open at the header's value, chi-square with one degree of freedom
        when it is right.
    delta_f_n : the change of F_open (N) the samples point to, and ``sd_f_n`` its standard deviation.
    shift : how far (N/V, µm) the estimate lies from where the samples' own F_open puts it (its bias
        if the header is off by ``delta_f_n``).
    threshold : the chi-square above which the header is taken as wrong.
    """

    chi2: float
    delta_f_n: float
    sd_f_n: float
    shift: np.ndarray
    threshold: float

    @property
    def inconsistent(self) -> bool:
        """The header's preload force cannot explain the samples."""
        return self.chi2 > self.threshold

    @property
    def suspect(self) -> bool:
        """The samples point to another preload force by more than their noise (two standard
        deviations): the move it implies belongs in sigma even where it is not yet a mismatch."""
        return self.chi2 > PRELOAD_SUSPECT_CHI2

    def reason(self, f_open_n: float) -> str:
        """Why the estimate is mismatched (a phrase)."""
        return (f"the header's preload force {f_open_n:.1f} N disagrees with the samples (they point to "
                f"{f_open_n + self.delta_f_n:.1f} ± {self.sd_f_n:.1f} N, chi2 {self.chi2:.0f})")


def preload_check(sens: PreloadSensitivity | None, fit: LocalFit, n: int, threshold: float) -> PreloadCheck | None:
    """Test the header's preload force against a plain fit's samples (its first ``n`` residuals): the
    score of F_open at the header's value (its derivative's part the fit's own two directions cannot
    take up, against the residual), chi-square(1) if the header is right. An ECU computes the force
    from the rail pressure; 10 % off at the nominal 28 N moves L_h by about 0.3 µm while the residual
    stays white, and one injection carries F_open to about ±0.6 N. None where the sensitivity could
    not be simulated."""
    if sens is None:
        return None
    g = sens.du - sens.s @ sens.jac                 # the part of dU/dF the fit cannot absorb
    gg = float(g @ g)
    if not (math.isfinite(gg) and gg > 0):
        return None
    r = fit.residual[:n]
    sigma = fit.sigma_v
    delta = float(g @ r) / gg
    return PreloadCheck(delta * delta * gg / sigma ** 2, delta, sigma / math.sqrt(gg), sens.s * delta, threshold)
