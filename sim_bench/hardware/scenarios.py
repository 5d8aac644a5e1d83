"""Bench scenarios: what the simulated injectors do over time, and what goes wrong on the bus.

The vocabulary shared by every bench (this end-to-end bench and :mod:`sim_bench.benches.tracking_bench`): a
scenario has a ``name``, its ``targets`` (required: a scenario without targets cannot be built), the
``drive`` its amplifier follows (:mod:`estimator.model.drive`), a ``description``, and
``truth(injector, k, t, rng) -> Truth`` for injection ``k`` of an injector at time ``t``; each bench
keeps its scenarios in a :class:`Registry`, from which the command lines take their choices.

Temperature law of the simulated actuators (docs/guide/simulator.md): N_u(T) = 15 + 0.06 T
(N/V, T in degC, so 15 N/V at 0 degC and 21 N/V at 100 degC, Table 1's range), plus a
per-injector series-production offset. L_h per injector, drifting with wear. The preload is the
valve spring's 28 N (Table 2) plus a rail-pressure share that varies per injection.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Generic, NamedTuple, Protocol, TypeVar

import numpy as np

from estimator.model.drive import Drive, StandardDrive
from estimator.model.parameters import NOMINAL_PRELOAD_N, load_nominal

NU_RANGE = (load_nominal().psa.nu_min_n_per_v, load_nominal().psa.nu_max_n_per_v)   # Table 1, 0-100 degC
NU_AT_0C = NU_RANGE[0]
NU_PER_DEGC = (NU_RANGE[1] - NU_RANGE[0]) / 100.0   # N/V per degC: the range over 0-100 degC


def nu_of_temperature(t_c: float) -> float:
    """Coupling factor of a nominal actuator at temperature t_c (degC), N/V."""
    return NU_AT_0C + NU_PER_DEGC * t_c


class Truth(NamedTuple):
    """What a simulated injection really is: N_u (N/V), L_h (µm, as scenarios state it), valve preload
    F_open (N) and the fuel temperature its header reports (degC, NaN: none reported)."""

    nu_n_per_v: float
    lh_um: float
    f_open_n: float
    temperature_c: float


class _Named(Protocol):
    """What a registry keeps: a scenario with a name (and its targets)."""

    @property
    def name(self) -> str: ...


S = TypeVar("S", bound=_Named)


class Registry(Generic[S]):
    """The scenarios of one bench by name: unique names, each with targets of the bench's type."""

    def __init__(self, bench: str, targets_type: type) -> None:
        self.bench = bench
        self.targets_type = targets_type
        self._by_name: dict[str, S] = {}

    def register(self, sc: S) -> S:
        """Add a scenario; ValueError for a scenario without targets or a name given twice."""
        name = sc.name
        if not isinstance(getattr(sc, "targets", None), self.targets_type):
            raise ValueError(f"{self.bench} scenario {name!r} has no targets")
        if name in self._by_name:
            raise ValueError(f"{self.bench} scenario {name!r} registered twice")
        self._by_name[name] = sc
        return sc

    def __getitem__(self, name: str) -> S:
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"unknown {self.bench} scenario {name!r}; one of {', '.join(self)}") from None

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    def __iter__(self) -> Iterator[str]:
        return iter(self._by_name)

    def __len__(self) -> int:
        return len(self._by_name)

    def values(self) -> Iterator[S]:
        """The scenarios in registration order."""
        return iter(self._by_name.values())


@dataclass(frozen=True)
class FaultRates:
    """Per-frame probabilities of bus faults, and bus stalls (the node pauses sending)."""

    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0         # swap with the next frame
    corrupt: float = 0.0         # flip one payload bit (sample pairs only, so the CRC must catch it)
    stall_every_s: float = 0.0   # 0: never
    stall_s: float = 0.0

    @property
    def any(self) -> bool:
        return any((self.drop, self.duplicate, self.reorder, self.corrupt, self.stall_every_s))


@dataclass(frozen=True)
class BenchTargets:
    """Pass criteria of a bench scenario, after ``SETTLE`` injections of each injector.

    ``lh_um``: max |L_h error| in µm; ``nu_pct``: max |N_u error| in %. None: not scored (a
    scenario that measures something else, e.g. overload), which must be said explicitly.
    """

    lh_um: float | None
    nu_pct: float | None


SETTLE = 30   # injections of each injector before the targets apply


@dataclass(frozen=True)
class Scenario:
    """One bench scenario (all injectors share rate and profiles; they differ in N_u offset and L_h)."""

    name: str
    targets: BenchTargets
    drive: Drive = field(default_factory=StandardDrive)   # what the amplifier is commanded to deliver
    injectors: int = 4
    rate_hz: float = 25.0                    # injections per second per injector
    seconds: float = 20.0
    temperature_c: tuple[float, float] = (40.0, 40.0)   # from, to over ``seconds``
    lh_um: tuple[float, ...] = (1.5, 3.0, 5.0, 7.0, 2.2, 6.1, 4.0, 0.8)
    nu_offset: tuple[float, ...] = (0.0, 0.04, -0.05, 0.02, -0.03, 0.05, -0.01, 0.03)
    wear_um: float = 0.0                     # L_h drift over ``seconds``
    rail_force_n: tuple[float, float] = (0.0, 0.0)   # extra preload: mean, std per injection
    mismatch: bool = False
    faults: FaultRates = field(default_factory=FaultRates)
    window_s: float = 100e-6
    decimation: int = 1                      # send every n-th sample (slower buses)
    pool: int = 0                            # >0: precompute this many injections per injector and cycle
    series_lot: bool = False                 # the injectors are series parts of one lot (sim_bench.hardware.series_life):
                                             # their own structure and rail-pressure walk, one amplifier chain
    swap_at: int | None = None               # series lot: injector 1's part is swapped at this injection
    settle: int = SETTLE                     # injections of each injector before the targets apply
    ok_within_um: float = math.inf           # no ok published with L_h further off than this (any injection)
    description: str = ""

    def temperature(self, t: float) -> float:
        """Temperature at time t (s) since start, degC."""
        a, b = self.temperature_c
        return a + (b - a) * min(max(t / self.seconds, 0.0), 1.0)

    def truth(self, injector: int, k: int, t: float, rng: np.random.Generator) -> Truth:
        """Truth of injection ``k`` of ``injector`` at time t (s since start); the same for any k."""
        temp = self.temperature(t)
        nu = nu_of_temperature(temp) + self.nu_offset[injector % len(self.nu_offset)]
        nu = float(np.clip(nu, *NU_RANGE))
        lh = self.lh_um[injector % len(self.lh_um)] + self.wear_um * min(t / self.seconds, 1.0)
        mean, std = self.rail_force_n
        f_open = NOMINAL_PRELOAD_N + max(0.0, mean + std * float(rng.standard_normal())) if (mean or std) else NOMINAL_PRELOAD_N
        return Truth(nu, lh, f_open, temp)


# Bus budget assumed by the overload scenario: 500 kbit/s arbitration, 2 Mbit/s data phase.
# One injection of 201 samples is 1 classic header + 14 FD frames of 64 bytes + classic trailer +
# 16-byte SimTruth, and the estimator answers with three frames; with bit stuffing that is about
# 6.4 ms of bus time, i.e. about 155 injections/s for the whole bus. Overload sends twice that.
BUS_INJECTIONS_PER_S = 155.0

SCENARIOS: Registry[Scenario] = Registry("bench", BenchTargets)
register = SCENARIOS.register


_TRACK = BenchTargets(lh_um=0.2, nu_pct=0.3)   # the matched-plant scenarios
register(Scenario("nominal", _TRACK, description="4 injectors at 25 Hz, 40 degC, matched plant"))
register(Scenario("temperature-ramp", _TRACK, temperature_c=(20.0, 100.0), seconds=40.0,
                  description="20 -> 100 degC over the run (N_u 16.2 -> 21 N/V)"))
register(Scenario("wear", _TRACK, wear_um=1.0, seconds=40.0, description="L_h grows by 1 µm over the run"))
register(Scenario("warm-up", _TRACK, temperature_c=(0.0, 100.0), seconds=60.0, rate_hz=5.0,
                  description="cold engine to 100 degC in 60 s, FuelTemperature in the headers, 5 Hz"))
register(Scenario("mismatch", BenchTargets(lh_um=0.5, nu_pct=None), mismatch=True, window_s=150e-6,
                  description="hysteresis plant (±2 V model error), 150 µs sent"))
register(Scenario("faults", _TRACK, faults=FaultRates(drop=0.01, duplicate=0.01, reorder=0.01, corrupt=0.01,
                                                     stall_every_s=5.0, stall_s=0.2),
                  description="1 % each of dropped, duplicated, reordered, corrupted frames; 0.2 s stall every 5 s"))
register(Scenario("multi-injector", _TRACK, injectors=6, rate_hz=16.0, description="6 injectors at 16 Hz"))
register(Scenario("overload", BenchTargets(lh_um=None, nu_pct=None), injectors=4,
                  rate_hz=2 * BUS_INJECTIONS_PER_S / 4, pool=64,
                  description=f"2 x the bus budget ({2 * BUS_INJECTIONS_PER_S:.0f} injections/s): latency and "
                              "memory, not accuracy"))


SWAP_SETTLE = 30   # series lot: the swapped injector is judged again this many injections after the swap
register(Scenario("series-lot", BenchTargets(lh_um=0.15, nu_pct=None), series_lot=True, swap_at=80, rate_hz=10.0,
                  seconds=20.0, window_s=200e-6, settle=60, ok_within_um=0.3,
                  description="4 series parts of one lot (±10 %, one amplifier chain), warming up while the rail "
                              "pressure wanders 28-300 N, injector 1's part swapped at injection 80; default "
                              "configuration (learning on: the four calibrations queue for one background process, "
                              "so targets apply from injection 60); N_u not scored (a learned model's N_u carries its "
                              "calibration's uncertainty)"))


def get(name: str, **overrides) -> Scenario:
    """A scenario by name with optional field overrides (e.g. seconds, drive); KeyError if unknown."""
    base = SCENARIOS[name]
    seconds = overrides.get("seconds")
    if seconds is not None and not (math.isfinite(seconds) and 0 < seconds <= 86_400):
        raise KeyError(f"seconds = {seconds} must be within (0, 86400] s")
    return replace(base, **{k: v for k, v in overrides.items() if v is not None})
