"""Fast simulators per sample period, bounded: an LRU of ``max_size`` and an optional set of periods.

A :class:`~estimator.model.fast_sim.FastSimulator` tabulates its transition matrices for one sample
period (about 3 MB and 30 ms to build). A bus node that varies ``SamplePeriod`` must not be able to
grow the estimator's memory: at most ``max_size`` simulators are kept, least recently used first out,
and where ``periods_ns`` is given every other period is refused with a reason. Nor may it keep the
worker building: beyond ``build_burst`` simulators at once, a pool builds one every
``build_interval_s`` of the injections' own (bus) time; an injection whose period has no simulator
and finds the budget spent is refused before any simulation. The budget runs on the injections'
time, so a replay of a capture refuses what the live daemon refused; injections without a time
(single trace files) are not budgeted.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Iterable

from estimator.model.fast_sim import FastSimulator
from estimator.model.parameters import InjectorParameters, load_nominal

BUILD_BURST = 2            # simulators a pool may build at once ...
BUILD_INTERVAL_S = 10.0    # ... and then one every this many seconds of bus time


class SimulatorPool:
    """LRU-bounded simulators keyed by the sample period in ns (rounded to 1 ps).

    Parameters
    ----------
    params : the model parameters every simulator uses (default: Tables 1 and 2).
    max_size : simulators kept at most.
    periods_ns : the accepted sample periods in ns; empty: any positive period.
    build_burst, build_interval_s : the build budget (see the module docstring).
    """

    def __init__(self, params: InjectorParameters | None = None, max_size: int = 4,
                 periods_ns: Iterable[int] = (), build_burst: int = BUILD_BURST,
                 build_interval_s: float = BUILD_INTERVAL_S) -> None:
        if max_size < 1:
            raise ValueError(f"max_size = {max_size} must be >= 1")
        if build_burst < 1 or not build_interval_s > 0:
            raise ValueError(f"build budget {build_burst}, {build_interval_s} s must be >= 1 and > 0 s")
        self.params = params or load_nominal()
        self.max_size = max_size
        self.periods_ns = frozenset(int(p) for p in periods_ns)
        self._sims: OrderedDict[float, FastSimulator] = OrderedDict()
        self._last_key: tuple[float, float] = (math.nan, math.nan)
        self.built = 0          # simulators built so far (evictions = built - len)
        self.over_budget = 0    # injections refused because the build budget was spent
        self.build_burst, self.build_interval_s = build_burst, build_interval_s
        self._tokens = float(build_burst)
        self._t_tokens: float | None = None

    def _key(self, dt_s: float) -> float:
        """The pool's key of a sample period (s): ns to 1 ps. The last one is remembered (every injection
        looks its simulator up three times, at one period)."""
        last = self._last_key
        if dt_s == last[0]:
            return last[1]
        key = round(dt_s * 1e9, 3)
        self._last_key = (dt_s, key)   # one tuple: a reader on another thread sees a pair that belongs together
        return key

    def refusal(self, dt_s: float, time_s: float = math.nan) -> str | None:
        """Why this sample period (s) of an injection at ``time_s`` (s, bus time; NaN: unknown) is not
        accepted, or None."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            return f"sample period {dt_s!r} s is not positive"
        key = self._key(dt_s)
        if self.periods_ns and key not in self.periods_ns:
            return (f"sample period {dt_s * 1e9:g} ns is not one of the configured "
                    f"{', '.join(str(p) for p in sorted(self.periods_ns))} ns")
        if key not in self._sims and not self._budget(time_s):
            self.over_budget += 1
            return (f"no simulator for sample period {dt_s * 1e9:g} ns and the build budget is spent "
                    f"({self.build_burst} at once, then one every {self.build_interval_s:g} s)")
        return None

    def _budget(self, time_s: float) -> bool:
        """Whether a simulator may be built now (the tokens refilled up to ``time_s``)."""
        if not math.isfinite(time_s):
            return True
        if self._t_tokens is not None:
            self._tokens = min(float(self.build_burst),
                               self._tokens + max(time_s - self._t_tokens, 0.0) / self.build_interval_s)
        self._t_tokens = time_s
        return self._tokens >= 1.0

    def has(self, dt_s: float) -> bool:
        """Whether a simulator for ``dt_s`` (s) is built."""
        return self.built_for(dt_s) is not None

    def built_for(self, dt_s: float) -> FastSimulator | None:
        """The simulator for ``dt_s`` (s) if one is built, else None; never builds one, nor counts as a
        use (a lookup on every injection, beside the estimate that used it)."""
        return self._sims.get(self._key(dt_s)) if math.isfinite(dt_s) else None

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
        self._tokens -= 1.0
        self._store(key, sim)
        return sim

    def _store(self, key: float, sim: FastSimulator) -> None:
        self._sims[key] = sim
        self._sims.move_to_end(key)
        while len(self._sims) > self.max_size:
            self._sims.popitem(last=False)

    def __len__(self) -> int:
        return len(self._sims)
