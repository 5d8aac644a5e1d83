"""Bounded by design: the simulator pool (LRU, optional set of periods) and the bus clock."""

from __future__ import annotations

import math

import pytest

from estimator.codec.bus_clock import BusClock
from estimator.ident.config import TrackerConfig
from estimator.ident.simulators import SimulatorPool
from estimator.ident.status import Status
from estimator.ident.tracker import Tracker

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
