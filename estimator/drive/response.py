"""The valve's response to the scaled standard drive: plateau stroke and opening instant of the model,
and their derivatives in the scale, N_u, L_h and the preload force."""

from __future__ import annotations

from dataclasses import dataclass

from estimator.drive.standard import AmplifierDrive
from estimator.ident.coords import UM_PER_M
from estimator.model.fast_sim import PLATEAU_WINDOW_S, FastSimulator
from estimator.units import US_PER_S

STEP_NU, STEP_LH_UM, STEP_F_N, STEP_SCALE = 0.05, 0.1, 10.0, 0.01   # finite-difference steps

_TRAPEZOIDS: dict[float, AmplifierDrive] = {}


def trapezoid(dt_s: float) -> AmplifierDrive:
    """The built-in trapezoid on the grid ``dt_s`` (s), built once per grid."""
    got = _TRAPEZOIDS.get(dt_s)
    if got is None:
        got = _TRAPEZOIDS.setdefault(dt_s, AmplifierDrive.trapezoid(dt_s))
    return got


@dataclass(frozen=True)
class Response:
    """The valve's response to the scaled standard drive at one operating point, and its derivatives:
    stroke (µm) and opening instant (µs after the start of charging)."""

    stroke_um: float
    opening_us: float
    d_scale: tuple[float, float]        # d(stroke, opening)/d scale
    d_nu: tuple[float, float]           # per N/V
    d_lh: tuple[float, float]           # per µm
    d_f: tuple[float, float]            # per N


def respond(sim: FastSimulator, scale: float, nu: float, lh_um: float, f_open_n: float,
            drive: AmplifierDrive | None = None) -> tuple[float, float]:
    """(plateau stroke µm, opening instant µs) of the model for ``scale`` × the standard drive
    (``drive``, default the built-in trapezoid; a measured one with the model's measurement chain undone);
    NaN when the valve does not open. The drive is linear in its scale, so one sampling per grid serves
    every scale."""
    unit = (drive or trapezoid(sim.dt_s)).actuator_samples(sim.dt_s, PLATEAU_WINDOW_S[1], sim.params.chain)
    _, t_open, stroke = sim.valve_prediction(scale * unit, nu, lh_um / UM_PER_M, f_open_n)
    return stroke * UM_PER_M, t_open * US_PER_S


def linearise(sim: FastSimulator, scale: float, nu: float, lh_um: float, f_open_n: float,
              drive: AmplifierDrive | None = None) -> Response:
    """:func:`respond` and its forward-difference derivatives (five simulations)."""
    base = respond(sim, scale, nu, lh_um, f_open_n, drive)

    def diff(other: tuple[float, float], step: float) -> tuple[float, float]:
        return ((other[0] - base[0]) / step, (other[1] - base[1]) / step)
    _lo_nu, hi_nu = sim.nu_range
    dnu = STEP_NU if nu + STEP_NU <= hi_nu else -STEP_NU
    return Response(base[0], base[1],
                    diff(respond(sim, scale + STEP_SCALE, nu, lh_um, f_open_n, drive), STEP_SCALE),
                    diff(respond(sim, scale, nu + dnu, lh_um, f_open_n, drive), dnu),
                    diff(respond(sim, scale, nu, lh_um + STEP_LH_UM, f_open_n, drive), STEP_LH_UM),
                    diff(respond(sim, scale, nu, lh_um, f_open_n + STEP_F_N, drive), STEP_F_N))
