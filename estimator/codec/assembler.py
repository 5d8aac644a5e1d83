"""Reassembly of injections from header, sample blocks and trailer, with per-injector validity.

Validity is data and time is an argument (``now`` in seconds, any monotonic clock): the assembler
never reads a clock, so the live daemon and the offline replay behave identically on the same
frames. Every rejected injection produces exactly one :class:`Rejected` with a reason; no bad
injection can stall the next one (a new header always starts afresh).

Reasons and the EstimatorStatus counters they feed:

=================  =====================================================================  ===============
reason             meaning                                                                counter
=================  =====================================================================  ===============
``crc``            trailer CRC-32 differs from the CRC of the received samples           RejectedCrc
``missing``        blocks missing at the trailer, or a header/trailer was lost            RejectedMissing
``duplicate``      a block index received twice                                           RejectedMissing
``order``          a block arrived out of order                                           RejectedMissing
``counter``        block/trailer counter differs from the header's                        RejectedMissing
``timeout``        header without trailer within ``timeout_s``                            RejectedTimeout
``invalid``        header values out of range, sample count mismatch, invalid samples     RejectedInvalid
=================  =====================================================================  ===============
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from estimator.codec.records import InjectionHeader, InjectionTrailer, SampleBlock
from estimator.codec.samples import INVALID_RAW, SampleLayout, samples_crc32


class RejectReason(str, Enum):
    """Why an injection is rejected (the module table); a ``str`` so logs and JSON show the word."""

    CRC = "crc"
    MISSING = "missing"
    DUPLICATE = "duplicate"
    ORDER = "order"
    COUNTER = "counter"
    TIMEOUT = "timeout"
    INVALID = "invalid"

    @property
    def counter(self) -> str:
        """The ``Counters``/EstimatorStatus field this reason is counted in."""
        return _REASON_COUNTER[self]

    def __str__(self) -> str:
        return self.value


_REASON_COUNTER = {RejectReason.CRC: "rejected_crc", RejectReason.MISSING: "rejected_missing",
                   RejectReason.DUPLICATE: "rejected_missing", RejectReason.ORDER: "rejected_missing",
                   RejectReason.COUNTER: "rejected_missing", RejectReason.TIMEOUT: "rejected_timeout",
                   RejectReason.INVALID: "rejected_invalid"}
MAX_SAMPLE_PERIOD_NS = 20_000


@dataclass(frozen=True)
class Completed:
    """A complete, CRC-checked injection (physical units) with the time its trailer arrived."""

    header: InjectionHeader
    current_a: np.ndarray
    voltage_v: np.ndarray
    t_last: float


@dataclass(frozen=True)
class Rejected:
    """An injection that will not be estimated, and why (see the module table)."""

    injector_id: int
    counter: int
    reason: RejectReason
    detail: str = ""


@dataclass
class _Pending:
    header: InjectionHeader
    started: float
    n_blocks: int
    cur: list[np.ndarray] = field(default_factory=list)
    vol: list[np.ndarray] = field(default_factory=list)
    failed: tuple[RejectReason, str] | None = None
    gap: int = -1   # first block index skipped: "missing" unless it turns up later ("order")
    foreign: int = -1   # counter of the first block that did not belong to this injection


class Assembler:
    """Per-injector reassembly state for up to ``max_injectors`` injectors."""

    def __init__(self, layout: SampleLayout, timeout_s: float = 0.05, max_injectors: int = 8) -> None:
        self.layout = layout
        self.timeout_s = timeout_s
        self.max_injectors = max_injectors
        self._pending: dict[int, _Pending] = {}
        self._orphans: dict[int, int] = {}   # injector -> counter of sample blocks seen without header
        self._timed_out: dict[int, int] = {}  # injector -> counter of the last injection rejected by timeout

    def _header_problem(self, h: InjectionHeader) -> str | None:
        if not (0 < h.sample_period_ns <= MAX_SAMPLE_PERIOD_NS):
            return f"sample period {h.sample_period_ns} ns"
        if not (3 <= h.sample_count <= 255 * self.layout.per_block):
            return f"sample count {h.sample_count}"
        if not math.isfinite(h.preload_force_n):
            return "preload force"
        return None

    def on_header(self, h: InjectionHeader, now: float) -> list[Rejected]:
        """A header starts an injection; one already pending for that injector is rejected."""
        out = self._orphan_flush(h.injector_id, h.counter)
        old = self._pending.pop(h.injector_id, None)
        if old is not None:
            out.append(Rejected(old.header.injector_id, old.header.counter, RejectReason.MISSING,
                                "next header before the trailer"))
        prob = self._header_problem(h)
        n_blocks = -(-h.sample_count // self.layout.per_block)
        p = _Pending(h, now, n_blocks)
        if prob:
            p.failed = (RejectReason.INVALID, prob)
        self._pending[h.injector_id] = p
        return out

    def on_samples(self, b: SampleBlock, now: float) -> list[Rejected]:
        """A sample block for the pending injection of its injector."""
        p = self._pending.get(b.injector_id)
        if p is None:
            # no header: the injection is lost; count it once, when its counter changes or a header comes
            out = []
            if b.injector_id in self._orphans and self._orphans[b.injector_id] != b.counter:
                out.append(Rejected(b.injector_id, self._orphans[b.injector_id], RejectReason.MISSING, "no header"))
            self._orphans[b.injector_id] = b.counter
            return out
        if p.failed:
            if p.failed[0] == RejectReason.MISSING and b.block_index == p.gap and b.counter == p.header.counter:
                p.failed = (RejectReason.ORDER, f"block {b.block_index} arrived after block {b.block_index + 1} or later")
            return []
        if b.counter != p.header.counter:
            p.failed = (RejectReason.COUNTER, f"block counter {b.counter} != header {p.header.counter}")
            p.foreign = b.counter
        elif b.block_index < len(p.cur):
            p.failed = (RejectReason.DUPLICATE, f"block {b.block_index} twice")
        elif b.block_index > len(p.cur):
            p.gap = len(p.cur)
            p.failed = (RejectReason.MISSING, f"block {p.gap} missing (got {b.block_index})")
        elif b.block_index >= p.n_blocks:
            p.failed = (RejectReason.INVALID, f"block {b.block_index} beyond the sample count")
        else:
            p.cur.append(b.current_raw)
            p.vol.append(b.voltage_raw)
        return []

    def on_trailer(self, t: InjectionTrailer, now: float) -> list[Completed | Rejected]:
        """The trailer completes (or rejects) the pending injection of its injector."""
        p = self._pending.pop(t.injector_id, None)
        if p is None:
            orphan = self._orphans.pop(t.injector_id, None)
            out: list[Completed | Rejected] = []
            if self._timed_out.pop(t.injector_id, None) == t.counter:
                return out   # a late trailer of an injection already rejected by timeout
            if orphan is not None and orphan != t.counter:
                out.append(Rejected(t.injector_id, orphan, RejectReason.MISSING, "no header"))
            out.append(Rejected(t.injector_id, t.counter, RejectReason.MISSING, "trailer without header"))
            return out
        out = list(self._orphan_flush(t.injector_id, p.header.counter))
        h = p.header
        if t.counter != h.counter and t.counter == p.foreign:
            # this injection lost its trailer and the next one its header: two losses
            out.append(Rejected(h.injector_id, h.counter, RejectReason.MISSING, "trailer lost"))
            out.append(Rejected(h.injector_id, t.counter, RejectReason.MISSING, "header lost"))
            return out
        if p.failed:
            out.append(Rejected(h.injector_id, h.counter, *p.failed))
            return out
        if t.counter != h.counter:
            out.append(Rejected(h.injector_id, h.counter, RejectReason.COUNTER, f"trailer counter {t.counter}"))
            return out
        if len(p.cur) != p.n_blocks:
            out.append(Rejected(h.injector_id, h.counter, RejectReason.MISSING, f"{len(p.cur)} of {p.n_blocks} blocks"))
            return out
        n = h.sample_count
        cur = np.concatenate(p.cur)
        vol = np.concatenate(p.vol)
        tail_c, tail_v = cur[n:], vol[n:]
        cur, vol = cur[:n], vol[:n]
        if samples_crc32(cur, vol) != t.crc32:
            out.append(Rejected(h.injector_id, h.counter, RejectReason.CRC, "CRC-32 mismatch"))
            return out
        if np.any(tail_c != 0) or np.any(tail_v != 0):
            out.append(Rejected(h.injector_id, h.counter, RejectReason.INVALID,
                                "sample count mismatch (data after the last sample)"))
            return out
        if np.any(cur == INVALID_RAW) or np.any(vol == INVALID_RAW):
            out.append(Rejected(h.injector_id, h.counter, RejectReason.INVALID, "invalid (NaN) samples"))
            return out
        out.append(Completed(h, cur * self.layout.current_scale, vol * self.layout.voltage_scale, now))
        return out

    def poll(self, now: float) -> list[Rejected]:
        """Reject injections whose trailer is overdue."""
        out = []
        for inj_id, p in list(self._pending.items()):
            if now - p.started > self.timeout_s:
                del self._pending[inj_id]
                self._timed_out[inj_id] = p.header.counter
                out.append(Rejected(inj_id, p.header.counter, RejectReason.TIMEOUT,
                                    f"no trailer after {self.timeout_s * 1e3:.0f} ms"))
        return out

    def _orphan_flush(self, injector_id: int, counter: int | None) -> list[Rejected]:
        c = self._orphans.pop(injector_id, None)
        if c is None or c == counter:
            return []
        return [Rejected(injector_id, c, RejectReason.MISSING, "no header")]

    def pending(self) -> int:
        """Number of injections being assembled."""
        return len(self._pending)
