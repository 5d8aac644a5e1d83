"""Bounded by design: the simulator pool (LRU, optional set of periods) and the bus clock."""

from __future__ import annotations

import math

import pytest

from estimator.codec.bus_clock import BusClock
from estimator.ident.config import TrackerConfig
from estimator.ident.simulators import SimulatorPool
from estimator.ident.status import Status
from estimator.ident.tracking.tracker import Tracker

from ..helpers import measured


def test_pool_keeps_at_most_max_size_least_recently_used_out():
    pool = SimulatorPool(max_size=3)
    sims = [pool.get(p * 1e-9) for p in (500, 400, 250)]
    assert pool.get(500e-9) is sims[0]            # a hit refreshes it
    pool.get(200e-9)                              # evicts 400 ns, the least recently used
    assert len(pool) == 3 and pool.built == 4
    assert pool.get(500e-9) is sims[0] and pool.get(250e-9) is sims[2]
    assert pool.get(400e-9) is not sims[1] and pool.built == 5
    for k in range(100):
        pool.get((300 + k) * 1e-9)
    assert len(pool) == 3


def test_configured_periods_refuse_the_others_with_a_reason():
    t = Tracker(TrackerConfig(), pool=SimulatorPool(periods_ns=(500,)))
    inj, _ = measured(17.0, 3.0, 11, window_s=100e-6)
    assert t.update(inj).status != Status.REJECTED
    from dataclasses import replace
    odd = replace(inj, dt_s=400e-9)
    res = t.update(odd)
    assert res.status == Status.REJECTED and "400 ns is not one of the configured 500 ns" in res.reason
    assert len(t.pool) == 1
    assert t.update(replace(inj, dt_s=float("nan"))).status == Status.REJECTED


def test_bus_clock_takes_frame_time_and_guards_a_silent_bus():
    c = BusClock(silent_bus_s=1.0)
    assert c.idle(5.0) is None                   # nothing received yet: no time at all
    assert c.on_frame(100.0, arrived=10.0) == 100.0
    assert c.on_frame(0.0, arrived=10.1) == 100.0          # missing stamp: the current time
    assert c.on_frame(99.0, arrived=10.2) == 100.0         # backwards: never rewinds
    assert c.on_frame(math.nan, arrived=10.3) == 100.0
    assert c.idle(10.9) is None                  # a stalled reader is not a silent bus
    assert c.idle(11.3 + 1e-9) == pytest.approx(101.0)
    assert c.end() == 101.0
    with pytest.raises(ValueError):
        BusClock(0)


def test_new_sample_periods_are_built_within_a_budget_of_bus_time():
    """A flood of ever new sample periods cannot keep the worker building: two simulators at once,
    then one every 10 s of the injections' own time; the rest is refused before any simulation
    (counted), and a replay (the same times) refuses the same. Injections without a time are not
    budgeted (offline files)."""
    from dataclasses import replace

    t = Tracker(TrackerConfig(), pool=SimulatorPool(max_size=4))
    inj, _ = measured(17.0, 3.0, 12, window_s=100e-6)
    statuses = []
    for k, period_ns in enumerate((500, 510, 520, 530)):
        res = t.update(replace(inj, dt_s=period_ns * 1e-9, injector_id=k % 8, time_s=100.0 + 0.1 * k))
        statuses.append(res.status)
    assert [s == Status.REJECTED for s in statuses] == [False, False, True, True]
    assert t.pool.built == 2 and t.pool.over_budget == 2 and "build budget" in res.reason
    later = t.update(replace(inj, dt_s=530e-9, injector_id=3, time_s=110.3))   # 10 s on: one more
    assert later.status != Status.REJECTED and t.pool.built == 3
    untimed = Tracker(TrackerConfig(), pool=SimulatorPool(max_size=4))
    for k, period_ns in enumerate((500, 510, 520, 530)):
        untimed.update(replace(inj, dt_s=period_ns * 1e-9, injector_id=k, time_s=float("nan")))
    assert untimed.pool.built == 4 and untimed.pool.over_budget == 0


def test_garbage_on_a_new_sample_period_is_refused_before_any_simulator_is_built():
    """A stranger's cheap injection (15 samples 8 µs apart: fewer than 40 in the 100 µs window) is
    refused by what needs no simulation; the pool builds nothing for it."""
    import numpy as np

    from estimator.ident.measurement import Injection

    t = Tracker(TrackerConfig(), pool=SimulatorPool(max_size=4))
    rng = np.random.default_rng(3)
    coarse = Injection(np.abs(rng.normal(5.0, 1.0, 15)), rng.normal(50.0, 5.0, 15), 8e-6, 28.0, 3, 0,
                       float("nan"), 1.0)
    res = t.update(coarse)
    assert res.status == Status.REJECTED and "coarsely" in res.reason and t.pool.built == 0
