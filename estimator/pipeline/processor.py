"""Events -> recursive estimator -> output frames. No threads, no bus, no clocks of its own.

Used unchanged by the live daemon and by the offline replay, so both publish the same estimates
for the same frames.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

from estimator.codec.assembler import Completed, Rejected, RejectReason
from estimator.codec.frame import Frame
from estimator.codec.ingest import Counters, Event, Malformed
from estimator.codec.records import (
    HEARTBEAT_COUNTERS,
    Codec,
    Command,
    DriveCorrection,
    DriveCorrectionRow,
    EstimateQuality,
    EstimateState,
    EstimatorCommand,
    EstimatorHealth,
    EstimatorStatus,
    ModelCalibration,
    ValvePrediction,
)
from estimator.drive.correction import (
    CORRECTION_STATES,
    Correction,
    DriveCompensator,
    correction_after,
    estimate_unchecked,
)
from estimator.errors import ParameterError
from estimator.ident.learning.selfcal import CalibrationStatus
from estimator.ident.measurement import Injection
from estimator.ident.status import Learning, Status
from estimator.ident.tracking.tracker import Tracker, TrackResult
from estimator.pipeline.ratelimit import RateLimitedLog
from estimator.units import PER_MICRO, UM_PER_M, US_PER_S

log = logging.getLogger(__name__)
COMMAND_POLICIES = ("off", "reset-only", "all")   # who may steer the estimator over the bus (config key commands)
TABLE_ROWS_PER_INJECTION = 2   # DriveCorrectionTable rows sent with each injection's correction, in turn


ROW_FIELDS = ("time_s", "injector_id", "counter", "status", "nu_n_per_v", "lh_um", "sigma_nu_n_per_v", "sigma_lh_um",
              "raw_nu_n_per_v", "raw_lh_um", "t_contact_us", "t_open_us", "stroke_um", "evaluations", "reason",
              "learning", "out_of_tolerance", "drive_scale", "drive_offset_us", "drive_state")


def result_row(res: TrackResult, injector_id: int, counter: int, time_s: float,
               learning: CalibrationStatus | None = None, correction: Correction | None = None) -> dict[str, Any]:
    """One injection as a flat row (``ROW_FIELDS``): filtered and raw estimate, prediction, status, the
    injector's learning state and the parameters its last calibration found out of tolerance
    (``;``-separated), the drive correction (scale, offset µs, ``valid``/``held``/``none``); units in
    the names; None where there is no value."""
    f = res.filtered_dict()
    raw = res.raw.to_dict()
    row = {"time_s": round(time_s, 6) if math.isfinite(time_s) else None, "injector_id": injector_id,
           "counter": counter, "status": res.status.value, "raw_nu_n_per_v": raw.get("nu_n_per_v"),
           "raw_lh_um": raw.get("lh_um"), "evaluations": res.evaluations, "reason": res.reason}
    for k in ("nu_n_per_v", "lh_um", "sigma_nu_n_per_v", "sigma_lh_um", "t_contact_us", "t_open_us", "stroke_um"):
        row[k] = f.get(k)
    row["learning"] = str(learning.state) if learning is not None else None
    row["out_of_tolerance"] = ";".join(learning.out_of_tolerance) if learning is not None else None
    valid = correction if correction is not None and correction.valid else None
    row["drive_scale"] = round(valid.scale, 5) if valid is not None else None
    row["drive_offset_us"] = round(valid.offset_us, 3) if valid is not None else None
    row["drive_state"] = correction.state if correction is not None else None
    return row


#: EstimatorHealth's rolling counters (the rest are gauges)
HEALTH_COUNTERS = ("commands_applied", "stale", "injections_shed", "simulators_built", "simulators_evicted",
                   "builds_refused", "worker_errors", "xcp_writes")


def _wrap_masks(codec: Codec, record: type[EstimatorStatus] | type[EstimatorHealth],
                names: tuple[str, ...]) -> dict[str, int]:
    """Each rolling counter's mask: it wraps at its signal's width in the DBC."""
    msg = codec.messages[record]
    return {name: (1 << msg.get_signal_by_name(record.SIGNALS[name]).length) - 1 for name in names}


def correction_frame(codec: Codec, injector_id: int, counter: int, c: Correction) -> Frame:
    """The DriveCorrection frame of one injector's correction (NaN has no wire form: 0 with State none)."""
    def v(x: float) -> float:
        return x if math.isfinite(x) else 0.0
    return codec.encode(DriveCorrection(injector_id, counter, c.scale, c.offset_us, v(c.stroke_um), v(c.sigma_stroke_um),
                                        v(c.opening_us), v(c.sigma_opening_us), c.scale_per_kn, c.offset_per_kn_us,
                                        v(c.preload_n), CORRECTION_STATES.index(c.state),
                                        int(c.at_limit), int(c.trust_limited)))


def table_frames(codec: Codec, injector_id: int, counter: int, c: Correction, rows: Sequence[int]) -> list[Frame]:
    """The DriveCorrectionTable frames of the correction's table rows ``rows`` (none without a table)."""
    table = c.table if c.valid else ()
    return [codec.encode(DriveCorrectionRow(injector_id, counter, i, len(table), *table[i])) for i in rows
            if i < len(table)]


def output_frames(codec: Codec, injector_id: int, counter: int, res: TrackResult) -> list[Frame]:
    """EstimateState, EstimateQuality and ValvePrediction of one result (the frames the daemon sends)."""
    have = math.isfinite(res.nu_n_per_v) and math.isfinite(res.lh_m)
    status = codec.status_code(res.status if have else Status.NO_ESTIMATE)
    enc = codec.encode
    return [
        enc(EstimateState(injector_id, counter, res.nu_n_per_v, res.lh_m * UM_PER_M, status)),
        enc(EstimateQuality(injector_id, counter, res.raw.cost_vs * PER_MICRO, res.sigma_nu, res.sigma_lh_m * UM_PER_M,
                            res.evaluations, int(res.raw.robust))),
        enc(ValvePrediction(injector_id, counter, res.t_contact_s * US_PER_S, res.t_open_s * US_PER_S, res.stroke_m * UM_PER_M)),
    ]


def calibration_frame(codec: Codec, injector_id: int, status: CalibrationStatus) -> Frame:
    """The ModelCalibration frame of one injector's self-calibration status."""
    return codec.encode(ModelCalibration(injector_id, codec.calibration_code(status.state), status.batch, status.rms_before_v,
                                         status.rms_after_v, status.calibrations & 0xFF, status.preload_span,
                                         len(status.out_of_tolerance)))


@dataclass(frozen=True)
class Published:
    """One published estimate: the injection's identification, the tracker's result, the injector's
    learning and drive correction. The one record every output renders: the JSON lines
    (:meth:`to_dict`: ``replay --json``, ``track``), the table rows (:meth:`to_row`: ``replay --csv``,
    the fleet, :func:`~estimator.pipeline.estimates.iter_estimates`) and the CAN frames
    (:attr:`frames`: the daemon, ``replay --out``; needs the ``codec``)."""

    injector_id: int
    counter: int
    t_last: float
    result: TrackResult
    codec: Codec | None = field(default=None, repr=False, compare=False)
    calibrations: tuple[tuple[int, CalibrationStatus], ...] = ()   # self-calibration changes (injector, status)
    learning: CalibrationStatus | None = None   # where this injector's learning stands (None: learning off)
    correction: Correction | None = None   # the injector's drive correction (None: drive correction off)
    table_rows: tuple[int, ...] = ()       # the rows of its table sent with it (DriveCorrectionTable)

    @cached_property
    def frames(self) -> list[Frame]:
        """The output frames (:func:`output_frames`), encoded when first asked for: the daemon and a
        replay with an output log send them; rows (``replay --csv``, the fleet) do not need them
        (≈ 0.2 ms an injection)."""
        codec = self.codec
        if codec is None:
            raise ValueError("a published estimate without a codec has no frames")
        out = output_frames(codec, self.injector_id, self.counter, self.result)
        if self.correction is not None:
            out.append(correction_frame(codec, self.injector_id, self.counter, self.correction))
            out.extend(table_frames(codec, self.injector_id, self.counter, self.correction, self.table_rows))
        return out + [calibration_frame(codec, i, st) for i, st in self.calibrations]

    def stale(self, age_s: float) -> Published:
        """This injection published as ``stale`` (it is ``age_s`` s after its last frame: the estimator is
        behind); the estimate is the same, only its status and reason say it is late."""
        reason = f"published {age_s * 1e3:.0f} ms after the injection's last frame (estimator behind)"
        return replace(self, result=replace(self.result, status=Status.STALE, reason=reason))

    def to_row(self, time_s: float) -> dict[str, Any]:
        """One table row (replay ``--csv``, fleet): see :func:`result_row`."""
        return result_row(self.result, self.injector_id, self.counter, time_s, self.learning, self.correction)

    def to_dict(self) -> dict[str, Any]:
        """The JSON line (``replay --json``, ``track``): the published (``filtered``: the estimate, its
        σ, drift rate and valve prediction) and the raw estimate, the status and its reason, the
        outliers this injection decided, the injector's learning (None: off) and drive correction
        (absent: off), and the learning changes it brought (``self_calibration``, ModelCalibration
        frames)."""
        f = self.result.filtered_dict()
        out = {"injector_id": self.injector_id, "counter": self.counter, "status": self.result.status.value,
               "reason": self.result.reason, "outliers": self.result.outliers, "filtered": f,
               "raw": self.result.raw.to_dict(),
               "learning": self.learning.to_dict() if self.learning is not None else None}
        if self.calibrations:   # self-calibration changes with this injection (ModelCalibration frames)
            out["self_calibration"] = {str(i): st.to_dict() for i, st in self.calibrations}
        if self.correction is not None:
            out["drive_correction"] = self.correction.to_dict()
        return out


class Processor:
    """The estimator as the daemon runs it: the tracker, learning and the drive correction for each
    injection, and the output frames (what :func:`~estimator.pipeline.build.build_pipeline` returns
    third).

    :meth:`estimate` takes one :class:`~estimator.ident.measurement.Injection` and, where the caller
    knows it (an ECU knows its next rail pressure), the next injection's preload force; it returns a
    :class:`Published`: the tracker's result (``result``), the injector's learning state (``learning``)
    and its drive correction (``correction``, a :class:`~estimator.drive.correction.Correction` for that
    preload force, carried to any other by :meth:`~estimator.drive.correction.Correction.at`), and the
    CAN frames the daemon sends (``frames``). :meth:`handle` does the same for the codec's events (the
    daemon's and a replay's path). The same estimate and correction come from a ``Tracker`` and a
    ``DriveCompensator`` through :func:`~estimator.drive.correction.estimate_unchecked` and
    :func:`~estimator.drive.correction.correction_after`.
    """

    def __init__(self, codec: Codec, tracker: Tracker, counters: Counters, commands: str = "reset-only",
                 compensator: DriveCompensator | None = None) -> None:
        if commands not in COMMAND_POLICIES:
            raise ValueError(f"commands = {commands!r} must be one of {', '.join(COMMAND_POLICIES)}")
        self.codec = codec
        self.tracker = tracker
        self.counters = counters
        self.commands = commands
        self.compensator = compensator      # per-injector drive corrections (None: off)
        self.rlog = RateLimitedLog(log)
        self._logged: dict[int, str] = {}   # the learning state last logged per injector (progress is not logged)
        self._table_cursor: dict[int, int] = {}   # the next drive-table row to send per injector
        # rolling counters: each wraps at its signal's width (32 or 16 bits)
        self._masks = _wrap_masks(codec, EstimatorStatus, HEARTBEAT_COUNTERS)
        self._health_masks = _wrap_masks(codec, EstimatorHealth, HEALTH_COUNTERS)
        self._handlers: dict[type, Callable[[Any], Published | None]] = {
            Completed: self._estimate, Rejected: self._log_reject, Malformed: self._log_malformed,
            EstimatorCommand: self._command}

    def handle(self, events: Sequence[Event]) -> list[Published]:
        """Process events in order (a handler per event type); returns one Published per injection that
        reached the estimator."""
        out = []
        for e in events:
            pub = self._handlers[type(e)](e)
            if pub is not None:
                out.append(pub)
        return out

    def _log_reject(self, e: Rejected) -> None:
        self.rlog.log(logging.WARNING, f"reject-{e.reason}", "injector %d counter %d rejected: %s (%s)",
                      e.injector_id, e.counter, e.reason, e.detail)

    def _log_malformed(self, e: Malformed) -> None:
        self.rlog.log(logging.WARNING, f"malformed-{e.arbitration_id}", "malformed frame 0x%03X: %s",
                      e.arbitration_id, e.detail)

    def prior_problem(self, nu_n_per_v: float, lh_um: float) -> str | None:
        """Why a prior (N/V, µm) is outside the physical ranges (Table 1's N_u, the model's L_h), or None."""
        lo, hi = self.tracker.config.ident.lh_range(self.tracker.params)
        try:
            self.tracker.params.psa.check_nu(nu_n_per_v)
        except ParameterError as exc:
            return str(exc)
        if not (math.isfinite(lh_um) and lo <= lh_um <= hi):
            return f"L_h = {lh_um:.3f} µm outside [{lo:g}, {hi:g}] µm"
        return None

    def _command(self, c: EstimatorCommand) -> None:
        """Apply a command as the policy allows: ``off`` none, ``reset-only`` resets and relearns,
        ``all`` priors too. Applied commands are logged rate-limited per kind, like rejects."""
        cnt = self.counters
        if c.command == Command.NONE:
            return
        if c.command not in (Command.RESET, Command.SET_PRIOR, Command.RELEARN):
            cnt.commands_unknown += 1
            self.rlog.log(logging.WARNING, "command-unknown", "injector %d: undefined command code %d ignored",
                          c.injector_id, c.command)
            return
        name = Command(c.command).name.lower()
        allowed = self.commands == "all" or (self.commands == "reset-only" and c.command != Command.SET_PRIOR)
        if not allowed:
            cnt.commands_refused += 1
            self.rlog.log(logging.WARNING, f"command-policy-{name}", "injector %d: command %s refused (commands = %s)",
                          c.injector_id, name, self.commands)
            return
        if c.command in (Command.RESET, Command.RELEARN):
            (self.tracker.reset if c.command == Command.RESET else self.tracker.relearn)(c.injector_id)
            if self.compensator is not None and c.command == Command.RESET:
                self.compensator.forget(c.injector_id)
            cnt.commands_applied += 1
            self.rlog.log(logging.INFO, f"command-{name}", "injector %d: %s by command", c.injector_id, name)
            return
        problem = self.prior_problem(c.prior_nu_n_per_v, c.prior_lh_um)
        if problem:
            cnt.commands_refused += 1
            self.rlog.log(logging.WARNING, "command-prior-range", "injector %d: prior refused: %s",
                          c.injector_id, problem)
            return
        self.tracker.set_prior(c.injector_id, c.prior_nu_n_per_v, c.prior_lh_um)
        cnt.commands_applied += 1
        log.info("injector %d: prior N_u=%.4f N/V, L_h=%.3f µm by command", c.injector_id, c.prior_nu_n_per_v,
                 c.prior_lh_um)

    def _estimate(self, e: Completed) -> Published:
        h = e.header
        # time of the injection: the bus timestamp of its last frame (the same live and in replay)
        inj = Injection(e.current_a, e.voltage_v, h.sample_period_ns * 1e-9, h.preload_force_n, h.injector_id,
                        h.counter, h.fuel_temperature_c, e.t_last)
        return self.estimate(inj)

    def estimate(self, inj: Injection, next_preload_n: float | None = None) -> Published:
        """One injection through the estimator: counted, logged, its learning and drive correction (for
        ``next_preload_n``, N, the next injection's preload force when the caller knows it, as an ECU
        does; else this injection's). An injection its drive correction drove beyond the levels the
        injector's model was checked at is estimated as such (:func:`estimate_unchecked`)."""
        res = (self.tracker.update(inj) if self.compensator is None
               else estimate_unchecked(self.compensator, self.tracker, inj))
        # an "unconfirmed" injection is counted when the next one decides (accepted or outlier)
        self.counters.rejected_outlier += res.outliers
        self.counters.accepted += res.accepted
        if res.failed_probe:
            self.rlog.log(logging.INFO, "drive-probe", "injector %d counter %d: %s", inj.injector_id, inj.counter,
                          res.reason)
        elif res.status == Status.REJECTED and not res.outliers:
            self.counters.reject(RejectReason.INVALID)
            self.rlog.log(logging.WARNING, "reject-estimator", "injector %d counter %d rejected: %s",
                          inj.injector_id, inj.counter, res.reason)
        changes = tuple(self.tracker.take_calibration_changes()) if self.tracker.calibrator is not None else ()
        for iid, st in changes:
            if st.state != self._logged.get(iid) and st.state in (Learning.ADOPTED, Learning.REFUSED,
                                                                  Learning.RELEARNING):
                log.info("injector %d: learning %s (%s)", iid, st.state, st.message)
            self._logged[iid] = st.state
            if st.state == Learning.ADOPTED and st.out_of_tolerance:
                log.warning("injector %d: out_of_tolerance: %s beyond the part's tolerance", iid,
                            ", ".join(st.out_of_tolerance))
        correction = self._correction(inj, res, next_preload_n) if self.compensator is not None else None
        rows: tuple[int, ...] = ()
        if correction is not None and correction.table:   # a few rows of the table with each injection, in turn
            n = len(correction.table)
            first = self._table_cursor.get(inj.injector_id, 0) % n
            rows = tuple((first + k) % n for k in range(min(TABLE_ROWS_PER_INJECTION, n)))
            self._table_cursor[inj.injector_id] = (first + len(rows)) % n
        return Published(inj.injector_id, inj.counter, inj.time_s, res, self.codec, changes,
                         self.tracker.calibration.get(inj.injector_id), correction, rows)

    @property
    def has_background(self) -> bool:
        """Whether deferred work (the drive correction's tables and derivatives) waits for :meth:`background`."""
        return self.compensator is not None and self.compensator.has_background

    def background(self) -> bool:
        """One injector's deferred drive-correction work (the daemon's worker runs it when no injection
        waits; left undone, it runs before that injector's next injection); whether there was any."""
        return self.compensator is not None and self.compensator.background() > 0

    def _correction(self, inj: Injection, res: TrackResult, preload_n: float | None = None) -> Correction:
        assert self.compensator is not None
        before = self.compensator.drive_disagreements
        corr = correction_after(self.compensator, self.tracker, inj, res, preload_n)
        if self.compensator.drive_disagreements != before:   # counted there, logged once per minute here
            self.rlog.log(logging.WARNING, "drive-disagrees", "injector %d counter %d: correction held: %s",
                          inj.injector_id, inj.counter, corr.reason)
        return corr

    def status_frame(self, queue_depth: int, latency_p99_ms: float, uptime_s: float,
                     stage_p99_ms: dict[str, float] | None = None) -> Frame:
        """The EstimatorStatus heartbeat frame (``stage_p99_ms``: p99 per latency stage, keys queue,
        assembly, estimation, send, in ms)."""
        counts: dict[str, Any] = {name: getattr(self.counters, name) & self._masks[name] for name in HEARTBEAT_COUNTERS}
        stages: dict[str, Any] = {f"{k}_p99_ms": v for k, v in (stage_p99_ms or {}).items()}
        return self.codec.encode(EstimatorStatus(**counts, queue_depth=queue_depth, latency_p99_ms=latency_p99_ms,
                                                 uptime_s=int(uptime_s), **stages))

    def health_frame(self, pending_injections: int) -> Frame:
        """The EstimatorHealth frame: commands applied, stale estimates, shed injections, the simulators
        built, evicted and refused by the build budget (the shared pool's and the injectors' own), worker
        errors; ``pending_injections``: complete injections waiting for the worker."""
        c = self.counters
        pools = [self.tracker.pool, *list(self.tracker.own_pools.values())]   # list(): one atomic copy
        built = sum(p.built for p in pools)
        counts = {"commands_applied": c.commands_applied, "stale": c.stale, "injections_shed": c.injections_shed,
                  "simulators_built": built, "simulators_evicted": built - sum(len(p) for p in pools),
                  "builds_refused": sum(p.over_budget for p in pools), "worker_errors": c.worker_errors,
                  "xcp_writes": c.xcp_writes}
        return self.codec.encode(EstimatorHealth(
            **{k: v & self._health_masks[k] for k, v in counts.items()},
            pending_injections=min(pending_injections, 0xFFFF), injectors=min(len(self.tracker.states), 255)))
