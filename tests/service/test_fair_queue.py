"""The worker's fair share between injectors (estimator.service.fair_queue)."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.service.fair_queue import FairQueue


def _drain(q: FairQueue, cost: dict[int, float]) -> list:
    got = []
    while (t := q.take()) is not None:
        got.append(t[1])
        q.charge(t[0], cost.get(t[0], 0.001))
    return got


def test_without_overload_items_come_in_arrival_order():
    q: FairQueue[str] = FairQueue()
    for k, inj in enumerate((0, 1, 2, 3)):
        q.put(inj, f"{inj}-{k}")
    assert _drain(q, {}) == ["0-0", "1-1", "2-2", "3-3"] and len(q) == 0


def test_a_flooding_injector_waits_behind_itself():
    """Injector 1 has four injections waiting and keeps sending; injector 0's one injection, arriving
    last, is estimated after the one in progress, not after the backlog."""
    q: FairQueue[str] = FairQueue()
    for k in range(4):
        q.put(1, f"attack-{k}")
    inj, item = q.take()
    assert item == "attack-0"
    q.put(0, "legit")                 # arrives while attack-0 is being estimated
    q.charge(inj, 0.005)
    q.put(1, "attack-4")
    assert q.take() == (0, "legit")


def test_worker_time_is_shared_by_cost_not_by_count():
    """Seven strangers whose injections cost 5 ms against a legitimate 1 ms: over a long backlog each
    gets the same worker time, so the cheap injector is served five times as often."""
    q: FairQueue[tuple[int, int]] = FairQueue(per_injector=1000)
    for k in range(200):
        for inj in range(8):
            q.put(inj, (inj, k))
    cost = {0: 0.001, **{i: 0.005 for i in range(1, 8)}}
    served = _drain(q, cost)[:400]
    time_used = {i: sum(cost[i] for j, _ in served if j == i) for i in range(8)}
    assert max(time_used.values()) - min(time_used.values()) <= 0.005 + 1e-9
    assert sum(1 for j, _ in served if j == 0) > 4 * sum(1 for j, _ in served if j == 1)


def test_idle_time_earns_no_credit():
    """An injector that was quiet while another used the worker joins at the worker's virtual clock:
    it does not get the whole idle time back as a burst of priority."""
    # injector 0 goes first, then alternates with injector 1 by cost, not 40 turns in a row
    q: FairQueue[str] = FairQueue(per_injector=100)
    for k in range(50):
        q.put(1, f"a{k}")
    for _ in range(40):
        inj, _item = q.take()
        q.charge(inj, 0.002)
    for k in range(5):
        q.put(0, f"b{k}")
    seq = []
    for _ in range(6):
        inj, _item = q.take()
        seq.append(inj)
        q.charge(inj, 0.002)
    assert seq == [0, 1, 0, 1, 0, 1]


def test_a_full_injector_sheds_its_own_oldest_never_anothers():
    q: FairQueue[str] = FairQueue(per_injector=2)
    q.put(0, "legit")
    assert q.put(1, "a0") is None and q.put(1, "a1") is None
    assert q.put(1, "a2") == "a0" and q.shed == 1 and len(q) == 3
    assert set(_drain(q, {})) == {"legit", "a1", "a2"}


def test_absurd_settings_are_refused():
    with pytest.raises(ValueError):
        FairQueue(per_injector=0)


def test_known_injectors_go_before_unknown_ones_whatever_the_tags():
    q: FairQueue[str] = FairQueue()
    q.put(1, "new-0")
    inj, _ = q.take()
    q.charge(inj, 0.001)
    q.put(0, "known-0", known=True)
    q.charge(0, 0.0)
    q.put(1, "new-1")
    q.put(2, "new-2")
    q.put(0, "known-1", known=True)
    assert [q.take()[1] for _ in range(4)] == ["known-0", "known-1", "new-1", "new-2"]


def test_an_established_injectors_late_injection_is_shed_and_the_next_taken():
    q: FairQueue[str] = FairQueue(deadline_s=0.004)
    q.put(0, "old", known=True, arrived=0.000)
    q.put(0, "new", known=True, arrived=0.005)
    q.put(1, "stranger", known=False, arrived=0.000)
    assert q.take(now=0.0065) == (0, "new")          # "old" waited 6.5 ms > 4 ms: shed on the way
    assert list(q.expired) == [(0, "old")] and q.shed == 1
    q.charge(0, 0.001)
    assert q.take(now=1.0) == (1, "stranger")        # a new injector is never shed by age
    assert q.take(now=1.0) is None and len(q) == 0


def test_without_a_deadline_nothing_is_shed_by_age():
    q: FairQueue[str] = FairQueue()
    q.put(0, "a", known=True, arrived=0.0)
    assert q.take(now=100.0) == (0, "a") and not q.expired


@pytest.mark.parametrize("offered_per_s", [500.0, 3000.0, 6000.0])
def test_above_capacity_the_rule_estimates_fewer_injections_never_later_ones(offered_per_s):
    """A seeded simulation of the worker (no wall clock): eight established injectors at ``offered_per_s``
    in all, each estimate costing 0.4-1.2 ms (a capacity near 1,250/s). Whatever the load, every
    injection estimated waited at most the deadline; the queue stays bounded; every injection is
    estimated, shed or still waiting; every injector keeps its share; below capacity (random arrivals,
    40 % busy) at most 1 % is shed."""
    rng = np.random.default_rng(5)
    deadline = 0.004
    q: FairQueue[tuple[int, float]] = FairQueue(deadline_s=deadline)
    arrivals = sorted((float(t), int(rng.integers(8))) for t in rng.uniform(0.0, 2.0, int(offered_per_s * 2.0)))
    now, k, waits, done, overflow, depth = 0.0, 0, [], {i: 0 for i in range(8)}, 0, 0
    while k < len(arrivals) or len(q):
        while k < len(arrivals) and arrivals[k][0] <= now:
            t, inj = arrivals[k]
            overflow += q.put(inj, (inj, t), known=True, arrived=t) is not None
            k += 1
        depth = max(depth, len(q))
        taken = q.take(now)
        if taken is None:
            if k < len(arrivals):
                now = arrivals[k][0]
            continue
        inj, (_, t) = taken
        waits.append(now - t)
        cost = float(rng.uniform(0.0004, 0.0012))
        now += cost
        q.charge(inj, cost)
        done[inj] += 1
    assert max(waits) <= deadline
    assert depth <= 8 * q.per_injector
    assert sum(done.values()) + len(q.expired) + overflow == len(arrivals)
    estimated = sum(done.values())
    assert min(done.values()) >= 0.08 * estimated       # fair: each of 8 keeps (about) its eighth
    if offered_per_s < 1000.0:
        assert len(q.expired) <= 0.01 * len(arrivals) and overflow == 0
    else:
        assert estimated >= 0.8 * 2.0 * 1250.0 / 1.5     # the worker stays busy at its capacity
