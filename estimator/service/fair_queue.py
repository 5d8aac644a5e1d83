"""Fair sharing of the worker between injectors: complete injections wait per injector, and the
injector with the least worker time used goes next.

Frames are still decoded and assembled in bus order as they arrive (about 5 µs a frame), so the
header-to-trailer timeouts are judged as before. Only the identification, the expensive part
(0.5–5 ms an injection, more for a new injector's cold start), is scheduled: by start-time fair
queueing (Goyal, Vin and Cheng, 1996) with the worker time each identification took as its cost.
Every injector has a tag, the worker time it has used on the worker's virtual clock; the lowest
tag goes next; an injector that was idle joins at the virtual clock, so idling earns no credit and
a new injector id none either; when nothing waits, every debt is forgiven.

Injectors the daemon knows (established: estimated many times since their last reset) go before
any it does not, so a stranger flooding unused injector ids, or resetting them to make every
injection a cold start, delays an established injector by the one identification in progress.
Among equals, an injector that sends more than its share waits behind itself (a round of turns at
most), not behind the flood's backlog. When the worker cannot keep up, it is the flooding
injector's oldest waiting injections that are shed (counted), never another's. Without overload
each injection is estimated as soon as it is complete, as the offline replay does.

Above capacity the daemon sheds rather than queues, by one rule per injector: when an established
injector's injection comes to the head after waiting longer than the deadline (``shed_after_ms``),
it is shed unestimated and counted, and the injector's next one is taken instead. The worker's
time then goes only to injections it can still publish within the deadline; an established
injector's filter loses an update, not its timeliness, and every injector with traffic keeps being
estimated in turn (a shed item books no cost, so its injector stays at the front). An injector the
daemon does not know yet is never shed by age: its first estimate is what it waits for.
"""

from __future__ import annotations

import collections
from typing import Generic, TypeVar

T = TypeVar("T")

PENDING_PER_INJECTOR = 4      # complete injections that may wait per injector; older ones are shed


class FairQueue(Generic[T]):
    """Waiting injections per injector; :meth:`take` returns the next one to estimate, :meth:`charge`
    books the worker time (s) its identification took. No clock of its own: the order depends only
    on the items and the costs booked, so a test drives it exactly.

    ``put`` returns the item shed to make room (the injector's oldest), or None.
    """

    def __init__(self, per_injector: int = PENDING_PER_INJECTOR, deadline_s: float | None = None) -> None:
        if per_injector < 1:
            raise ValueError(f"per_injector = {per_injector}: must be >= 1")
        if deadline_s is not None and not deadline_s > 0:
            raise ValueError(f"deadline_s = {deadline_s}: must be > 0 s or None")
        self.per_injector = per_injector
        self.deadline_s = deadline_s           # an established injector's item older than this at take is shed
        # per injector: (class, arrival number, arrival time s, item)
        self._waiting: dict[int, collections.deque[tuple[int, int, float, T]]] = {}
        self.expired: collections.deque[tuple[int, T]] = collections.deque()   # shed by age, for the caller to count
        self._tag: dict[int, float] = {}       # start tag of the injector's next item, the end of its last one
        self._virtual = 0.0                    # the tag of the item served last
        self._arrivals = 0
        self.shed = 0
        self.pending = 0                       # items waiting (an int: another thread may read it)

    def __len__(self) -> int:
        return self.pending

    def put(self, injector: int, item: T, known: bool = False, arrived: float = 0.0) -> T | None:
        """Queue ``item`` of ``injector``; returns the injector's oldest item if it had to be shed.
        ``known``: the injector is an established one, served before any that is not (a new id, one
        just reset), whatever the tags, and shed by age; ``arrived``: when it was complete (s, the
        clock :meth:`take` is given)."""
        q = self._waiting.setdefault(injector, collections.deque())
        if not self.pending:   # the worker was idle: nobody owes it anything
            self._virtual = max(self._virtual, max(self._tag.values(), default=0.0))
        if not q:   # the injector becomes active: it joins at the virtual clock, idle time earns nothing
            self._tag[injector] = max(self._virtual, self._tag.get(injector, 0.0))
        shed = None
        if len(q) >= self.per_injector:
            shed = q.popleft()[3]
            self.shed += 1
            self.pending -= 1
        q.append((0 if known else 1, self._arrivals, arrived, item))
        self._arrivals += 1
        self.pending += 1
        return shed

    def take(self, now: float = 0.0) -> tuple[int, T] | None:
        """The next (injector, item): known injectors first, then the lowest tag, then the earliest
        arrival; None when nothing waits. Book its cost with :meth:`charge` before the next ``take``.
        With a deadline, a known injector's item that has waited longer than it at ``now`` (s) is
        shed on the way (appended to :attr:`expired`)."""
        while True:
            best: tuple[int, float, int, int] | None = None
            for injector, q in self._waiting.items():
                if q:
                    key = (q[0][0], self._tag[injector], q[0][1], injector)
                    if best is None or key < best:
                        best = key
            if best is None:
                return None
            cls, tag, _, injector = best
            self._virtual = tag
            self.pending -= 1
            _, _, arrived, item = self._waiting[injector].popleft()
            if cls == 0 and self.deadline_s is not None and now - arrived > self.deadline_s:
                self.shed += 1
                self.expired.append((injector, item))
                continue
            return injector, item

    def charge(self, injector: int, seconds: float) -> None:
        """Book ``seconds`` of worker time to the injector's last item taken."""
        # its next waiting item, if any, starts where this one ended
        self._tag[injector] = self._tag.get(injector, self._virtual) + max(0.0, seconds)
