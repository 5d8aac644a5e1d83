"""Frames in, events out: decode (cantools/numpy), reassemble, count. Pure: time is an argument.

The same :class:`Ingest` runs in the live daemon's worker and in the offline replay, which is
why the two produce identical output on identical frames.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

from estimator.codec.assembler import Assembler, Completed, Rejected, RejectReason
from estimator.codec.errors import MalformedFrame
from estimator.codec.frame import Frame
from estimator.codec.records import (
    HEARTBEAT_COUNTERS,
    Codec,
    EstimatorCommand,
    InjectionHeader,
    InjectionTrailer,
    SampleBlock,
)


@dataclass
class Counters:
    """Everything the EstimatorStatus heartbeat reports (its rolling counters, ``records.HEARTBEAT_COUNTERS``,
    under the same names and in the same order, first), plus finer detail for logs, JSON and the
    EstimatorHealth message: frames_unknown, frames_total, commands_applied, worker_errors (unexpected
    exceptions in the worker, a bug; logged rate-limited), stale (estimates the daemon published as
    ``stale``: later than ``stale_after_ms``), injections_shed (complete injections the daemon's worker
    dropped unestimated, overloaded by their injector) and the rejections per reason."""

    accepted: int = 0
    rejected_crc: int = 0
    rejected_missing: int = 0
    rejected_timeout: int = 0
    rejected_invalid: int = 0
    rejected_outlier: int = 0
    frames_dropped: int = 0
    frames_malformed: int = 0
    bus_errors: int = 0
    commands_refused: int = 0
    commands_unknown: int = 0
    frames_unknown: int = 0
    frames_total: int = 0
    commands_applied: int = 0
    xcp_writes: int = 0
    worker_errors: int = 0
    stale: int = 0
    injections_shed: int = 0
    reasons: dict[str, int] = field(default_factory=dict)

    def reject(self, reason: RejectReason | str) -> None:
        """Count one rejected injection under its reason (and the heartbeat counter it maps to)."""
        reason = RejectReason(reason)
        self.reasons[reason.value] = self.reasons.get(reason.value, 0) + 1
        setattr(self, reason.counter, getattr(self, reason.counter) + 1)


# the heartbeat's counters are the records' list (one source): Counters begins with exactly those
assert tuple(f.name for f in fields(Counters))[:len(HEARTBEAT_COUNTERS)] == HEARTBEAT_COUNTERS, \
    "ingest.Counters must begin with records.HEARTBEAT_COUNTERS, in order"


@dataclass(frozen=True)
class Malformed:
    """A frame with a known identifier that could not be decoded."""

    arbitration_id: int
    detail: str


Event = Completed | Rejected | EstimatorCommand | Malformed


class Ingest:
    """Decodes frames and reassembles injections; counts unknown and malformed frames."""

    def __init__(self, codec: Codec, timeout_s: float = 0.05, max_injectors: int = 8) -> None:
        self.codec = codec
        self.assembler = Assembler(codec.layout, timeout_s, max_injectors)
        self.counters = Counters()
        self.max_injectors = max_injectors
        # the records the estimator consumes and what each does; every other identifier is foreign
        self._handlers: dict[type, Callable[[Any, float], list[Any]]] = {
            InjectionHeader: self.assembler.on_header, SampleBlock: self.assembler.on_samples,
            InjectionTrailer: self.assembler.on_trailer, EstimatorCommand: lambda rec, now: [rec]}
        self._inputs = {codec.frame_id(rt) for rt in self._handlers}

    def feed(self, frame: Frame, now: float) -> list[Event]:
        """One frame at time ``now`` (s); returns the events it completes (also timeouts up to now)."""
        c = self.counters
        c.frames_total += 1
        out: list[Event] = list(self.poll(now))
        if frame.arbitration_id not in self._inputs or frame.is_extended_id:
            c.frames_unknown += 1        # other traffic on the bus (our own outputs, other ECUs)
            return out
        try:
            rec: Any = self.codec.decode(frame)   # one of the handlers' records: its identifier is an input
        except MalformedFrame as exc:
            c.frames_malformed += 1
            out.append(Malformed(frame.arbitration_id, str(exc)))
            return out
        if rec.injector_id >= self.max_injectors:
            c.frames_malformed += 1
            out.append(Malformed(frame.arbitration_id, f"injector {rec.injector_id} >= {self.max_injectors}"))
            return out
        events = self._handlers[type(rec)](rec, now)
        for e in events:
            if isinstance(e, Rejected):
                c.reject(e.reason)
        return out + list(events)

    def poll(self, now: float) -> list[Rejected]:
        """Timeouts up to ``now``."""
        events = self.assembler.poll(now)
        for e in events:
            self.counters.reject(e.reason)
        return events
