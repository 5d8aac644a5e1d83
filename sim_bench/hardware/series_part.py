"""Series parts: simulated injectors whose structure differs from Tables 1-2 as production parts do.

Table 1's mounting values come from one laboratory's finite-element model and Table 2's from one
valve; series parts differ by 5-15 %. A :class:`SeriesPart` draws every structural parameter within
``±spread`` (uniform, relative), and optionally adds what a real test bench adds: the amplifier's
anti-aliasing filters and I/U skew, a preload force in the header that is off the true one (an ECU
computes it from rail pressure), and the hysteresis/series-resistance mismatch of
:class:`sim_bench.hardware.plant.PlantConfig`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimator.model.chain import NO_CHAIN, MeasurementChain
from estimator.model.parameters import STRUCTURAL, InjectorParameters, load_nominal, scaled

#: the chain of a "chain" series part: a 300 kHz filter on U, and I sampled one sample (0.5 µs) late
TYPICAL_CHAIN = MeasurementChain.from_cutoffs(u_cutoff_hz=300e3, i_skew_s=0.5e-6)


@dataclass(frozen=True)
class SeriesPart:
    """One simulated series injector: its true parameters, chain, header preload error and mismatch.

    ``factors`` maps ``"table.field"`` to the true value over the nominal one; ``preload_factor`` is
    the header's PreloadForce over the true preload force.
    """

    factors: dict
    chain: MeasurementChain = NO_CHAIN
    preload_factor: float = 1.0
    mismatch: bool = False

    @property
    def params(self) -> InjectorParameters:
        """The true parameters of this part."""
        return scaled(load_nominal(), self.factors)

    def describe(self) -> str:
        """One line: the largest deviations and what else the part has."""
        worst = sorted(self.factors.items(), key=lambda kv: -abs(kv[1] - 1))[:3]
        parts = [", ".join(f"{k.split('.')[1]} {100 * (f - 1):+.0f} %" for k, f in worst)]
        if not self.chain.identity:
            parts.append("chain")
        if self.preload_factor != 1.0:
            parts.append(f"preload {100 * (self.preload_factor - 1):+.0f} %")
        if self.mismatch:
            parts.append("hysteresis")
        return "; ".join(parts)


def draw(rng: np.random.Generator, spread: float = 0.10, chain: MeasurementChain = NO_CHAIN,
         preload_spread: float = 0.0, mismatch: bool = False) -> SeriesPart:
    """A seeded series part: every structural parameter uniform within ``±spread`` (relative), the
    header's preload force within ``±preload_spread`` of the true one."""
    factors = {f"{t}.{n}": float(1.0 + rng.uniform(-spread, spread)) for t, n in STRUCTURAL}
    pf = float(1.0 + rng.uniform(-preload_spread, preload_spread)) if preload_spread > 0 else 1.0
    return SeriesPart(factors, chain, pf, mismatch)
