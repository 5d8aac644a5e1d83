"""Pipeline time from the bus: frame timestamps, plus a documented wall-clock guard for a silent bus.

Timeouts (a header without its trailer) are judged by the timestamps the bus gave the frames, never
by the reading process's clock: a daemon stalled for a while (SIGSTOP, swap, a slow disk) finds the
frames it missed in its socket with their original timestamps and judges them as a replay of the
capture would. Only when no frame at all has *arrived* for ``silent_bus_s`` of wall-clock time (a
sender that died mid-injection on an otherwise silent bus) does the clock move on without the bus:
bus time = last frame timestamp + wall time since that frame arrived. A replay ends with the same
step (:meth:`BusClock.end`), so a capture whose last injection never completes counts the same
timeout live and offline. Stalls longer than ``silent_bus_s`` can still make live and replay differ.
No threads, no clock reads: the caller passes its monotonic clock in.
"""

from __future__ import annotations

import math


class BusClock:
    """Frame timestamps -> pipeline time (s), monotonic non-decreasing."""

    def __init__(self, silent_bus_s: float = 1.0) -> None:
        if not (math.isfinite(silent_bus_s) and silent_bus_s > 0):
            raise ValueError(f"silent_bus_s = {silent_bus_s!r} must be a positive number of seconds")
        self.silent_bus_s = silent_bus_s
        self.now = 0.0                       # pipeline time, s (bus clock)
        self._arrived: float | None = None   # local monotonic time the last frame arrived, s

    def on_frame(self, timestamp: float, arrived: float | None = None) -> float:
        """The pipeline time of a frame stamped ``timestamp`` (s) that arrived at ``arrived`` (monotonic s).

        A missing (0), non-finite or backward timestamp counts as the current pipeline time: one
        bad stamp cannot rewind the clock or time out everything at once by jumping back and forth.
        """
        if math.isfinite(timestamp) and timestamp > self.now:
            self.now = timestamp
        if arrived is not None:
            self._arrived = arrived
        return self.now

    def idle(self, mono: float) -> float | None:
        """Pipeline time while no frame arrives (monotonic ``mono`` s), or None while the guard holds."""
        if self._arrived is None:
            return None
        silent = mono - self._arrived
        if silent < self.silent_bus_s:
            return None
        return self.now + silent

    def end(self) -> float:
        """The pipeline time at the end of a capture: the silent-bus guard has run out."""
        return self.now + self.silent_bus_s
