"""The worker's fair share between injectors (estimator.service.fair_queue)."""

from __future__ import annotations

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
