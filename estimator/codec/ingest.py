"""Frames in, events out: decode (cantools/numpy), reassemble, count. Pure: time is an argument.

The same :class:`Ingest` runs in the live daemon's worker and in the offline replay, which is
why the two produce identical output on identical frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from estimator.codec.assembler import REASON_COUNTER, Assembler, Completed, Rejected
from estimator.codec.frame import Frame
from estimator.codec.records import (Codec, EstimatorCommand, InjectionHeader, InjectionTrailer, MalformedFrame,
                                     SampleBlock)


@dataclass
class Counters:
    """Everything the EstimatorStatus heartbeat reports, plus finer detail for logs and JSON."""

    accepted: int = 0
    rejected_crc: int = 0
    rejected_missing: int = 0
    rejected_timeout: int = 0
    rejected_invalid: int = 0
    rejected_outlier: int = 0
    frames_dropped: int = 0
    frames_malformed: int = 0
    frames_unknown: int = 0
    frames_total: int = 0
    bus_errors: int = 0
    commands_applied: int = 0
    commands_refused: int = 0
    commands_unknown: int = 0
    worker_errors: int = 0       # unexpected exceptions in the worker (a bug; logged rate-limited)
    reasons: dict[str, int] = field(default_factory=dict)

    def reject(self, reason: str) -> None:
        """Count one rejected injection under its reason (and the DBC counter it maps to)."""
        self.reasons[reason] = self.reasons.get(reason, 0) + 1
        attr = REASON_COUNTER.get(reason, "rejected_invalid")
        setattr(self, attr, getattr(self, attr) + 1)


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
        self._inputs = {codec.messages.header.frame_id, codec.messages.samples.frame_id,
                        codec.messages.trailer.frame_id, codec.messages.command.frame_id}

    def feed(self, frame: Frame, now: float) -> list[Event]:
        """One frame at time ``now`` (s); returns the events it completes (also timeouts up to now)."""
        c = self.counters
        c.frames_total += 1
        out: list[Event] = list(self.poll(now))
        if frame.arbitration_id not in self._inputs or frame.is_extended_id:
            c.frames_unknown += 1        # other traffic on the bus (our own outputs, other ECUs)
            return out
        try:
            rec = self.codec.decode(frame)
        except MalformedFrame as exc:
            c.frames_malformed += 1
            out.append(Malformed(frame.arbitration_id, str(exc)))
            return out
        if getattr(rec, "injector_id", 0) >= self.max_injectors:
            c.frames_malformed += 1
            out.append(Malformed(frame.arbitration_id, f"injector {rec.injector_id} >= {self.max_injectors}"))
            return out
        if isinstance(rec, InjectionHeader):
            events = self.assembler.on_header(rec, now)
        elif isinstance(rec, SampleBlock):
            events = self.assembler.on_samples(rec, now)
        elif isinstance(rec, InjectionTrailer):
            events = self.assembler.on_trailer(rec, now)
        elif isinstance(rec, EstimatorCommand):
            return out + [rec]
        else:
            events = []
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
