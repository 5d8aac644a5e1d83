"""Series injectors through their life: the operating conditions a learning estimator meets in a car.

A :class:`Life` is one injector position of a lot: the series part mounted there (every structural
parameter within the lot's spread of Tables 1-2, :mod:`sim_bench.hardware.series_part`; a configurable share
of parts beyond the datasheet tolerance), the lot-wide amplifier chain (its own anti-aliasing filter
and I/U skew), a warm-up that moves N_u, a rail pressure that wanders between idle and full load
(preload force 28-300 N, a bounded random walk), slow wear of the idle stroke and, optionally, the
part swapped for another one at a given injection under the same injector id.

Everything is drawn from one seeded generator, so a seed names a lot: :func:`draw_lot` is what the
tracking bench's ``lot-life`` scenario, the self-calibration bench's false-refusal sweep and the
end-to-end ``series-lot`` bench run.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from estimator.ident.measurement import Injection
from estimator.model.chain import MeasurementChain
from estimator.model.parameters import NOMINAL_PRELOAD_N
from sim_bench.hardware import series_part
from sim_bench.hardware.amplifiers import STANDARD, Amplifier
from sim_bench.hardware.plant import Measurement, Plant, PlantConfig

PRELOAD_RANGE_N = (NOMINAL_PRELOAD_N, 300.0)   # idle to full load
PRELOAD_STEP = 0.35          # the rail pressure's walk: a step of up to 35 % of the range per injection
NU_COLD, NU_RISE = 15.6, 3.6  # N/V: the warm-up from cold, and its rise
NU_OFFSET = 0.4              # N/V: a part's own offset, uniform
WARM_UP_TAU = 25.0           # injections: the warm-up's time constant
LH_UM = (1.0, 8.0)           # a part's idle stroke, uniform
WEAR_UM = 0.05               # L_h grows by up to this much over a life (uniform)
TOLERANCE = 0.10             # the datasheet tolerance of every structural parameter (relative)
BEYOND = (0.15, 0.20)        # a part beyond tolerance: one mounting stiffness this far off (relative)
WINDOW_S = 200e-6


@dataclass(frozen=True)
class LotSpec:
    """What a lot is made of: its parts' spread, the share beyond tolerance, its chain and swaps.

    ``swap_at``: the injection at which the part at each of ``swapped`` positions is replaced by
    another one drawn from the same lot (None: no swap). ``hysteresis``: (position, gain, shape) of
    parts whose charge-voltage hysteresis R(N_u)·I cannot explain (the mismatch plant's, of that size
    and :data:`~sim_bench.hardware.plant.HYSTERESIS_SHAPES` form); such a part is within tolerance and
    stays mounted.
    """

    spread: float = TOLERANCE
    beyond_fraction: float = 0.0
    chain: MeasurementChain = series_part.TYPICAL_CHAIN
    swap_at: int | None = None
    swapped: tuple[int, ...] = ()
    window_s: float = WINDOW_S
    wear_um: float = WEAR_UM
    nu_rise: float = NU_RISE               # N/V: the warm-up's rise from NU_COLD
    lh_um: tuple[float, float] = LH_UM     # a part's idle stroke, uniform
    amplifier: Amplifier = STANDARD        # whose standard drive a correction scales
    hysteresis: tuple[tuple[int, float, str], ...] = ()


@dataclass
class Life:
    """One injector position: its parts (a second one after a swap), its truth per injection."""

    position: int
    parts: list[series_part.SeriesPart]
    beyond: list[bool]
    lh_um: list[float]
    nu_offset: float
    swap_at: int | None
    chain: MeasurementChain
    window_s: float
    wear_um: float
    seed: int
    nu_rise: float = NU_RISE
    amplifier: Amplifier = STANDARD
    hysteresis: tuple[float, str] | None = None   # the first part's (gain, shape) of a hysteresis R(N_u) I misses
    _plants: list[Plant] = field(default_factory=list, repr=False)
    _preload: float | None = field(default=None, repr=False)

    def part_at(self, k: int) -> int:
        """Which part is mounted at injection ``k`` (0, or 1 after the swap)."""
        return int(self.swap_at is not None and k >= self.swap_at)

    def truth(self, k: int, n: int, preload_n: float) -> tuple[float, float]:
        """(N_u N/V, L_h µm) at injection ``k`` of ``n``."""
        nu = NU_COLD + self.nu_rise * (1.0 - math.exp(-k / WARM_UP_TAU)) + self.nu_offset
        lh = self.lh_um[self.part_at(k)] + self.wear_um * k / max(n - 1, 1)
        return nu, lh

    def measure(self, k: int, n: int, rng: np.random.Generator, scale_for: Callable[[float], float] | None = None,
                preload_n: float | None = None) -> tuple[Measurement, dict]:
        """Injection ``k`` of a life of ``n``: the plant's measurement and the truth. Injections are
        measured in order (the rail pressure walks from one to the next). ``scale_for``: the plateau
        current scale of the amplifier's standard drive at this injection's preload force (a corrected drive;
        None: the standard drive). ``preload_n``: this preload force (N) instead of the next step of
        the walk (a caller that drew the walk ahead, :meth:`preload_walk`)."""
        if not self._plants:
            amp = self.amplifier
            cfg = PlantConfig(window_s=self.window_s, chain=self.chain, drive=amp.standard, ripple_a=amp.ripple_a,
                              ripple_period_s=amp.ripple_period_s)
            own = [cfg] * len(self.parts)
            if self.hysteresis is not None:
                own[0] = replace(cfg, mismatch=True, hysteresis_gain=self.hysteresis[0],
                                 hysteresis_shape=self.hysteresis[1])
            self._plants = [Plant(c, p.params) for c, p in zip(own, self.parts)]
        f = self._walk(rng) if preload_n is None else preload_n
        nu, lh = self.truth(k, n, f)
        p = self.part_at(k)
        scale = scale_for(f) if scale_for is not None else 1.0
        drive = self.amplifier.drive(scale) if scale_for is not None else None
        m = self._plants[p].measure(nu, lh * 1e-6, f, rng, drive)
        return m, {"k": k, "part": p, "nu_true": nu, "lh_true_um": lh, "beyond": self.beyond[p], "f_open_n": f,
                   "scale": scale}

    def _walk(self, rng: np.random.Generator) -> float:
        """The rail pressure's next step (N): a bounded random walk, reflected at idle and full load."""
        lo, hi = PRELOAD_RANGE_N
        if self._preload is None:
            self._preload = float(rng.uniform(lo, hi))
        f = self._preload + float(rng.uniform(-PRELOAD_STEP, PRELOAD_STEP)) * (hi - lo)
        f = 2 * hi - f if f > hi else (2 * lo - f if f < lo else f)
        self._preload = f
        return f

    def preload_walk(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """The preload forces (N) of ``n`` injections, drawn ahead (an ECU knows its next rail pressure)."""
        self._preload = None
        return np.array([self._walk(rng) for _ in range(n)])

    def injections(self, n: int, rng: np.random.Generator | None = None, interval_s: float = 1.0,
                   preloads: Sequence[float] | None = None) -> Iterator[tuple[Injection, Measurement, dict]]:
        """The first ``n`` injections: (what the estimator gets, the plant's measurement, the truth).
        ``preloads``: each injection's preload force (N) instead of the rail pressure's walk."""
        rng = rng if rng is not None else np.random.default_rng(self.seed)
        self._preload = None
        for k in range(n):
            m, truth = self.measure(k, n, rng, preload_n=None if preloads is None else preloads[k])
            inj = Injection(m.current_a, m.voltage_v, m.dt_s, m.f_open_n, self.position % 8, k % 256, float("nan"),
                            k * interval_s)
            yield inj, m, truth


def _draw_part(rng: np.random.Generator, spec: LotSpec, beyond: bool) -> series_part.SeriesPart:
    part = series_part.draw(rng, spread=spec.spread, chain=spec.chain)
    if not beyond:
        return part
    factors = dict(part.factors)   # one mounting stiffness beyond the tolerance, either way
    name = "psa.kg1_n_per_m" if rng.uniform() < 0.5 else "psa.kg2_n_per_m"
    factors[name] = 1.0 + float(rng.choice([-1.0, 1.0]) * rng.uniform(*BEYOND))
    return series_part.SeriesPart(factors, spec.chain)


def draw_lot(positions: int, seed: int, spec: LotSpec = LotSpec()) -> list[Life]:
    """``positions`` seeded injector lives of one lot (``spec``)."""
    rng = np.random.default_rng(seed)
    n_beyond = int(round(spec.beyond_fraction * positions))
    hysteresis = {pos: (gain, shape) for pos, gain, shape in spec.hysteresis}
    kept = [p for p in range(positions) if (spec.swap_at is None or p not in spec.swapped)   # parts that stay
            and p not in hysteresis]
    beyond_at = set(rng.choice(kept, size=min(n_beyond, len(kept)), replace=False).tolist()) if n_beyond else set()
    lives = []
    for pos in range(positions):
        flags = [pos in beyond_at]
        parts = [_draw_part(rng, spec, flags[0])]
        lhs = [float(rng.uniform(*spec.lh_um))]
        if spec.swap_at is not None and pos in spec.swapped:
            flags.append(False)
            parts.append(_draw_part(rng, spec, False))
            lhs.append(float(rng.uniform(*spec.lh_um)))
        lives.append(Life(pos, parts, flags, lhs, float(rng.uniform(-NU_OFFSET, NU_OFFSET)),
                          spec.swap_at if len(parts) > 1 else None, spec.chain, spec.window_s,
                          float(rng.uniform(0.0, spec.wear_um)), int(rng.integers(2 ** 31)), spec.nu_rise,
                          spec.amplifier, hysteresis.get(pos)))
    return lives
