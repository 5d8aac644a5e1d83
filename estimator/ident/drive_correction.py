"""The drive that opens every valve alike: a per-injector correction of the standard drive.

The estimator knows each injector's coupling factor N_u and idle stroke L_h (with their covariance)
and, once learned, its own structural parameters. From them this module computes how the standard
drive (:class:`~estimator.model.drive.StandardDrive`) must be changed so that the injector's valve
opens as the **target** says: the plateau current's scale (the stroke follows the charge) and the
start-of-charge offset (the opening instant moves with it one to one). The default target is the
nominal injector's (Tables 1-2, ``nominal_nu_n_per_v``, ``nominal_lh_um``) under the standard drive
at Table 2's preload force, so every injector of an engine opens as the nominal one does, whatever
its part and its rail pressure; a stroke (µm) and/or an opening instant (µs after the nominal start
of charging) may be configured instead.

The plateau stroke is close to linear in the scale (≈ 27 µm per unit) and in L_h (-1 µm/µm), so a
Newton step from the last correction, with derivatives refreshed every ``refresh`` injections or
when the model changes, reaches the target in one simulation an injection. The correction carries
its own sensitivities to the preload force (per kN) so that an amplifier applies it at the next
injection's rail pressure, and the σ of the stroke and the opening instant it will give, propagated
from the estimate's covariance; for a calibrated model that states what its own uncertainty leaves in
the valve's motion, that statement in place of the calibration's share of the covariance.

Only an ``ok`` estimate yields a correction; otherwise the last valid one is repeated and marked
``held`` (never a correction from a mismatched or uncertain estimate). Pure: no clocks, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from estimator.errors import EstimatorError
from estimator.ident.coords import UM_PER_M
from estimator.ident.measurement import Injection
from estimator.ident.status import Status
from estimator.ident.tracker import Tracker, TrackResult
from estimator.model.drive import STANDARD_AMPLITUDE_A, StandardDrive
from estimator.model.fast_sim import PLATEAU_WINDOW_S, FastSimulator
from estimator.model.parameters import NOMINAL_PRELOAD_N
from estimator.units import US_PER_S

N_PER_KN = 1e3
NOMINAL_NU_N_PER_V = 16.4      # Table 3's N_u at room temperature (the nominal injector of the default target)
NOMINAL_LH_UM = 3.0            # and its idle stroke
MAX_INTERVAL_S = 60.0          # a longer pause between injections: N_u is not carried forward by the drift rate
REFRESH_INJECTIONS = 16        # derivatives are simulated again this often (and whenever the model changes)
CORRECTION_STATES = ("none", "valid", "held")   # DriveCorrection.State: code = index (the DBC's value table)
STEP_NU, STEP_LH_UM, STEP_F_N, STEP_SCALE = 0.05, 0.1, 10.0, 0.01   # finite-difference steps


@dataclass(frozen=True)
class DriveTarget:
    """What every valve should do. ``stroke_um`` (plateau stroke, µm) and ``opening_us`` (opening
    instant after the nominal start of charging, µs): None takes the nominal injector's under the
    standard drive at ``nominal_preload_n``."""

    stroke_um: float | None = None
    opening_us: float | None = None
    nominal_nu_n_per_v: float = NOMINAL_NU_N_PER_V
    nominal_lh_um: float = NOMINAL_LH_UM
    nominal_preload_n: float = NOMINAL_PRELOAD_N
    scale_limits: tuple[float, float] = (0.7, 1.5)         # plateau current relative to the standard drive's
    offset_limits_us: tuple[float, float] = (-50.0, 50.0)  # start of charging relative to the standard drive's

    def __post_init__(self) -> None:
        lo, hi = self.scale_limits
        if not (0.0 < lo < hi and math.isfinite(hi)):
            raise ValueError(f"scale_limits = {self.scale_limits}: need 0 < low < high")
        lo, hi = self.offset_limits_us
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"offset_limits_us = {self.offset_limits_us} µs: need low < high")
        for name in ("stroke_um", "opening_us"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} = {v}: must be positive (or unset for the nominal injector's)")


@dataclass(frozen=True)
class Correction:
    """The correction of one injector's standard drive, for the preload force ``preload_n``.

    ``scale`` × the standard plateau current, charging ``offset_us`` later (negative: earlier) than the
    standard drive; at another preload force F an amplifier applies ``scale + scale_per_kn·(F -
    preload_n)/1000`` and likewise the offset (:meth:`at`). ``stroke_um``/``opening_us`` are what the
    injector's model predicts with it, ``sigma_*`` their 1σ from the estimate's covariance.
    ``held``: the estimate was not ``ok``, this is the last valid correction repeated (``valid`` False
    when there has been none yet: the standard drive). ``at_limit``: a limit kept the target out of reach.
    """

    scale: float = 1.0
    offset_us: float = 0.0
    stroke_um: float = math.nan
    opening_us: float = math.nan
    sigma_stroke_um: float = math.nan
    sigma_opening_us: float = math.nan
    target_stroke_um: float = math.nan
    target_opening_us: float = math.nan
    scale_per_kn: float = 0.0
    offset_per_kn_us: float = 0.0
    preload_n: float = math.nan
    valid: bool = False
    held: bool = False
    at_limit: bool = False

    @property
    def state(self) -> str:
        """``none`` (no ok estimate yet), ``valid`` (from this injection) or ``held`` (the last valid one):
        :data:`CORRECTION_STATES`, the words of ``DriveCorrection.State``."""
        return "held" if self.held else ("valid" if self.valid else "none")

    def at(self, preload_n: float, target: DriveTarget | None = None) -> tuple[float, float]:
        """(scale, offset µs) to apply at ``preload_n`` (N), within the target's limits."""
        if not self.valid:
            return 1.0, 0.0
        d_kn = (preload_n - self.preload_n) / N_PER_KN if math.isfinite(self.preload_n) else 0.0
        t = target or DriveTarget()
        scale = float(np.clip(self.scale + self.scale_per_kn * d_kn, *t.scale_limits))
        offset = float(np.clip(self.offset_us + self.offset_per_kn_us * d_kn, *t.offset_limits_us))
        return scale, offset

    def to_dict(self) -> dict[str, float | bool | str | None]:
        """JSON-ready (units in the names; NaN as None), with the :attr:`state` word."""
        out: dict[str, float | bool | str | None] = {}
        for k, v in self.__dict__.items():
            out[k] = None if isinstance(v, float) and not math.isfinite(v) else v
        out["state"] = self.state
        return out


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


_UNIT: dict[float, np.ndarray] = {}


def standard_samples(sim: FastSimulator, scale: float) -> np.ndarray:
    """The standard drive with ``scale`` × its plateau current, on the simulator's grid to the end of
    the plateau window (A): the drive is linear in its amplitude, so one sampling per grid serves."""
    unit = _UNIT.get(sim.dt_s)
    if unit is None:
        unit = _UNIT.setdefault(sim.dt_s, StandardDrive(STANDARD_AMPLITUDE_A).samples(PLATEAU_WINDOW_S[1], sim.dt_s))
    return scale * unit


def respond(sim: FastSimulator, scale: float, nu: float, lh_um: float, f_open_n: float) -> tuple[float, float]:
    """(plateau stroke µm, opening instant µs) of the model for the scaled standard drive; NaN when the
    valve does not open."""
    _, t_open, stroke = sim.valve_prediction(standard_samples(sim, scale), nu, lh_um / UM_PER_M, f_open_n)
    return stroke * UM_PER_M, t_open * US_PER_S


def linearise(sim: FastSimulator, scale: float, nu: float, lh_um: float, f_open_n: float) -> Response:
    """:func:`respond` and its forward-difference derivatives (five simulations)."""
    base = respond(sim, scale, nu, lh_um, f_open_n)

    def diff(other: tuple[float, float], step: float) -> tuple[float, float]:
        return ((other[0] - base[0]) / step, (other[1] - base[1]) / step)
    _lo_nu, hi_nu = sim.nu_range
    dnu = STEP_NU if nu + STEP_NU <= hi_nu else -STEP_NU
    return Response(base[0], base[1],
                    diff(respond(sim, scale + STEP_SCALE, nu, lh_um, f_open_n), STEP_SCALE),
                    diff(respond(sim, scale, nu + dnu, lh_um, f_open_n), dnu),
                    diff(respond(sim, scale, nu, lh_um + STEP_LH_UM, f_open_n), STEP_LH_UM),
                    diff(respond(sim, scale, nu, lh_um, f_open_n + STEP_F_N), STEP_F_N))


@dataclass
class _Injector:
    """What the compensator keeps per injector between injections."""

    last: Correction = field(default_factory=Correction)
    response: Response | None = None
    model: object | None = None         # the simulator the derivatives were taken with
    age: int = 0                        # injections since the derivatives were refreshed
    time_s: float = math.nan            # the last injection's time (s)


class DriveCompensator:
    """Per-injector drive corrections from the tracker's results (``update`` once per injection).

    ``nominal``: a simulator of the configured (nominal) parameters, for the default target (else each
    ``update`` passes one).
    """

    def __init__(self, target: DriveTarget | None = None, nominal: FastSimulator | None = None,
                 refresh: int = REFRESH_INJECTIONS) -> None:
        self.target = target or DriveTarget()
        self.nominal = nominal
        self.refresh = refresh
        self._injectors: dict[int, _Injector] = {}
        self._targets: dict[int, tuple[float, float]] = {}

    def warm_up(self, nominal: FastSimulator) -> None:
        """The target and one correction on a throw-away injector, so the first real one is not slow
        (the daemon calls it before READY)."""
        cov = np.diag([0.01, 0.01])
        self.update(-1, True, nominal, NOMINAL_NU_N_PER_V, NOMINAL_LH_UM + 1.0, cov, NOMINAL_PRELOAD_N, nominal)
        self.forget(-1)

    def forget(self, injector_id: int) -> None:
        """Drop an injector's corrections (a reset: it is driven with the standard drive again)."""
        self._injectors.pop(injector_id, None)

    def last(self, injector_id: int) -> Correction:
        """The injector's last correction (the standard drive, ``valid`` False, if none)."""
        st = self._injectors.get(injector_id)
        return st.last if st is not None else Correction()

    def target_at(self, nominal: FastSimulator) -> tuple[float, float]:
        """(stroke µm, opening µs) the target asks for: the configured values, else the nominal
        injector's (simulated once with ``nominal``, a simulator of the configured parameters)."""
        t = self.target
        if t.stroke_um is not None and t.opening_us is not None:
            return t.stroke_um, t.opening_us
        nominal = self.nominal or nominal
        got = self._targets.get(id(nominal))
        if got is None:
            got = respond(nominal, 1.0, t.nominal_nu_n_per_v, t.nominal_lh_um, t.nominal_preload_n)
            if not (math.isfinite(got[0]) and math.isfinite(got[1])):
                raise ValueError("the nominal injector's valve does not open under the standard drive")
            self._targets = {id(nominal): got}
        return (t.stroke_um if t.stroke_um is not None else got[0],
                t.opening_us if t.opening_us is not None else got[1])

    def update(self, injector_id: int, ok: bool, sim: FastSimulator | None, nu: float, lh_um: float,
               cov: np.ndarray | None, f_open_n: float, nominal: FastSimulator | None = None,
               rate_n_per_v_s: float = 0.0, time_s: float = math.nan) -> Correction:
        """The correction after one injection: computed from an ``ok`` estimate (``nu`` N/V, ``lh_um``
        µm, ``cov`` their 2×2 covariance in N/V and µm) with the injector's model ``sim`` at the
        preload force ``f_open_n`` (N; the next injection's if known, else this one's); otherwise the
        last valid one, ``held``. ``nominal``: a simulator of the configured parameters (the default
        target), when the compensator was built without one. The correction is for the next
        injection: N_u moves on by the filter's drift rate ``rate_n_per_v_s`` over the last interval
        between this injector's injections (``time_s``, s; a warm-up would otherwise leave it behind)."""
        st = self._injectors.setdefault(injector_id, _Injector())
        interval = time_s - st.time_s if math.isfinite(time_s) and math.isfinite(st.time_s) else 0.0
        st.time_s = time_s
        if math.isfinite(rate_n_per_v_s) and 0.0 < interval < MAX_INTERVAL_S:
            nu = nu + rate_n_per_v_s * interval
        nominal = self.nominal or nominal
        usable = (ok and sim is not None and nominal is not None and cov is not None and math.isfinite(nu)
                  and math.isfinite(lh_um) and math.isfinite(f_open_n))
        if not usable:
            st.last = replace(st.last, held=st.last.valid)
            return st.last
        assert sim is not None and cov is not None and nominal is not None
        try:
            corr = self._correct(st, sim, nominal, nu, lh_um, np.asarray(cov, dtype=float), f_open_n)
        except (EstimatorError, ValueError, FloatingPointError):   # e.g. N_u outside the simulator's range
            st.last = replace(st.last, held=st.last.valid)
            return st.last
        st.last = corr
        return corr

    def _correct(self, st: _Injector, sim: FastSimulator, nominal: FastSimulator, nu: float, lh_um: float,
                 cov: np.ndarray, f_open_n: float) -> Correction:
        t = self.target
        lo, hi = t.scale_limits
        target_stroke, target_opening = self.target_at(nominal)
        scale = float(np.clip(st.last.scale if st.last.valid else 1.0, lo, hi))
        if st.response is None or st.model is not sim or st.age >= self.refresh:
            st.response, st.model, st.age = linearise(sim, scale, nu, lh_um, f_open_n), sim, 0
            stroke, opening = st.response.stroke_um, st.response.opening_us
        else:
            stroke, opening = respond(sim, scale, nu, lh_um, f_open_n)
        st.age += 1
        r = st.response
        if not (math.isfinite(stroke) and math.isfinite(opening)) or r.d_scale[0] <= 0:
            # the valve does not open with this drive: the most current the limits allow, then again
            scale = hi
            st.response, st.model, st.age = linearise(sim, scale, nu, lh_um, f_open_n), sim, 1
            r = st.response
            stroke, opening = r.stroke_um, r.opening_us
            if not (math.isfinite(stroke) and math.isfinite(opening)) or r.d_scale[0] <= 0:
                raise ValueError("the valve does not open within the scale limits")
        for _ in range(3):   # Newton on the scale: the stroke is close to linear in it
            new = float(np.clip(scale + (target_stroke - stroke) / r.d_scale[0], lo, hi))
            if abs(new - scale) < 1e-5:
                break
            step = new - scale
            scale = new
            if abs(step) * r.d_scale[0] < 0.05:   # small: the linear model is exact enough, no simulation
                stroke, opening = stroke + r.d_scale[0] * step, opening + r.d_scale[1] * step
                break
            stroke, opening = respond(sim, scale, nu, lh_um, f_open_n)
            if not (math.isfinite(stroke) and math.isfinite(opening)):
                raise ValueError("the valve does not open within the scale limits")
        at_limit = scale in (lo, hi) and abs(stroke - target_stroke) > 0.01
        olo, ohi = t.offset_limits_us
        offset = float(np.clip(target_opening - opening, olo, ohi))
        at_limit = at_limit or offset in (olo, ohi)
        # at another preload force the drive that keeps stroke and opening on target (to first order)
        ds_df = -r.d_f[0] / r.d_scale[0]
        do_df = -(r.d_f[1] + r.d_scale[1] * ds_df)
        js = np.array([r.d_nu[0], r.d_lh[0]])
        jo = np.array([r.d_nu[1], r.d_lh[1]])
        cal = sim.params.calibration   # what the model's own uncertainty leaves in the motion (0: in cov)
        var_s = float(js @ cov @ js) + (cal.stroke_rel_sigma * stroke) ** 2
        var_o = float(jo @ cov @ jo) + (cal.opening_sigma_s * US_PER_S) ** 2
        return Correction(scale, offset, stroke, offset + opening, math.sqrt(max(var_s, 0.0)),
                          math.sqrt(max(var_o, 0.0)), target_stroke, target_opening,
                               ds_df * N_PER_KN, do_df * N_PER_KN, f_open_n, True, False, at_limit)


def correction_after(compensator: DriveCompensator, tracker: Tracker, inj: Injection, res: TrackResult,
                     preload_n: float | None = None) -> Correction:
    """The injector's drive correction after the tracker's result ``res`` for ``inj``: from an ``ok``
    estimate with the model the injector is estimated with, at ``preload_n`` (N; default this
    injection's preload force), its covariance the published σ (which may cover a bias) with the
    filter's correlation; otherwise the last one, held. Where the injector's calibrated model states
    the uncertainty it leaves in the valve's motion and that model is validated (:func:`_validated`),
    that replaces the share of N_u's and L_h's covariance the calibration put there (the motion keeps
    less of a structural error than they do)."""
    iid = inj.injector_id
    st = tracker.states.get(iid)
    ok = res.status == Status.OK
    sim = tracker.model_simulator(iid, inj.dt_s)
    cov = None
    if st is not None and ok:
        p = np.asarray(st.p, dtype=float)[:2, :2]
        var = np.array([res.sigma_nu ** 2, (res.sigma_lh_m * UM_PER_M) ** 2])
        cal = sim.params.calibration if sim is not None else None
        if cal is not None and cal.has_response and _validated(tracker, iid):
            var = np.maximum(var - np.diag(cal.cov(res.nu_n_per_v)), np.diag(p))
        rho = float(p[0, 1] / math.sqrt(p[0, 0] * p[1, 1])) if p[0, 0] > 0 and p[1, 1] > 0 else 0.0
        c = rho * math.sqrt(var[0] * var[1])
        cov = np.array([[var[0], c], [c, var[1]]])
    return compensator.update(iid, ok, sim, res.nu_n_per_v, res.lh_m * UM_PER_M,
                              cov, inj.f_open_n if preload_n is None else preload_n,
                              tracker.nominal_simulator(inj.dt_s), res.rate_n_per_v_s, inj.time_s)


def _validated(tracker: Tracker, injector_id: int) -> bool:
    """Whether the injector's model may be trusted with its own statement of the motion's uncertainty:
    a model learned from a first window of twelve injections only once its refinement over a larger
    window agreed with it or replaced it (that window left one part of 24 with N_u four of its stated
    σ off); a parameter file's model, or one used without learning, as it is."""
    status = tracker.calibration.get(injector_id)
    return status is None or status.source != "learned" or status.refined

