"""The drive that opens every valve alike: a per-injector correction of the amplifier's standard drive.

The estimator knows each injector's coupling factor N_u and idle stroke L_h (with their covariance)
and, once learned, its own structural parameters. From them this module computes how the amplifier's
standard drive (:mod:`estimator.drive.standard`: learned from the measured current, or a configured
table) must be changed so that the injector's valve opens as the **target** says
(:mod:`estimator.drive.target`): the plateau current's scale (the stroke follows the charge) and the
start-of-charge offset (the opening instant moves with it one to one).

The plateau stroke is close to linear in the scale (≈ 27 µm per unit) and in L_h (-1 µm/µm), so a
Newton step from the last correction, with derivatives refreshed every ``refresh`` injections or
when the model or the drive changes, reaches the target in one simulation an injection. The
correction carries its own sensitivities to the preload force (per kN), the limits it was computed
with, and the σ of the stroke and the opening instant it will give, propagated from the estimate's
covariance; for a calibrated model that states what its own uncertainty leaves in the valve's
motion, that statement in place of the calibration's share of the covariance.

Only an ``ok`` estimate whose injection's current agrees with the standard drive yields a fresh
correction. After an estimate that is not ``ok`` the correction is computed again for the new
preload force from the last ``ok`` estimate (N_u carried on by its drift rate) and marked ``held``:
never carried across idle by a first-order sensitivity. A measured current the standard drive does
not explain holds the last correction as it is and says why. Pure: no clocks, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from typing import NamedTuple

import numpy as np

from estimator.drive import row_carry
from estimator.drive.response import Response, linearise, respond, trapezoid
from estimator.drive.standard import AmplifierDrive, DriveCheck, DriveLearner
from estimator.drive.target import NOMINAL_LH_UM, NOMINAL_NU_N_PER_V, DriveTarget, resolve
from estimator.errors import EstimatorError
from estimator.ident.coords import UM_PER_M
from estimator.ident.measurement import Injection
from estimator.ident.status import Status
from estimator.ident.tracking.tracker import Tracker, TrackResult
from estimator.model.drive import SAMPLE_PERIOD_S
from estimator.model.fast_sim import FastSimulator
from estimator.model.parameters import NOMINAL_PRELOAD_N
from estimator.units import US_PER_S

N_PER_KN = 1e3
MAX_INTERVAL_S = 60.0          # a longer pause between injections: N_u is not carried forward by the drift rate
REFRESH_INJECTIONS = 32        # derivatives are simulated again this often (and whenever the model changes)
ROW_PERIOD = 4                 # one preload-table row computed again every this many injections (the others
                               # carried by their derivatives; a row they would move too far goes first)
ROW_REFRESH = 32               # a row's derivatives are simulated again after this many of its corrections
ROWS_AFTER_CHANGE = 4          # rows computed each injection after the model or the drive changed
LINEAR_STROKE_UM = 0.1         # a Newton step that moves the stroke and the opening instant less than these is
LINEAR_OPENING_US = 0.3        # taken from the derivatives, without a simulation (over 2,000 random steps within
                               # these, anywhere in the operating range, 0.001 µm and 0.06 µs off a simulation)
CARRY_OPENING_US = 0.5         # a table row the derivatives would move further is simulated again at once
FAR_ROWS = 2                   # at most this many such rows an injection, the farthest first (a row carried
                               # across a bend of the opening instant is the farthest: its derivative is none)
DERIVATIVE_MISS_US = 0.2       # such a row whose simulation lands further than this from its carry gets its
                               # derivatives taken again
CARRY_STROKE_UM = 0.1          # the correction is carried from the last simulation while the estimate and the
CARRY_MAIN_OPENING_US = 0.3    # scale move its stroke and opening instant less than these (both are close to
                               # linear in N_u, L_h and the scale: over 1,900 random moves within these, anywhere
                               # in the operating range, the carry missed a simulation by 0.002 µm and 0.015 µs at
                               # the p99), and the preload force less than the next two: the opening instant
CARRY_PRELOAD_STROKE_UM = 0.02  # bends within a few newtons near idle, where a derivative in the preload force
CARRY_PRELOAD_OPENING_US = 0.1  # is no derivative (0.05 µm and 0.3 µs there cost the ECU loop's opening p95)
CARRY_NU_SHARE = 0.5           # a held correction's N_u, carried by the drift rate, is uncertain by this share of
                               # the carry
STROKE_PER_SCALE_UM = 27.0     # the plateau stroke's growth per unit of scale: a first step toward the target
TRUST_STEP = 0.1               # the scale moves at most this far beyond the levels its model was checked at
CHECKED_SLACK = 0.01           # a measured scale this close to the checked ones is among them (the amplifier's
                               # ripple and the scale's own noise)
TRUST_REL = 0.05               # σ: this share of the motion the model is extrapolated to beyond those levels (a
                               # model learned at the standard drive and driven at 1.4 was 0.46 µm off in 11 µm)
PRELOAD_REL = 1.0              # σ: this share of the motion a model extrapolates from the lowest preload force it
                               # was calibrated over toward idle, where the valve's own spring and pressure balance,
                               # which the voltage hardly sees, decide the motion. On the compensation bench's lots
                               # the error was 0.03-0.3 of it for most parts, 0.58-0.68 for one (0.45 µm short at
                               # 30 N, calibrated at 47-180 N) and 1.9 for a part whose opening instant bends 2-3 N
                               # below the model's (1.95 µs late at 39.5 N, calibrated down to 40.7 N): the whole
                               # motion, not a share, is what nothing checked; above the span 0.02-0.06, within
                               # the stated σ
JITTER_WEIGHT = 0.1            # weight of each new injection in the running mean square of the jitter
JITTER_MIN = 5                 # injections compared before the jitter enters σ
JITTER_CLIP = 4.0              # a difference beyond this many RMS (plus the floor, µm and µs) counts as that much
JITTER_FLOOR = (0.05, 0.5)
CORRECTION_STATES = ("none", "valid", "held")   # DriveCorrection.State: code = index (the DBC's value table)
_DEFAULT_TARGET = DriveTarget()
Table = tuple[tuple[float, float, float, float, float], ...]   # rows (preload N, scale, offset µs, σ stroke µm,
#                                                                  σ opening µs), increasing in the preload force


@dataclass(frozen=True)
class Correction:
    """The correction of one injector's standard drive, for the preload force ``preload_n``.

    ``scale`` × the standard drive's current, charging ``offset_us`` later (negative: earlier) than the
    standard drive; at another preload force F an amplifier applies ``scale + scale_per_kn·(F -
    preload_n)/1000`` and likewise the offset, within the limits the correction was computed with
    (:meth:`at`). ``stroke_um``/``opening_us`` are what the injector's model predicts with it,
    ``sigma_*`` their 1σ. ``held``: not from this injection's estimate (it was not ``ok``, or its current
    disagreed with the standard drive; ``reason`` says which); ``valid`` False: no correction yet (the
    standard drive). ``at_limit``: a limit kept the target out of reach, and stroke and opening are what
    the limited drive gives. ``drive_scale``: the measured current's scale relative to the standard
    drive (NaN: not checked). ``checked``: the scales at which the injector's model explained the
    measured injections (``ok``); ``trust_limited``: the scale stopped ``TRUST_STEP`` beyond them short of
    the target (the trust region: the target is approached as injections at the new levels confirm
    the model), stroke and opening being what that drive gives, σ widened for the extrapolation.
    ``table``: the correction at the preload table's forces, rows (preload N, scale, offset µs, σ of
    stroke µm and opening µs there), taken by :meth:`at` and :meth:`sigma_at` (empty: the sensitivities).
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
    scale_limits: tuple[float, float] = _DEFAULT_TARGET.scale_limits
    offset_limits_us: tuple[float, float] = _DEFAULT_TARGET.offset_limits_us
    reason: str = ""
    drive_scale: float = math.nan
    table: Table = ()
    checked: tuple[float, float] | None = None
    trust_limited: bool = False

    @classmethod
    def of(cls, **values: object) -> Correction:
        """A correction from its fields by name (the others their defaults), as the constructor makes it
        but without the frozen dataclass's ``__setattr__`` per field: every injection makes one, and the
        21 calls took 7 µs of the correction's 40 on a slow hour."""
        if not _CORRECTION_FIELDS.issuperset(values):
            raise TypeError(f"Correction has no field {', '.join(sorted(set(values) - _CORRECTION_FIELDS))}")
        out = object.__new__(cls)
        out.__dict__.update(_CORRECTION_DEFAULTS)
        out.__dict__.update(values)
        return out

    @property
    def state(self) -> str:
        """``none`` (no ok estimate yet), ``valid`` (from this injection) or ``held`` (the last valid one):
        :data:`CORRECTION_STATES`, the words of ``DriveCorrection.State``."""
        return "held" if self.held else ("valid" if self.valid else "none")

    def at(self, preload_n: float) -> tuple[float, float]:
        """(scale, offset µs) to apply at ``preload_n`` (N), within the limits it was computed with: the
        preload table interpolated linearly (clamped at its ends), shifted so that it gives this
        correction at its own preload force; without a table, the per-kN sensitivities."""
        if not self.valid:
            return 1.0, 0.0
        if self.table:
            f, s, o = np.array(self.table).T[:3]
            here = math.isfinite(self.preload_n)
            scale = float(np.interp(preload_n, f, s)) + (self.scale - float(np.interp(self.preload_n, f, s)) if here else 0.0)
            offset = float(np.interp(preload_n, f, o)) + (self.offset_us - float(np.interp(self.preload_n, f, o))
                                                          if here else 0.0)
        else:
            d_kn = (preload_n - self.preload_n) / N_PER_KN if math.isfinite(self.preload_n) else 0.0
            scale = self.scale + self.scale_per_kn * d_kn
            offset = self.offset_us + self.offset_per_kn_us * d_kn
        return float(np.clip(scale, *self.scale_limits)), float(np.clip(offset, *self.offset_limits_us))

    def sigma_at(self, preload_n: float) -> tuple[float, float]:
        """σ of the stroke (µm) and the opening instant (µs) the correction gives where :meth:`at` takes
        it, at ``preload_n`` (N): at the correction's own preload force its own σ; elsewhere the table's
        rows interpolated linearly (clamped at its ends), with whatever the correction's own σ states
        beyond the rows at its preload force added in quadrature (a held correction's carried N_u, a
        newer estimate's jitter); without a table, its own σ. A model used below the preload forces it
        was calibrated over states the motion it extrapolates there, so the rows near idle can state
        far more than a correction at full load."""
        own = (self.sigma_stroke_um, self.sigma_opening_us)
        if not (self.valid and self.table) or preload_n == self.preload_n:
            return own
        columns = np.array(self.table).T
        f = columns[0]
        out = []
        for rows, mine in zip(columns[3:5], own):
            there = float(np.interp(preload_n, f, rows))
            here = float(np.interp(self.preload_n, f, rows)) if math.isfinite(self.preload_n) else there
            extra = mine * mine - here * here if math.isfinite(mine) else 0.0
            out.append(math.sqrt(there * there + max(extra, 0.0)))
        return out[0], out[1]

    def to_dict(self) -> dict[str, object]:
        """JSON-ready (units in the names; NaN as None; the table as rows [preload N, scale, offset µs,
        σ stroke µm, σ opening µs]),
        with the :attr:`state` word."""
        out: dict[str, object] = {}
        for k, v in self.__dict__.items():
            out[k] = None if isinstance(v, float) and not math.isfinite(v) else (
                [list(x) if isinstance(x, tuple) else x for x in v] if isinstance(v, tuple) else v)
        out["state"] = self.state
        return out


_CORRECTION_DEFAULTS = {f.name: f.default for f in fields(Correction)}
_CORRECTION_FIELDS = frozenset(_CORRECTION_DEFAULTS)


class _OkEstimate(NamedTuple):
    """The last ``ok`` estimate a held correction is computed from again."""

    sim: FastSimulator
    nu: float
    lh_um: float
    cov: np.ndarray
    rate_n_per_v_s: float
    time_s: float


@dataclass
class _Point:
    """The Newton iteration's memory at one preload force: the derivatives and what they were taken
    with, and the last correction computed there."""

    response: Response | None = None
    model: FastSimulator | None = None  # the simulator the derivatives were taken with
    drive: AmplifierDrive | None = None   # and the standard drive
    age: int = 0                        # corrections since the derivatives were refreshed
    last: Correction | None = None
    anchor: tuple[float, ...] | None = None   # the last simulation: scale, N_u, L_h µm, preload N, stroke µm,
                                              # opening µs (the correction's carries start from it)
    due: bool = False                   # its derivatives are to be taken again (deferred)

    def linearise(self, sim: FastSimulator, scale: float, nu: float, lh_um: float, f_open_n: float,
                  drive: AmplifierDrive, age: int = 0) -> Response:
        """Take the derivatives afresh at ``scale`` (N_u, L_h µm, preload N) with ``sim`` and ``drive``:
        they become the point's, the carries' anchor this simulation, ``age`` corrections old."""
        r = linearise(sim, scale, nu, lh_um, f_open_n, drive)
        self.response, self.model, self.drive, self.age, self.due = r, sim, drive, age, False
        self.anchor = (scale, nu, lh_um, f_open_n, r.stroke_um, r.opening_us)
        return r


@dataclass
class _Injector:
    """What the compensator keeps per injector between injections."""

    last: Correction = field(default_factory=Correction)
    main: _Point = field(default_factory=_Point)
    rows: list[_Point] = field(default_factory=list)   # one per preload of the table
    grid: np.ndarray = field(default_factory=lambda: np.empty((0, row_carry.COLUMNS)))   # the rows' numbers
    next_row: int = 0
    turn: int = 0                       # injections with a table
    time_s: float = math.nan            # the last injection's time (s)
    ok: _OkEstimate | None = None
    checked: tuple[float, float] | None = None   # scales at which the model below explained the injections
    checked_model: object | None = None
    steps: list[float] = field(default_factory=lambda: [TRUST_STEP, TRUST_STEP])   # the trust region beyond the
    # checked scales, below and above: halved toward a level the model failed at, doubled back as levels pass
    measured: tuple[np.ndarray, tuple[AmplifierDrive | None, str, float]] | None = None   # the last current's check
    jitter: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])   # samples, mean square (µm², µs²)
    pending: tuple[FastSimulator, FastSimulator, float, float, np.ndarray, AmplifierDrive] | None = None
    # the table's work for the last ok estimate (model, nominal, N_u, L_h µm, covariance, drive), deferred


class DriveCompensator:
    """Per-injector drive corrections from the tracker's results (``update`` once per injection).

    ``nominal``: a simulator of the configured (nominal) parameters, for the default target (else each
    ``update`` passes one). ``standard``: the amplifier's standard drive when the target configures it
    as a current table (the pipeline reads the file); ``trapezoid`` builds the built-in one, ``learned``
    learns each injector's from its first injections.

    ``deferred``: the work an injection's correction does not need at once — the preload table's rows
    and the refresh of the correction's derivatives, nearly all of its simulations — waits for
    :meth:`background` (the daemon runs it when no injection waits), or else runs before the
    injector's next injection: the published table is then the previous estimate's, which
    :meth:`Correction.at` shifts to this correction. Without it, every correction is complete when
    :meth:`update` returns.
    """

    def __init__(self, target: DriveTarget | None = None, nominal: FastSimulator | None = None,
                 refresh: int = REFRESH_INJECTIONS, standard: AmplifierDrive | None = None,
                 deferred: bool = False) -> None:
        self.target = target or DriveTarget()
        self.nominal = nominal
        self.refresh = refresh
        self.deferred = deferred
        if standard is None and self.target.drive_file is not None:
            raise ValueError(f"amplifier_drive = {self.target.amplifier_drive!r}: the current table must be "
                             "read and passed as standard (estimator.pipeline does)")
        if standard is None and self.target.amplifier_drive == "trapezoid":
            standard = AmplifierDrive.trapezoid()
        self.standard = standard
        self.drive_disagreements = 0        # injections whose current the standard drive did not explain
        self._injectors: dict[int, _Injector] = {}
        self._learners: dict[int, DriveLearner] = {}   # kept through a reset: the amplifier is the same
        self._targets: dict[int, tuple[float, float]] = {}
        self._due: dict[int, None] = {}     # injectors with deferred work, oldest first

    def warm_up(self, nominal: FastSimulator) -> None:
        """The target and one correction on a throw-away injector, so the first real one is not slow
        (the daemon calls it before READY)."""
        cov = np.diag([0.01, 0.01])
        st = _Injector()
        drive = self.standard or trapezoid(nominal.dt_s)
        self._correct(st.main, nominal, nominal, NOMINAL_NU_N_PER_V, NOMINAL_LH_UM + 1.0, cov, NOMINAL_PRELOAD_N, drive)
        self._table(st, nominal, nominal, NOMINAL_NU_N_PER_V, NOMINAL_LH_UM + 1.0, cov, drive)

    def forget(self, injector_id: int) -> None:
        """Drop an injector's corrections (a reset: it is driven with the standard drive again); a
        learned standard drive is kept (the amplifier has not changed)."""
        self._injectors.pop(injector_id, None)
        self._due.pop(injector_id, None)

    def learned_drives(self) -> dict[int, AmplifierDrive]:
        """The standard drives learned per injector (none where the drive is configured): what a
        restarted daemon restores, so that its first injections are corrected at once."""
        if self.standard is not None:
            return {}
        return {iid: learner.drive for iid, learner in self._learners.items() if learner.drive is not None}

    def restore_drives(self, drives: dict[int, AmplifierDrive]) -> None:
        """Take ``drives`` as learned (:meth:`learned_drives` of an earlier run); ignored where the drive
        is configured. Each injection's current is still checked against it: an amplifier that changed
        holds the corrections and says so."""
        if self.standard is not None:
            return
        for iid, drive in drives.items():
            self._learners[iid] = DriveLearner.learned(drive, self.target.learn_injections, self.target.drive_tolerance)

    def last(self, injector_id: int) -> Correction:
        """The injector's last correction (the standard drive, ``valid`` False, if none)."""
        st = self._injectors.get(injector_id)
        return st.last if st is not None else Correction()

    def drive_of(self, injector_id: int) -> AmplifierDrive | None:
        """The standard drive the injector's corrections are computed with (None: not learned yet)."""
        if self.standard is not None:
            return self.standard
        learner = self._learners.get(injector_id)
        return learner.drive if learner is not None else None

    def target_at(self, nominal: FastSimulator) -> tuple[float, float]:
        """(stroke µm, opening µs) the target asks for (:func:`~estimator.drive.target.resolve` with
        ``nominal``, a simulator of the configured parameters, and the configured drive, else the
        built-in trapezoid: one target for every injector, whatever each one's learned drive)."""
        nominal = self.nominal or nominal
        got = self._targets.get(id(nominal))
        if got is None:
            got = resolve(nominal, self.target, self.standard or trapezoid(nominal.dt_s))
            self._targets = {id(nominal): got}
        return got

    def check_drive(self, injector_id: int, current_a: np.ndarray, dt_s: float) -> tuple[AmplifierDrive | None, str, float]:
        """The injector's standard drive after this injection's measured current (learning it from
        injections at the standard drive), the reason it cannot serve this injection ("" when it can)
        and the measured scale relative to it."""
        drive = self.drive_of(injector_id)
        if drive is None:
            st = self._injectors.get(injector_id)
            learner = self._learners.setdefault(
                injector_id, DriveLearner(self.target.learn_injections, self.target.drive_tolerance))
            if st is None or not st.last.valid:          # the amplifier drives its standard drive
                learner.add(current_a, dt_s)
            drive = learner.drive
            if drive is None:
                return None, (f"learning the amplifier's standard drive from its measured current "
                              f"({learner.count} of {learner.needed} injections)"), math.nan
        check: DriveCheck = drive.check(current_a, dt_s, self.target.drive_tolerance)
        if not check.agrees:
            self.drive_disagreements += 1
            return drive, (f"the measured current disagrees with the amplifier's standard drive "
                           f"({drive.source}): {100 * check.residual_rel:.0f} % of it unexplained "
                           f"(drive_tolerance {100 * self.target.drive_tolerance:.0f} %)"), check.scale
        return drive, "", check.scale

    def unchecked(self, injector_id: int, sim: FastSimulator | None, current_a: np.ndarray, dt_s: float) -> bool:
        """Whether this injection's measured drive is beyond the scales at which the injector's model
        ``sim`` explained its injections (by more than ``CHECKED_SLACK``): the correction's probe of a
        new level, which the model may fail without the part being mismatched (the estimator then
        rejects the injection, :meth:`update` narrows the trust region toward it). The check of the
        current is kept for :meth:`update` of the same injection."""
        st = self._injectors.get(injector_id)
        checked = _checked(st, sim) if st is not None and sim is not None else None
        if st is None or checked is None:
            return False
        _, reason, measured = self._check(st, injector_id, current_a, dt_s)
        return not reason and not checked[0] - CHECKED_SLACK <= measured <= checked[1] + CHECKED_SLACK

    def _check(self, st: _Injector, injector_id: int, current_a: np.ndarray,
               dt_s: float) -> tuple[AmplifierDrive | None, str, float]:
        """:meth:`check_drive` once per measured current (:meth:`unchecked` and :meth:`update` share it)."""
        if st.measured is not None and st.measured[0] is current_a:
            return st.measured[1]
        got = self.check_drive(injector_id, current_a, dt_s)
        st.measured = (current_a, got)
        return got

    def _measured(self, st: _Injector, injector_id: int, sim: FastSimulator | None, current_a: np.ndarray | None,
                  dt_s: float) -> tuple[AmplifierDrive | None, str, float]:
        """The drive, the reason it cannot serve ("" when it can) and the measured scale of the injection
        (:meth:`check_drive`); without a measured current the configured, learned or built-in drive,
        unchecked (scale NaN)."""
        if current_a is None:
            return self.drive_of(injector_id) or trapezoid(sim.dt_s if sim else SAMPLE_PERIOD_S), "", math.nan
        got = self._check(st, injector_id, current_a, dt_s)
        st.measured = None
        return got

    def update(self, injector_id: int, ok: bool, sim: FastSimulator | None, nu: float, lh_um: float,
               cov: np.ndarray | None, f_open_n: float, nominal: FastSimulator | None = None,
               rate_n_per_v_s: float = 0.0, time_s: float = math.nan, current_a: np.ndarray | None = None,
               dt_s: float = math.nan, this_preload_n: float = math.nan,
               predicted: tuple[float, float] = (math.nan, math.nan), failed_probe: bool = False) -> Correction:
        """The correction after one injection: computed from an ``ok`` estimate (``nu`` N/V, ``lh_um``
        µm, ``cov`` their 2×2 covariance in N/V and µm) with the injector's model ``sim`` at the
        preload force ``f_open_n`` (N; the next injection's if known, else this one's). ``current_a``
        (A, sampled every ``dt_s`` s): the injection's measured current, checked against (or teaching)
        the amplifier's standard drive; without it the drive is taken as configured, learned or the
        built-in trapezoid, unchecked. After an estimate that is not ``ok`` the correction is computed
        again at ``f_open_n`` from the last ``ok`` one, ``held``; a current that disagrees holds the last
        correction as it is. ``nominal``: a simulator of the configured parameters (the default
        target), when the compensator was built without one. The correction is for the next injection:
        N_u moves on by the filter's drift rate ``rate_n_per_v_s`` over the last interval between this
        injector's injections (``time_s``, s; a warm-up would otherwise leave it behind). ``predicted``:
        the estimator's own prediction of this injection's (stroke µm, opening µs after its start of
        charging) from its measured current, at its preload force ``this_preload_n`` (N): compared with
        what the last correction predicted for it, the injection-to-injection jitter a correction
        cannot foresee (the amplifier's ripple, the estimate's noise) enters its σ. ``failed_probe``: the
        estimator rejected this injection because the model failed at its drive, beyond the checked
        scales (:meth:`unchecked`): the trust region on that side halves toward it, and the correction
        held from the last ``ok`` estimate stays inside."""
        st = self._injectors.get(injector_id)
        if st is None:
            st = self._injectors[injector_id] = _Injector()
        if injector_id in self._due:   # the last injection's deferred work, not done while the worker was busy
            self._catch_up(injector_id)
        interval = time_s - st.time_s if math.isfinite(time_s) and math.isfinite(st.time_s) else 0.0
        st.time_s = time_s
        if math.isfinite(rate_n_per_v_s) and 0.0 < interval < MAX_INTERVAL_S:
            nu = _carried_within(sim, nu, rate_n_per_v_s * interval)
        nominal = self.nominal or nominal
        drive, reason, measured = self._measured(st, injector_id, sim, current_a, dt_s)
        if current_a is not None and not reason:
            _jitter(st, this_preload_n, measured, predicted)
            if failed_probe:
                _narrow(st, sim, measured)
        if drive is None or reason:
            st.last = replace(st.last, held=st.last.valid, reason=reason, drive_scale=measured)
            return st.last
        usable = (ok and sim is not None and nominal is not None and cov is not None and math.isfinite(nu)
                  and math.isfinite(lh_um) and math.isfinite(f_open_n))
        table = st.last.table
        try:
            if usable:
                assert sim is not None and cov is not None and nominal is not None
                cov = np.asarray(cov, dtype=float)
                if st.ok is not None and st.ok.sim is not sim:   # another model: its jitter is measured anew
                    st.jitter = [0.0, 0.0, 0.0]
                _check_level(st, sim, measured)
                if self.deferred:
                    st.pending, fresh = (sim, nominal, nu, lh_um, cov, drive), st.last.table
                else:
                    fresh = self._table(st, sim, nominal, nu, lh_um, cov, drive)
                st.last = self._correct(st.main, sim, nominal, nu, lh_um, cov, f_open_n, drive,
                                        jitter=_jitter_var(st), checked=_checked(st, sim), steps=st.steps,
                                        drive_scale=measured,
                                        table=fresh, defer=self.deferred)
                if st.pending is not None or st.main.due:
                    self._due[injector_id] = None
                st.ok = _OkEstimate(sim, nu, lh_um, cov, rate_n_per_v_s if math.isfinite(rate_n_per_v_s) else 0.0,
                                    time_s)
                return st.last
            elif st.ok is not None and nominal is not None and math.isfinite(f_open_n):
                corr = replace(self._again(st, nominal, f_open_n, time_s, drive), held=True,
                               reason="estimate not ok: computed again from the last ok estimate")
                if st.main.due:
                    self._due[injector_id] = None
            else:
                corr = replace(st.last, held=st.last.valid, reason="no ok estimate yet" if not st.last.valid
                               else "estimate not ok")
        except (EstimatorError, ValueError, FloatingPointError) as exc:   # e.g. N_u outside the simulator's range
            corr = replace(st.last, held=st.last.valid, reason=f"no correction: {exc}")
        st.last = replace(corr, drive_scale=measured, table=table)
        return st.last

    def background(self, injectors: int = 1) -> int:
        """The deferred work of up to ``injectors`` injectors, the oldest first (the daemon calls it when
        no injection waits); the number served."""
        done = 0
        while self._due and done < injectors:
            self._catch_up(next(iter(self._due)))
            done += 1
        return done

    @property
    def has_background(self) -> bool:
        """Whether deferred work waits for :meth:`background`."""
        return bool(self._due)

    def _catch_up(self, injector_id: int) -> None:
        """The injector's deferred work: its preload table for its last ``ok`` estimate (the last
        correction takes it) and its derivatives due by age, taken again at its last simulation."""
        st = self._injectors.get(injector_id)
        try:
            if st is None:
                return
            pending, st.pending = st.pending, None
            pt = st.main
            try:
                if pending is not None:
                    table = self._table(st, *pending)
                    if table is not st.last.table:
                        st.last = replace(st.last, table=table)
                if pt.due and pt.model is not None and pt.drive is not None and pt.anchor is not None:
                    a = pt.anchor
                    pt.linearise(pt.model, a[0], a[1], a[2], a[3], pt.drive)
            except (EstimatorError, ValueError, FloatingPointError):
                pass   # the last table and derivatives serve on (the next correction says what fails)
            pt.due = False
        finally:   # done (or failed) only now: whoever watches has_background sees the work finished
            self._due.pop(injector_id, None)

    def _again(self, st: _Injector, nominal: FastSimulator, f_open_n: float, time_s: float,
               drive: AmplifierDrive) -> Correction:
        """The last ``ok`` estimate's correction at the preload force ``f_open_n`` (N), N_u carried on by
        its drift rate to ``time_s``, uncertain by ``CARRY_NU_SHARE`` of the carry (a warm-up's rate
        falls as it goes on: twelve held injections of a warming part put its stroke 0.44 µm off while
        its σ, the last estimate's, said 0.1 µm)."""
        ok = st.ok
        assert ok is not None
        dt = time_s - ok.time_s if math.isfinite(time_s) and math.isfinite(ok.time_s) else 0.0
        carried = ok.rate_n_per_v_s * dt if 0.0 < dt < MAX_INTERVAL_S else 0.0
        cov = ok.cov + np.diag([(CARRY_NU_SHARE * carried) ** 2, 0.0])
        return self._correct(st.main, ok.sim, nominal, _carried_within(ok.sim, ok.nu, carried), ok.lh_um, cov, f_open_n, drive,
                             jitter=_jitter_var(st), checked=_checked(st, ok.sim), steps=st.steps,
                             defer=self.deferred)

    def _correct(self, pt: _Point, sim: FastSimulator, nominal: FastSimulator, nu: float, lh_um: float,
                 cov: np.ndarray, f_open_n: float, drive: AmplifierDrive, derivatives: bool = True,
                 jitter: tuple[float, float] = (0.0, 0.0), refresh: int | None = None,
                 carry: bool = True, checked: tuple[float, float] | None = None,
                 steps: Sequence[float] = (TRUST_STEP, TRUST_STEP), drive_scale: float = math.nan,
                 table: Table = (), defer: bool = False) -> Correction:
        """The correction at ``f_open_n`` by Newton's method on the scale from ``pt``'s last one
        (``derivatives``: the per-kN sensitivities and the σ too, ``jitter`` the injection-to-injection
        variance of stroke and opening, µm² and µs², in it; ``refresh``: how many corrections the
        derivatives serve, default the compensator's). Where the estimate and the preload force moved
        so little since ``pt``'s last correction that its derivatives hold (:func:`_carry`), that
        correction is carried instead of simulated (``carry`` False: always simulated). ``checked``: the
        scales the model was checked at (None: unknown, the configured limits alone); the scale stays
        within ``steps`` (below, above; at most ``TRUST_STEP``) of them (:func:`_trust`). ``drive_scale``
        and ``table`` are passed on to the correction as they are. ``defer``: derivatives merely due by age are refreshed later
        (:meth:`background`), the old ones serving until then."""
        t = self.target
        lo, hi = _trust(t.scale_limits, checked, steps)
        target_stroke, target_opening = self.target_at(nominal)
        scale = min(max(pt.last.scale if pt.last is not None and pt.last.valid else 1.0, lo), hi)   # scalars: no numpy
        same = pt.response is not None and pt.model is sim and pt.drive is drive
        due = not same or pt.age >= (refresh or self.refresh)
        if due and same and defer:   # only by age: the old derivatives serve until the background refresh
            pt.due, due = True, False
        if due:
            if pt.model is not sim or pt.drive is not drive:   # derivatives at the drive the target asks for,
                # not at the last one's: taken at scale 1.0 for rows that settled at 0.75–0.9, a row's
                # carried opening instant missed by a third of its move, another's was six times its move
                scale = _aimed(sim, scale, nu, lh_um, f_open_n, drive, target_stroke, lo, hi,
                               pt.response.d_scale[0] if pt.response is not None else STROKE_PER_SCALE_UM)
            fresh = pt.linearise(sim, scale, nu, lh_um, f_open_n, drive)
            stroke, opening = fresh.stroke_um, fresh.opening_us
        else:
            carried = _carry(pt, scale, nu, lh_um, f_open_n) if carry else None
            if carried is not None:
                stroke, opening = carried
            else:
                stroke, opening = _simulated(pt, sim, scale, nu, lh_um, f_open_n, drive)
        pt.age += 1
        r = pt.response
        assert r is not None
        if not (math.isfinite(stroke) and math.isfinite(opening)) or r.d_scale[0] <= 0:
            # the valve does not open with this drive: the most current the limits allow, then again
            scale = hi
            r = pt.linearise(sim, scale, nu, lh_um, f_open_n, drive, age=1)
            stroke, opening = r.stroke_um, r.opening_us
            if not (math.isfinite(stroke) and math.isfinite(opening)) or r.d_scale[0] <= 0:
                raise ValueError("the valve does not open within the scale limits")
        for _ in range(3):   # Newton on the scale: the stroke is close to linear in it
            new = min(max(scale + (target_stroke - stroke) / r.d_scale[0], lo), hi)
            if abs(new - scale) < 1e-5:
                break
            step = new - scale
            scale = new
            if abs(step) * r.d_scale[0] < LINEAR_STROKE_UM and abs(step * r.d_scale[1]) < LINEAR_OPENING_US:
                # small: the linear model is exact enough, no simulation (a forward difference across a
                # bend of the opening instant is not: then the step is simulated)
                stroke, opening = stroke + r.d_scale[0] * step, opening + r.d_scale[1] * step
                break
            stroke, opening = _simulated(pt, sim, scale, nu, lh_um, f_open_n, drive)
            if not (math.isfinite(stroke) and math.isfinite(opening)):
                raise ValueError("the valve does not open within the scale limits")
        short = scale in (lo, hi) and abs(stroke - target_stroke) > 0.01
        at_limit = short and scale in t.scale_limits
        trust_limited = short and not at_limit
        olo, ohi = t.offset_limits_us
        offset = min(max(target_opening - opening, olo), ohi)
        at_limit = at_limit or offset in (olo, ohi)
        sigma_s, sigma_o, per_kn = math.nan, math.nan, (0.0, 0.0)
        if derivatives:
            idle = _toward_idle(sim, scale, nu, lh_um, f_open_n, drive, stroke, opening)
            sigma_s, sigma_o, per_kn = _uncertainty(r, sim, cov, scale, stroke, jitter, checked, idle)
        corr = Correction.of(scale=scale, offset_us=offset, stroke_um=stroke, opening_us=offset + opening, valid=True,
                             sigma_stroke_um=sigma_s, sigma_opening_us=sigma_o, target_stroke_um=target_stroke,
                             target_opening_us=target_opening, scale_per_kn=per_kn[0], offset_per_kn_us=per_kn[1],
                             preload_n=f_open_n, at_limit=at_limit, scale_limits=t.scale_limits, table=table,
                             offset_limits_us=t.offset_limits_us, drive_scale=drive_scale, checked=checked,
                             trust_limited=trust_limited)
        pt.last = corr
        return corr

    def _table(self, st: _Injector, sim: FastSimulator, nominal: FastSimulator, nu: float, lh_um: float,
               cov: np.ndarray, drive: AmplifierDrive) -> Table:
        """The preload table (preload N, scale, offset µs, σ of stroke µm and opening µs) for the estimate
        (``nu``, ``lh_um``), each row's σ as its last computation stated it (a correction's at that
        preload force, :func:`_uncertainty`; σ moves slowly, the carry is arithmetic): each
        row computed again in turn, one every ``ROW_PERIOD`` injections (``ROWS_AFTER_CHANGE`` an
        injection when the model or the drive changed), the others carried to the estimate by their own
        derivatives in N_u and L_h (arithmetic: the stroke is close to linear in both); the
        ``FAR_ROWS`` rows they would move the opening instant most, beyond ``CARRY_OPENING_US``, are
        simulated at once, with derivatives taken afresh where the simulation lands more than
        ``DERIVATIVE_MISS_US`` from the carry. Until every row has been computed with this
        model and drive, the last complete table (another model's: :meth:`Correction.at` shifts it to
        this correction), empty before the first."""
        preloads = self.target.table_preloads_n
        if len(st.rows) != len(preloads):
            st.rows, st.next_row = [_Point() for _ in preloads], 0
            st.grid = np.full((len(preloads), row_carry.COLUMNS), np.nan)
        stale = [i for i, pt in enumerate(st.rows) if pt.model is not sim or pt.drive is not drive]
        todo = stale[:ROWS_AFTER_CHANGE] if stale else []
        st.turn += 1
        if not stale and st.turn % ROW_PERIOD == 0:
            todo.append(st.next_row)
            st.next_row = (st.next_row + 1) % len(preloads)
        for i in todo:
            self._row(st, i, sim, nominal, nu, lh_um, cov, drive)
        if len(stale) > ROWS_AFTER_CHANGE:
            return st.last.table   # the last complete table (another model's) until every row is this one's
        target = self.target_at(nominal)
        limits = (*_trust(self.target.scale_limits, _checked(st, sim), st.steps), *self.target.offset_limits_us)
        scale, moved, offset, farthest = row_carry.carry_rows(st.grid, nu, lh_um, *target, limits)
        far = [] if not farthest > CARRY_OPENING_US else [
            i for i in np.argsort(-np.abs(moved))[:FAR_ROWS] if abs(moved[i]) > CARRY_OPENING_US]
        for i in far:   # beyond what the derivatives hold: simulated now; where the simulation shows that
            # they did not hold (a forward difference across a bend of the opening instant is no
            # derivative at all), simulated again with derivatives taken afresh
            foreseen = st.grid[i, row_carry.OPENING] + moved[i]
            self._row(st, i, sim, nominal, nu, lh_um, cov, drive)
            if not abs(st.grid[i, row_carry.OPENING] - foreseen) <= DERIVATIVE_MISS_US:
                st.rows[i].age = ROW_REFRESH
                self._row(st, i, sim, nominal, nu, lh_um, cov, drive)
        if far:
            scale, moved, offset, _ = row_carry.carry_rows(st.grid, nu, lh_um, *target, limits)
        sigma_s, sigma_o = st.grid[:, row_carry.SIGMA_STROKE], st.grid[:, row_carry.SIGMA_OPENING]
        return tuple(zip(preloads, scale.tolist(), offset.tolist(), sigma_s.tolist(), sigma_o.tolist()))

    def _row(self, st: _Injector, i: int, sim: FastSimulator, nominal: FastSimulator, nu: float, lh_um: float,
             cov: np.ndarray, drive: AmplifierDrive) -> None:
        """Row ``i`` of the preload table simulated for the estimate (``nu``, ``lh_um``), and its line of
        the injector's grid."""
        pt = st.rows[i]
        c = self._correct(pt, sim, nominal, nu, lh_um, cov, self.target.table_preloads_n[i], drive,
                          carry=False, refresh=ROW_REFRESH, checked=_checked(st, sim), steps=st.steps,
                          jitter=_jitter_var(st))
        r = pt.response
        assert r is not None
        st.grid[i] = (c.stroke_um, c.scale, c.opening_us - c.offset_us, nu, lh_um, r.d_nu[0], r.d_lh[0],
                      r.d_scale[0], r.d_nu[1], r.d_lh[1], r.d_scale[1], c.sigma_stroke_um, c.sigma_opening_us)


def _carry(pt: _Point, scale: float, nu: float, lh_um: float, f_open_n: float) -> tuple[float, float] | None:
    """(stroke µm, opening µs) at ``scale`` for the estimate (``nu``, ``lh_um``) at ``f_open_n`` (N),
    carried by ``pt``'s derivatives from its last simulation, when that moves the stroke and the
    opening instant less than ``CARRY_STROKE_UM``/``CARRY_MAIN_OPENING_US``, and the preload force's
    share of the move less than ``CARRY_PRELOAD_STROKE_UM``/``CARRY_PRELOAD_OPENING_US`` (the carry's
    error is of the second order, and does not build up: every carry starts from a simulation); else
    None (simulate). A steady engine's injections, the estimate's noise and drift with them, are
    carried; a rail pressure that moves is simulated."""
    a, r = pt.anchor, pt.response
    if a is None or r is None:
        return None
    ds, dnu, dlh, df = scale - a[0], nu - a[1], lh_um - a[2], f_open_n - a[3]
    f_stroke, f_opening = r.d_f[0] * df, r.d_f[1] * df
    if not (abs(f_stroke) < CARRY_PRELOAD_STROKE_UM and abs(f_opening) < CARRY_PRELOAD_OPENING_US):
        return None
    d_stroke = r.d_scale[0] * ds + r.d_nu[0] * dnu + r.d_lh[0] * dlh + f_stroke
    d_opening = r.d_scale[1] * ds + r.d_nu[1] * dnu + r.d_lh[1] * dlh + f_opening
    if not (abs(d_stroke) < CARRY_STROKE_UM and abs(d_opening) < CARRY_MAIN_OPENING_US):
        return None
    return a[4] + d_stroke, a[5] + d_opening


def _uncertainty(r: Response, sim: FastSimulator, cov: np.ndarray, scale: float, stroke: float,
                 jitter: tuple[float, float], checked: tuple[float, float] | None,
                 idle: tuple[float, float] = (0.0, 0.0)) -> tuple[float, float, tuple[float, float]]:
    """σ of the stroke (µm) and the opening instant (µs) a correction at ``scale`` gives (the estimate's
    covariance ``cov`` through the derivatives ``r``, what the model ``sim``'s own calibration leaves in
    the motion, the injection-to-injection ``jitter`` variances, the extrapolation beyond the
    ``checked`` scales, and ``PRELOAD_REL`` of ``idle``, the motion the model extrapolates toward idle
    below the preload forces it was calibrated over: :func:`_toward_idle`), and the per-kN
    sensitivities of scale and offset that keep stroke and opening on target at another preload force
    (to first order)."""
    ds_df = -r.d_f[0] / r.d_scale[0]
    per_kn = (ds_df * N_PER_KN, -(r.d_f[1] + r.d_scale[1] * ds_df) * N_PER_KN)
    cal = sim.params.calibration   # what the model's own uncertainty leaves in the motion (0: in cov)
    beyond = 0.0 if checked is None else max(scale - checked[1], checked[0] - scale, 0.0)
    var_s = (_quadratic(r.d_nu[0], r.d_lh[0], cov) + (cal.stroke_rel_sigma * stroke) ** 2 + jitter[0]
             + (TRUST_REL * r.d_scale[0] * beyond) ** 2 + (PRELOAD_REL * idle[0]) ** 2)
    var_o = (_quadratic(r.d_nu[1], r.d_lh[1], cov) + (cal.opening_sigma_s * US_PER_S) ** 2 + jitter[1]
             + (TRUST_REL * r.d_scale[1] * beyond) ** 2 + (PRELOAD_REL * idle[1]) ** 2)
    return math.sqrt(max(var_s, 0.0)), math.sqrt(max(var_o, 0.0)), per_kn


def _toward_idle(sim: FastSimulator, scale: float, nu: float, lh_um: float, f_open_n: float,
                 drive: AmplifierDrive, stroke: float, opening: float) -> tuple[float, float]:
    """How far (µm, µs) the model ``sim`` moves the stroke and the opening instant at ``scale`` from the
    lowest preload force it was calibrated over down to ``f_open_n`` (N): (0, 0) at or above it, and for
    a model that does not state its preload forces. One simulation, only below that force."""
    lo = sim.params.calibration.preload_lo_n
    if sim.params.calibration.preload_hi_n <= 0.0 or f_open_n >= lo:
        return 0.0, 0.0
    s_lo, o_lo = respond(sim, scale, nu, lh_um, lo, drive)
    if not (math.isfinite(s_lo) and math.isfinite(o_lo)):
        return 0.0, 0.0
    return stroke - s_lo, opening - o_lo


def _aimed(sim: FastSimulator, scale: float, nu: float, lh_um: float, f_open_n: float, drive: AmplifierDrive,
           target_stroke: float, lo: float, hi: float, per_scale_um: float) -> float:
    """The scale one Newton step from ``scale`` toward ``target_stroke`` (µm) within (``lo``, ``hi``),
    the stroke simulated at ``scale`` and assumed to grow by ``per_scale_um`` per unit of scale; ``scale``
    itself where the valve does not open there."""
    stroke, _ = respond(sim, scale, nu, lh_um, f_open_n, drive)
    if not (math.isfinite(stroke) and per_scale_um > 0):
        return scale
    return min(max(scale + (target_stroke - stroke) / per_scale_um, lo), hi)


def _simulated(pt: _Point, sim: FastSimulator, scale: float, nu: float, lh_um: float, f_open_n: float,
               drive: AmplifierDrive) -> tuple[float, float]:
    """:func:`respond`, kept as ``pt``'s anchor: the point later corrections are carried from."""
    stroke, opening = respond(sim, scale, nu, lh_um, f_open_n, drive)
    pt.anchor = (scale, nu, lh_um, f_open_n, stroke, opening)
    return stroke, opening


def _carried_within(sim: FastSimulator | None, nu: float, carry: float) -> float:
    """N_u (N/V) carried on by ``carry`` (N/V, a drift rate times the time since), within the N_u range
    ``sim`` simulates. A warm-up's rate carried over many held injections overshoots the part (a part
    near the top of the range was carried to 21.2 N/V: no correction could be computed, and the last one,
    beyond its trust region since a failed probe, was repeated for 60 injections)."""
    carried = nu + carry
    if sim is None or not math.isfinite(carried):
        return carried
    lo, hi = sim.nu_range
    return min(max(carried, lo), hi)


def _checked(st: _Injector, sim: FastSimulator) -> tuple[float, float] | None:
    """The scales at which ``sim`` explained the injector's injections (None: none known for it)."""
    return st.checked if st.checked_model is sim else None


def _check_level(st: _Injector, sim: FastSimulator, measured_scale: float) -> None:
    """An ``ok`` estimate with the model ``sim`` at the measured drive scale: the model is checked there
    (the interval of such scales starts again with another model; an unmeasured scale adds nothing)."""
    if not math.isfinite(measured_scale):
        return
    if st.checked_model is not sim or st.checked is None:
        st.checked, st.checked_model, st.steps = (measured_scale, measured_scale), sim, [TRUST_STEP, TRUST_STEP]
        return
    lo, hi = st.checked
    if measured_scale < lo - CHECKED_SLACK:   # a new level passed: the trust region on its side grows back
        st.steps[0] = min(2.0 * st.steps[0], TRUST_STEP)
    if measured_scale > hi + CHECKED_SLACK:
        st.steps[1] = min(2.0 * st.steps[1], TRUST_STEP)
    st.checked = (min(lo, measured_scale), max(hi, measured_scale))


def _narrow(st: _Injector, sim: FastSimulator | None, measured_scale: float) -> None:
    """The model failed at ``measured_scale``, beyond its checked scales: the trust region on that side
    ends halfway to it (a trust-region method's step after a failed one), or at the checked scales
    themselves once that is within ``CHECKED_SLACK`` of them: a level so close counts as checked, and a
    failure there would be taken for a changed part (the model is refined over the failed levels,
    :mod:`estimator.ident.learning.learning`, and a new model starts a new trust region)."""
    checked = _checked(st, sim) if sim is not None else None
    if checked is None or not math.isfinite(measured_scale):
        return
    side = 1 if measured_scale > checked[1] else 0 if measured_scale < checked[0] else -1
    if side < 0:
        return
    step = min(st.steps[side], 0.5 * abs(measured_scale - checked[side]))
    st.steps[side] = step if step >= CHECKED_SLACK else 0.0


def _trust(limits: tuple[float, float], checked: tuple[float, float] | None,
           steps: Sequence[float] = (TRUST_STEP, TRUST_STEP)) -> tuple[float, float]:
    """The scale limits within ``steps`` (below, above) of the checked scales (the configured ``limits``
    where nothing was checked)."""
    lo, hi = limits
    if checked is None:
        return lo, hi
    lo, hi = max(lo, checked[0] - steps[0]), min(hi, checked[1] + steps[1])
    return (lo, hi) if lo <= hi else (min(max(checked[0], limits[0]), limits[1]),) * 2


def _quadratic(a: float, b: float, cov: np.ndarray) -> float:
    """(a, b) cov (a, b)ᵀ of a 2×2 covariance, in scalars (every correction)."""
    return float(a * a * cov[0, 0] + 2.0 * a * b * cov[0, 1] + b * b * cov[1, 1])


def _jitter(st: _Injector, preload_n: float, measured_scale: float, predicted: tuple[float, float]) -> None:
    """Compare the estimator's own prediction of this injection (``predicted``: stroke µm, opening µs
    after its start of charging) with what the last correction predicted for it, when that correction
    was computed for this preload force (N) and the measured current shows the amplifier applied it."""
    last = st.last
    if not (last.valid and not last.held and math.isfinite(preload_n) and abs(last.preload_n - preload_n) < 0.5
            and math.isfinite(measured_scale) and abs(measured_scale - last.scale) < 0.02 * last.scale):
        return
    ds, do = predicted[0] - last.stroke_um, predicted[1] - (last.opening_us - last.offset_us)
    if not (math.isfinite(ds) and math.isfinite(do)):
        return
    n, ms_s, ms_o = st.jitter
    if n >= JITTER_MIN:   # one odd injection (a part swapped, an outlier) moves the mean square by a bounded step
        ds = min(abs(ds), JITTER_CLIP * math.sqrt(ms_s) + JITTER_FLOOR[0])
        do = min(abs(do), JITTER_CLIP * math.sqrt(ms_o) + JITTER_FLOOR[1])
    w = max(JITTER_WEIGHT, 1.0 / (n + 1))
    st.jitter = [n + 1, (1 - w) * ms_s + w * ds * ds, (1 - w) * ms_o + w * do * do]


def _jitter_var(st: _Injector) -> tuple[float, float]:
    """The injection-to-injection variance (µm², µs²) once enough injections were compared."""
    n, ms_s, ms_o = st.jitter
    return (ms_s, ms_o) if n >= JITTER_MIN else (0.0, 0.0)


def estimate_unchecked(compensator: DriveCompensator, tracker: Tracker, inj: Injection) -> TrackResult:
    """``tracker.update(inj)``, told whether the injection's measured drive lies beyond the levels the
    injector's model was checked at (:meth:`DriveCompensator.unchecked`): the estimate that goes with
    :func:`correction_after` in a closed loop."""
    sim = tracker.model_simulator(inj.injector_id, inj.dt_s)
    return tracker.update(inj, compensator.unchecked(inj.injector_id, sim, inj.current_a, inj.dt_s))


def correction_after(compensator: DriveCompensator, tracker: Tracker, inj: Injection, res: TrackResult,
                     preload_n: float | None = None) -> Correction:
    """The injector's drive correction after the tracker's result ``res`` for ``inj``: from an ``ok``
    estimate with the model the injector is estimated with, at ``preload_n`` (N; default this
    injection's preload force), its covariance the published σ (which may cover a bias) with the
    filter's correlation; the injection's measured current checked against the amplifier's standard
    drive; otherwise the last one, held. Where the injector's calibrated model states
    the uncertainty it leaves in the valve's motion and that model is validated (:func:`_validated`),
    that replaces the share of N_u's and L_h's covariance the calibration put there (the motion keeps
    less of a structural error than they do)."""
    iid = inj.injector_id
    st = tracker.states.get(iid)
    ok = res.status == Status.OK
    sim = tracker.model_simulator(iid, inj.dt_s)
    cov = None
    if st is not None and ok:   # in scalars: every injection
        p00, p01, p11 = float(st.p[0][0]), float(st.p[0][1]), float(st.p[1][1])
        v_nu, v_lh = res.sigma_nu ** 2, (res.sigma_lh_m * UM_PER_M) ** 2
        cal = sim.params.calibration if sim is not None else None
        if cal is not None and cal.has_response and _validated(tracker, iid):
            own = cal.cov(res.nu_n_per_v)
            v_nu, v_lh = max(v_nu - float(own[0, 0]), p00), max(v_lh - float(own[1, 1]), p11)
        rho = p01 / math.sqrt(p00 * p11) if p00 > 0 and p11 > 0 else 0.0
        c = rho * math.sqrt(v_nu * v_lh)
        cov = np.array(((v_nu, c), (c, v_lh)))
    return compensator.update(iid, ok, sim, res.nu_n_per_v, res.lh_m * UM_PER_M,
                              cov, inj.f_open_n if preload_n is None else preload_n,
                              tracker.nominal_simulator(inj.dt_s), res.rate_n_per_v_s, inj.time_s,
                              inj.current_a, inj.dt_s, inj.f_open_n,
                              (res.stroke_m * UM_PER_M, res.t_open_s * US_PER_S) if ok else (math.nan, math.nan),
                              res.failed_probe)


def _validated(tracker: Tracker, injector_id: int) -> bool:
    """Whether the injector's model may be trusted with its own statement of the motion's uncertainty:
    a model learned from a first window of twelve injections only once its refinement over a larger
    window agreed with it or replaced it (that window left one part of 24 with N_u four of its stated
    σ off); a parameter file's model, or one used without learning, as it is."""
    status = tracker.calibration.get(injector_id)
    return status is None or status.source != "learned" or status.refined

