"""Event-located reference simulator of the hybrid model (scipy ``solve_ivp``, DOP853).

Independent of the fast simulator's discretisation: the right-hand side of the current region is
integrated with tight tolerances and ``max_step`` of a quarter sample, every guard of the region is
a terminal, directional event, and at an event the reset map is applied and integration restarts.
The current is piecewise linear between its samples (the same first-order hold as the fast
simulator); integration restarts at every kink of the current so no derivative jump is stepped over.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from estimator.errors import InfeasibleError, ParameterError
from estimator.model import dynamics as dyn
from estimator.model.automaton import apply_reset, build_automaton, guard_value, in_contact, rearmed
from estimator.model.drive import SAMPLE_PERIOD_S
from estimator.model.dynamics import MODE_OPEN, STATUS_EVENT_CAP, STATUS_INFEASIBLE, STATUS_OK
from estimator.model.fast_sim import BatchResult
from estimator.model.hysteresis import element_voltage
from estimator.model.parameters import InjectorParameters, check_nu_in, load_nominal
from estimator.units import UM_PER_M

_INSTANT_TOL = 1e-9      # guard value (scaled, normalised) above which a new region's guard fires at once
_MAX_EVENTS = 10_000


def _kinks(cur: np.ndarray) -> np.ndarray:
    """Sample indices where the piecewise linear current changes slope (always 0 and N-1)."""
    d2 = np.abs(np.diff(cur, 2))
    scale = max(float(np.max(np.abs(cur))), 1e-12)
    inner = np.flatnonzero(d2 > 1e-12 * scale) + 1
    return np.unique(np.concatenate(([0], inner, [cur.size - 1])))


def simulate_reference(current_a: np.ndarray, nu_n_per_v: float, lh_m: float, f_open_n: float | None = None,  # noqa: C901
                       params: InjectorParameters | None = None, dt_s: float = SAMPLE_PERIOD_S,
                       rtol: float = 1e-11, atol: float = 1e-11) -> BatchResult:
    """Simulate one candidate; returns a :class:`BatchResult` with B = 1.

    ``atol`` is in the scaled units of :data:`dynamics.Z_SCALE` (µm, m/s, µC).
    """
    p = params or load_nominal()
    check_nu_in(np.array([nu_n_per_v], dtype=float), *p.psa.simulation_nu_range)
    cur = np.asarray(current_a, dtype=float)
    if cur.ndim != 1 or cur.size < 2 or not np.all(np.isfinite(cur)):
        raise ParameterError("current must be a 1-D array of at least 2 finite samples (A)")
    f_open = p.valve.f_open_n if f_open_n is None else float(f_open_n)
    n = cur.size
    h = dt_s * dyn.TIME_SCALE  # µs
    t_us = np.arange(n) * h
    st = dyn.build_structure(p)
    d = dyn.Z_SCALE
    a_all = dyn.region_matrices(st, p, np.array([nu_n_per_v]))[0] * (d[:, None] / d[None, :]) / dyn.TIME_SCALE
    aut = build_automaton(st, d)
    seated = False   # after a close, reopening needs the spring force alone (see dynamics)

    # the hysteresis element replaces R(N_u) I and adds its own voltage (estimator.model.hysteresis)
    hys = p.hysteresis
    row = dyn.output_row(p, nu_n_per_v)
    if hys.present:
        row[dyn.ZI] = 0.0
    cout = row / d
    element = element_voltage(hys, p.psa.r0b_v_per_n, cur, dt_s, nu_n_per_v)

    out = {k: np.full(n, np.nan) for k in ("u", "s3", "s4")}
    mode = np.zeros(n, dtype=np.int8)
    t_contact = t_open = np.nan

    def result(status: int) -> BatchResult:
        def one(v: float) -> np.ndarray:
            return np.array([v], dtype=float)

        return BatchResult(
            t_s=t_us / dyn.TIME_SCALE, current_a=cur, nu_n_per_v=one(nu_n_per_v), lh_m=one(lh_m),
            f_open_n=one(f_open), voltage_v=(out["u"] + element)[None], s3_m=out["s3"][None] / UM_PER_M,
            s4_m=out["s4"][None] / UM_PER_M, mode=mode[None], t_contact_s=one(t_contact / dyn.TIME_SCALE),
            t_open_s=one(t_open / dyn.TIME_SCALE), success=np.array([status == STATUS_OK]),
            status=np.array([status]))

    try:
        z0, region = dyn.initial_state(p, nu_n_per_v, lh_m, f_open)
    except InfeasibleError:
        return result(STATUS_INFEASIBLE)
    x = (z0 * d)[: dyn.NX]
    consts = np.array([0.0, 0.0, lh_m * d[dyn.ZL], f_open, 1.0])  # [I, dI/dt, L_h, F_open, 1] scaled

    def augmented(t: float, xv: np.ndarray) -> np.ndarray:
        z = np.empty(dyn.NZ)
        z[: dyn.NX] = xv
        z[dyn.NX:] = consts
        z[dyn.ZI] = np.interp(t, t_us, cur)
        return z

    def record(k: int, xv: np.ndarray, r: int) -> None:
        z = augmented(t_us[k], xv)
        out["u"][k], out["s3"][k], out["s4"][k] = cout @ z, xv[dyn.S3], xv[dyn.S4]
        mode[k] = aut.region_mode[r]

    if in_contact(aut.region_mode[region]):
        t_contact = 0.0
    record(0, x, region)
    kinks = _kinks(cur)
    n_events = 0
    for seg in range(kinks.size - 1):
        k0, k1 = int(kinks[seg]), int(kinks[seg + 1])
        t = t_us[k0]
        while True:
            a = a_all[region]
            ax, au = a[: dyn.NX, : dyn.NX], a[: dyn.NX, dyn.NX:]
            active = [j for j in range(dyn.MAX_GUARDS) if aut.target[region, j] >= 0]

            def rhs(tt: float, xv: np.ndarray, ax: np.ndarray = ax, au: np.ndarray = au) -> np.ndarray:
                u = consts.copy()
                u[0] = np.interp(tt, t_us, cur)
                result: np.ndarray = ax @ xv + au @ u
                return result

            events = []
            for j in active:
                def ev(tt: float, xv: np.ndarray, r: int = region, j: int = j, sn: bool = seated) -> float:
                    return guard_value(aut.guards, aut.open_seated, aut.open_index, r, j, augmented(tt, xv), sn)
                ev.terminal, ev.direction = True, 1.0   # type: ignore[attr-defined]  # solve_ivp reads them
                events.append(ev)
            t_eval = t_us[(t_us > t + 1e-12) & (t_us <= t_us[k1] + 1e-12)]
            if t_eval.size == 0:  # an event landed on the knot itself
                break
            sol = solve_ivp(rhs, (t, t_us[k1]), x, method="DOP853", rtol=rtol, atol=atol,
                            max_step=h / 4, events=events, t_eval=t_eval)
            for tk, xk in zip(sol.t, np.asarray(sol.y).reshape(dyn.NX, -1).T):
                record(int(round(tk / h)), xk, region)
                # re-armed: takes effect when the integration restarts
                seated = rearmed(aut.guards, aut.open_index, region, augmented(tk, xk), seated)
            if sol.status != 1:  # reached the knot
                if sol.t.size:
                    x = sol.y[:, -1]
                break
            # a terminal event: which guard fired first
            te = [(ts[0], i) for i, ts in enumerate(sol.t_events) if ts.size]
            t_ev, i_ev = min(te)
            x = sol.y_events[i_ev][0].copy()
            jn: int | None = active[i_ev]
            t = t_ev
            while jn is not None:
                z = augmented(t, x)
                seated = apply_reset(z, aut.reset[region, jn], seated)
                x = z[: dyn.NX]
                region = int(aut.target[region, jn])
                n_events += 1
                if in_contact(aut.region_mode[region]) and np.isnan(t_contact):
                    t_contact = t
                if aut.region_mode[region] == MODE_OPEN and np.isnan(t_open):
                    t_open = t
                z = augmented(t, x)
                jn = next((jj for jj in range(dyn.MAX_GUARDS) if aut.target[region, jj] >= 0
                          and guard_value(aut.guards, aut.open_seated, aut.open_index, region, jj, z, seated) > _INSTANT_TOL), None)
            if n_events > _MAX_EVENTS:
                return result(STATUS_EVENT_CAP)
            if t >= t_us[k1] - 1e-12:
                break
    return result(STATUS_OK)
