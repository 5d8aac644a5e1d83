"""The daemon's latency record: one sample per published injection, with its stages, for the
heartbeat's p99s."""

from __future__ import annotations

import collections
import threading
from dataclasses import dataclass

import numpy as np

STAGES = ("queue", "assembly", "estimation", "send")   # the parts of the latency, in order


WINDOW_S = 10.0    # the heartbeat's p99s cover the last 10 s


@dataclass
class Stats:
    """Latency samples (last 10 s, at most 100 000) for the heartbeat's p99s; the worker adds, the
    heartbeat thread reads (hence the lock).

    One sample per published injection: the total (last frame arrived -> EstimateState sent) and its
    :data:`STAGES` in seconds: waiting in the input queue, decoding and reassembly, the estimator,
    handing the frame to the bus.
    """

    window_s: float = WINDOW_S

    def __post_init__(self) -> None:
        self.samples: collections.deque[tuple[float, float, tuple[float, ...]]] = collections.deque(maxlen=100_000)
        self._lock = threading.Lock()

    def add(self, t: float, latency_s: float, stages_s: tuple[float, float, float, float]) -> None:
        with self._lock:
            self.samples.append((t, latency_s, stages_s))
            while self.samples and self.samples[0][0] < t - self.window_s:
                self.samples.popleft()

    def p99_ms(self) -> float:
        """p99 of the total latency in ms (0 without samples)."""
        return self.p99s_ms()[0]

    def p99s_ms(self) -> tuple[float, dict[str, float]]:
        """p99 of the total and of each stage (ms; 0 without samples)."""
        with self._lock:
            rows = [(s, *st) for _, s, st in self.samples]
        if not rows:
            return 0.0, dict.fromkeys(STAGES, 0.0)
        total, *stages = np.percentile(np.array(rows), 99, axis=0) * 1e3
        return float(total), dict(zip(STAGES, map(float, stages)))
