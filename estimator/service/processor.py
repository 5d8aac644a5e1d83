"""Events -> recursive estimator -> output frames. No threads, no bus, no clocks of its own.

Used unchanged by the live daemon and by the offline replay, so both publish the same estimates
for the same frames.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, fields

from estimator.codec.assembler import Completed, Rejected
from estimator.codec.ingest import Counters, Event, Malformed
from estimator.codec.records import (COMMAND_RESET, COMMAND_SET_PRIOR, Codec, EstimateQuality,
                                     EstimateState, EstimatorCommand, EstimatorStatus, ValvePrediction)
from estimator.ident.measurement import Injection
from estimator.ident.status import Status
from estimator.ident.tracker import Tracker, TrackResult
from estimator.service.ratelimit import RateLimitedLog

log = logging.getLogger(__name__)
# the heartbeat's counters are the Counters fields of the same name
_STATUS_COUNTERS = tuple(f.name for f in fields(EstimatorStatus) if f.name in {g.name for g in fields(Counters)})


@dataclass(frozen=True)
class Published:
    """One processed injection: its identification, the result and the frames sent for it."""

    injector_id: int
    counter: int
    t_last: float
    result: TrackResult
    frames: list

    def to_dict(self) -> dict:
        """JSON-ready line (replay output)."""
        f = self.result.filtered_dict()
        return {"injector_id": self.injector_id, "counter": self.counter, "status": self.result.status,
                "reason": self.result.reason, "filtered": f, "raw": self.result.raw.to_dict()}


class Processor:
    """Runs the tracker on completed injections and builds the estimator's output frames."""

    def __init__(self, codec: Codec, tracker: Tracker, counters: Counters) -> None:
        self.codec = codec
        self.tracker = tracker
        self.counters = counters
        self.rlog = RateLimitedLog(log)

    def handle(self, events: list[Event]) -> list[Published]:
        """Process events in order; returns one Published per injection that reached the estimator."""
        out = []
        for e in events:
            if isinstance(e, Completed):
                out.append(self._estimate(e))
            elif isinstance(e, Rejected):
                self.rlog.log(logging.WARNING, f"reject-{e.reason}", "injector %d counter %d rejected: %s (%s)",
                              e.injector_id, e.counter, e.reason, e.detail)
            elif isinstance(e, Malformed):
                self.rlog.log(logging.WARNING, f"malformed-{e.arbitration_id}", "malformed frame 0x%03X: %s",
                              e.arbitration_id, e.detail)
            elif isinstance(e, EstimatorCommand):
                self._command(e)
        return out

    def _command(self, c: EstimatorCommand) -> None:
        if c.command == COMMAND_RESET:
            self.tracker.reset(c.injector_id)
            log.info("injector %d: reset by command", c.injector_id)
        elif c.command == COMMAND_SET_PRIOR:
            psa = self.tracker.simulator(0.5e-6).params.psa
            if not (psa.nu_min_n_per_v <= c.prior_nu_n_per_v <= psa.nu_max_n_per_v and -5.0 <= c.prior_lh_um <= 15.0):
                self.rlog.log(logging.WARNING, "prior-range", "injector %d: prior N_u=%.3f N/V, L_h=%.3f µm out of "
                              "range, ignored", c.injector_id, c.prior_nu_n_per_v, c.prior_lh_um)
                return
            self.tracker.set_prior(c.injector_id, c.prior_nu_n_per_v, c.prior_lh_um)
            log.info("injector %d: prior N_u=%.4f N/V, L_h=%.3f µm by command", c.injector_id, c.prior_nu_n_per_v,
                     c.prior_lh_um)

    def _estimate(self, e: Completed) -> Published:
        h = e.header
        # time of the injection: the bus timestamp of its last frame (the same live and in replay)
        inj = Injection(e.current_a, e.voltage_v, h.sample_period_ns * 1e-9, h.preload_force_n, h.injector_id,
                        h.counter, h.fuel_temperature_c, e.t_last)
        res = self.tracker.update(inj)
        # an "unconfirmed" injection is counted when the next one decides (accepted or outlier)
        self.counters.rejected_outlier += res.outliers
        self.counters.accepted += res.accepted
        if res.status == Status.REJECTED and not res.outliers:
            self.counters.reject("invalid")
            self.rlog.log(logging.WARNING, "reject-estimator", "injector %d counter %d rejected: %s",
                          h.injector_id, h.counter, res.reason)
        return Published(h.injector_id, h.counter, e.t_last, res, self.frames_for(h.injector_id, h.counter, res))

    def frames_for(self, injector_id: int, counter: int, res: TrackResult) -> list:
        """EstimateState, EstimateQuality and ValvePrediction of one result."""
        have = math.isfinite(res.nu_n_per_v) and math.isfinite(res.lh_m)
        status = res.status.code if have else Status.NO_ESTIMATE.code
        enc = self.codec.encode
        return [
            enc(EstimateState(injector_id, counter, res.nu_n_per_v, res.lh_m * 1e6, status)),
            enc(EstimateQuality(injector_id, counter, res.raw.cost_vs * 1e6, res.sigma_nu, res.sigma_lh_m * 1e6,
                                res.evaluations, int(res.raw.robust))),
            enc(ValvePrediction(injector_id, counter, res.t_contact_s * 1e6, res.t_open_s * 1e6, res.stroke_m * 1e6)),
        ]

    def status_frame(self, queue_depth: int, latency_p99_ms: float, uptime_s: float):
        """The EstimatorStatus heartbeat frame."""
        counts = {name: getattr(self.counters, name) & 0xFFFFFFFF for name in _STATUS_COUNTERS}  # 32-bit rolling
        return self.codec.encode(EstimatorStatus(**counts, queue_depth=queue_depth, latency_p99_ms=latency_p99_ms,
                                                 uptime_s=int(uptime_s)))
