"""Fast simulators per sample period, bounded: an LRU of ``max_size`` and an optional set of periods.

A :class:`~estimator.model.fast_sim.FastSimulator` tabulates its transition matrices for one sample
period (about 3 MB and 30 ms to build). A bus node that varies ``SamplePeriod`` must not be able to
grow the estimator's memory: at most ``max_size`` simulators are kept, least recently used first out,
and where ``periods_ns`` is given every other period is refused with a reason.
"""

from __future__ import annotations

from collections.abc import Iterable

import math
from collections import OrderedDict

from estimator.model.fast_sim import FastSimulator
from estimator.model.parameters import InjectorParameters, load_nominal


class SimulatorPool:
    """LRU-bounded simulators keyed by the sample period in ns (rounded to 1 ps).

    Parameters
    ----------
    params : the model parameters every simulator uses (default: Tables 1 and 2).
    max_size : simulators kept at most.
    periods_ns : the accepted sample periods in ns; empty: any positive period.
    """

    def __init__(self, params: InjectorParameters | None = None, max_size: int = 4,
                 periods_ns: Iterable[int] = ()) -> None:
        if max_size < 1:
            raise ValueError(f"max_size = {max_size} must be >= 1")
        self.params = params or load_nominal()
        self.max_size = max_size
        self.periods_ns = frozenset(int(p) for p in periods_ns)
        self._sims: OrderedDict[float, FastSimulator] = OrderedDict()
        self.built = 0          # simulators built so far (evictions = built - len)

    @staticmethod
    def _key(dt_s: float) -> float:
        return round(dt_s * 1e9, 3)

    def refusal(self, dt_s: float) -> str | None:
        """Why this sample period (s) is not accepted, or None."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            return f"sample period {dt_s!r} s is not positive"
        if self.periods_ns and self._key(dt_s) not in self.periods_ns:
            return (f"sample period {dt_s * 1e9:g} ns is not one of the configured "
                    f"{', '.join(str(p) for p in sorted(self.periods_ns))} ns")
        return None

    def add(self, sim: FastSimulator) -> None:
        """Put an existing simulator in (it counts against ``max_size``)."""
        self._store(self._key(sim.dt_s), sim)

    def get(self, dt_s: float) -> FastSimulator:
        """The simulator for ``dt_s`` (s), built on first use; the least recently used one goes if full."""
        key = self._key(dt_s)
        sim = self._sims.get(key)
        if sim is not None:
            self._sims.move_to_end(key)
            return sim
        sim = FastSimulator(self.params, dt_s=dt_s)
        self.built += 1
        self._store(key, sim)
        return sim

    def _store(self, key: float, sim: FastSimulator) -> None:
        self._sims[key] = sim
        self._sims.move_to_end(key)
        while len(self._sims) > self.max_size:
            self._sims.popitem(last=False)

    def __len__(self) -> int:
        return len(self._sims)
