"""Shared test helpers: simulated measurements as the estimator receives them."""

from __future__ import annotations

import numpy as np

from estimator.ident.measurement import Injection
from sim_bench.plant import Plant, PlantConfig

_PLANTS: dict[tuple, Plant] = {}


def measured(nu: float, lh_um: float, seed: int, mismatch: bool = False, f_open_n: float = 28.0,
             window_s: float = 150e-6, **kw) -> tuple[Injection, object]:
    """One noisy, quantised injection from the simulated plant, and the plant's Measurement (truth)."""
    key = (mismatch, window_s, tuple(sorted(kw.items())))
    if key not in _PLANTS:
        _PLANTS[key] = Plant(PlantConfig(mismatch=mismatch, window_s=window_s, **kw))
    m = _PLANTS[key].measure(nu, lh_um * 1e-6, f_open_n, np.random.default_rng(seed))
    return Injection(m.current_a, m.voltage_v, m.dt_s, m.f_open_n), m
