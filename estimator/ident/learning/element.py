"""Whether an injector needs a hysteresis element, and how uncertain its shape leaves the estimates.

The paper's actuator model explains a part's charge-voltage hysteresis by R(N_u)·I. Where a batch
refuses that, :func:`calibrate_with_hysteresis_if_needed` calibrates it again with a hysteresis element
(:mod:`estimator.model.hysteresis`) in its place, twice: once with the plays at
:data:`~estimator.ident.learning.electrical.HYSTERESIS_THRESHOLDS_C` and once at
:data:`INTERLEAVED_THRESHOLDS_C`, whose half-widths lie between those. A sum of plays explains a
part's hysteresis only as far as its grid can draw the part's shape; what the grid cannot draw, the
structure and each injection's L_h take up while the voltage still fits to the noise. Two grids that
both explain the batch yet disagree on each injection's (N_u, L_h) show that error: the element is
adopted only when both explain the batch, and their disagreement joins the calibration's stated
uncertainty (:class:`~estimator.model.parameters.CalibrationUncertainty`), as two learned models
that explain the voltage alike already do (:func:`estimator.ident.learning.selfcal.disagreement`).

Measured on the bench's Bouc–Wen parts (a shape no sum of plays is built from): one grid explained a
part's first window (residual 7.4 sd, below the refusal at 8) and left its L_h up to 0.32 µm off
with a stated σ of 0.07 µm; the other grid did not explain it (20 sd). On a larger Bouc–Wen part the
two grids swapped roles and disagreed on L_h by 0.38 µm RMS; on Prandtl–Ishlinskii parts (the
element's own form) they agreed within 0.03 µm.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import replace
from typing import Any

import numpy as np

from estimator.errors import EstimatorError
from estimator.ident.fit.idle_stroke import predict_valve
from estimator.ident.learning.electrical import (
    HYSTERESIS_THRESHOLDS_C,
    WINDOW_S,
    ElectricalCalibration,
    calibrate_electrical,
    usable_injections,
)
from estimator.ident.measurement import Injection
from estimator.model.chain import MeasurementChain
from estimator.model.fast_sim import FastSimulator
from estimator.model.parameters import CalibrationUncertainty, InjectorParameters, load_nominal
from estimator.units import M_PER_UM

#: the second grid's play half-widths (C): each between two of the first grid's, the last beyond them
INTERLEAVED_THRESHOLDS_C = tuple(v * 1e-3 for v in (0.0, 0.006, 0.012, 0.018, 0.025, 0.035, 0.045, 0.057, 0.072,
                                                     0.09, 0.115, 0.15, 0.2, 0.26, 0.32))
GRIDS_C = (HYSTERESIS_THRESHOLDS_C, INTERLEAVED_THRESHOLDS_C)


def calibrate_with_hysteresis_if_needed(injections: list[Injection], base: InjectorParameters | None = None, *,
                                        hysteresis: bool, **kw: Any) -> ElectricalCalibration:
    """:func:`~estimator.ident.learning.electrical.calibrate_electrical` with the paper's R(N_u)·I, and
    (``hysteresis``) where that does not explain the batch, again with a hysteresis element in its
    place on each of :data:`GRIDS_C`. The element's calibration is adequate only when both grids
    explain the batch; it is the one that explains it better, its uncertainty widened by the two
    grids' disagreement (:func:`widened`). A refusal is the nearer miss, saying why. A part the
    paper's model explains never gets an element (``docs/design.md``)."""
    base = base or load_nominal()
    res = calibrate_electrical(injections, base, **kw)
    if res.adequate or not hysteresis:
        return res
    fits = [calibrate_electrical(injections, base, hysteresis=True, thresholds_c=g, **kw) for g in GRIDS_C]
    if all(f.adequate for f in fits):
        best, other = sorted(fits, key=lambda f: f.chi2)
        return widened(best, other, injections, base.chain, kw.get("window_s", WINDOW_S))
    nearer = min(fits, key=lambda f: f.misfit_z)
    if nearer.misfit_z >= res.misfit_z:
        return res                      # the refusal names the nearer miss
    if not nearer.adequate:
        return nearer
    worse = max(fits, key=lambda f: f.misfit_z)
    why = (f"a hysteresis element explains the batch on one grid of plays only (residual {nearer.misfit_z:.1f} "
           f"and {worse.misfit_z:.1f} sd above the noise): the part's hysteresis has a shape the element cannot "
           "draw, and the L_h it leaves is not known")
    return replace(nearer, adequate=False, misfit_z=worse.misfit_z, refusal=why, warnings=[*nearer.warnings, why])


def widened(best: ElectricalCalibration, other: ElectricalCalibration, injections: list[Injection],
            chain: MeasurementChain, window_s: float = WINDOW_S) -> ElectricalCalibration:
    """``best`` whose stated uncertainty also covers its disagreement with ``other`` (the same batch
    calibrated on the other grid, from a base with measurement chain ``chain``): the RMS over the
    batch of the two fits' difference in each injection's N_u (relative) and L_h, and in the valve's
    predicted plateau stroke (relative) and opening instant, each added in quadrature to ``best``'s
    own. The full difference, not half: the two grids' errors may share a sign."""
    usable, _ = usable_injections(injections, chain)
    d = disagreement_of(best, other, [inj.window(window_s) for inj in usable])
    cal = best.params.calibration
    both = replace(cal, nu_rel_sigma=min(math.hypot(cal.nu_rel_sigma, d.nu_rel_sigma), 0.1),
                   lh_sigma_m=min(math.hypot(cal.lh_sigma_m, d.lh_sigma_m), 10e-6),
                   stroke_rel_sigma=min(math.hypot(cal.stroke_rel_sigma, d.stroke_rel_sigma), 1.0),
                   opening_sigma_s=min(math.hypot(cal.opening_sigma_s, d.opening_sigma_s), 100e-6))
    grid = (f"the element's two grids of plays disagree on L_h by {d.lh_sigma_m / M_PER_UM:.3f} µm and on the "
            f"predicted stroke by {100 * d.stroke_rel_sigma:.2f} % (RMS; in the stated uncertainty)")
    return replace(best, params=replace(best.params, calibration=both), warnings=[*best.warnings, grid])


def disagreement_of(a: ElectricalCalibration, b: ElectricalCalibration, batch: list[Injection]) -> CalibrationUncertainty:
    """The RMS over ``batch`` (the calibrations' usable injections, cut to their window) of what ``a``
    and ``b`` say differently: N_u (relative), L_h (m), the predicted plateau stroke (relative) and
    opening instant (s). An injection the valve does not open on under either is left out of the
    last two."""
    nu_rel = a.nu_n_per_v / b.nu_n_per_v - 1.0
    lh_m = (a.lh_um - b.lh_um) * M_PER_UM
    sims = [FastSimulator(replace(c.params, chain=MeasurementChain()), batch[0].dt_s) for c in (a, b)]
    fits = [(inj, (float(a.nu_n_per_v[j]), float(a.lh_um[j]) * M_PER_UM),
             (float(b.nu_n_per_v[j]), float(b.lh_um[j]) * M_PER_UM)) for j, inj in enumerate(batch[:a.lh_um.size])]
    stroke, opening = valve_spread(sims[0], sims[1], fits)
    return CalibrationUncertainty(min(_rms(nu_rel), 0.1), min(_rms(lh_m), 10e-6), min(stroke, 1.0),
                                  min(opening, 100e-6))


def valve_spread(sim_a: FastSimulator, sim_b: FastSimulator,
                 fits: Iterable[tuple[Injection, tuple[float, float], tuple[float, float]]]) -> tuple[float, float]:
    """The RMS over injections, each with its fit (N_u N/V, L_h m) on model ``a`` and on model ``b``,
    of what ``a`` predicts differently from ``b`` for the valve: the plateau stroke (relative) and the
    opening instant (s). An injection either fit failed on (NaN), a simulator refuses, or the valve
    does not open on under either is left out (0 when none is left)."""
    stroke, opening = [], []
    for inj, fit_a, fit_b in fits:
        d = _valve_difference(inj, sim_a, fit_a, sim_b, fit_b)
        if d is not None:
            stroke.append(d[0])
            opening.append(d[1])
    return _rms(stroke), _rms(opening)


def _rms(v: Any) -> float:
    """Root mean square (0 for none)."""
    return float(np.sqrt(np.mean(np.square(v)))) if len(v) else 0.0


def _valve_difference(inj: Injection, sim_a: FastSimulator, fit_a: tuple[float, float], sim_b: FastSimulator,
                      fit_b: tuple[float, float]) -> tuple[float, float] | None:
    """What model ``a`` at its fit ``fit_a`` (N_u N/V, L_h m) predicts differently from model ``b`` at
    ``fit_b`` for the valve on ``inj``: the plateau stroke (``a``'s over ``b``'s, less 1) and the
    opening instant (s). None where either fit failed (NaN), a simulator refuses it, or the valve
    does not open under either."""
    if not all(math.isfinite(v) for v in (*fit_a, *fit_b)):
        return None
    try:
        ya, yb = predict_valve(sim_a, inj, *fit_a), predict_valve(sim_b, inj, *fit_b)
    except EstimatorError:     # e.g. an N_u at the edge of a simulator's range
        return None
    if all(np.isfinite(ya[1:])) and all(np.isfinite(yb[1:])) and yb[2] > 0:
        return ya[2] / yb[2] - 1.0, ya[1] - yb[1]
    return None
