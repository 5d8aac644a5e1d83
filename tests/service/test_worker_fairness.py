"""The daemon's worker under a flood on unused injector ids: the configured injector's injection is
estimated next, the flood's backlog is shed from the flooding injectors, and the health message
counts it. The worker's steps are driven directly (no threads): the order is exact."""

from __future__ import annotations

import time

from estimator.codec.injection_frames import injection_frames
from estimator.codec.records import Codec, EstimatorHealth
from estimator.io.captures import to_message
from estimator.service.config import DaemonConfig
from estimator.service.daemon import ESTABLISHED_AFTER, Daemon, QueueListener
from estimator.service.fair_queue import PENDING_PER_INJECTOR

from ..helpers import measured


def _daemon() -> tuple[Daemon, list[int]]:
    d = Daemon(DaemonConfig(bus="virtual:unused", self_calibration=None))
    d._listener = QueueListener(8192)
    order: list[int] = []
    d.send = lambda frames: order.extend(f.data[0] & 7 for f in frames[:1] if f.arbitration_id == 0x200)
    return d, order


def _send(d: Daemon, codec: Codec, injector: int, counter: int, seed: int, t: float) -> None:
    inj, _ = measured(17.0, 3.0, seed, window_s=100e-6)
    for fr in injection_frames(codec, injector, counter, inj.dt_s, inj.current_a, inj.voltage_v):
        d._listener.on_message_received(to_message(fr, timestamp=t))


def _step(d: Daemon) -> bool:
    while d._ingest_frames(d._listener, wait=False):   # everything that has arrived, in batches
        pass
    taken = d.waiting.take()
    if taken is not None:
        d._estimate(*taken)
    return taken is not None


def test_a_flood_on_unused_ids_waits_behind_an_established_injector():
    """Injector 0 is established (ten injections estimated); a stranger resets ids 1..7 and floods them:
    injector 0's next injection is estimated right after the one in progress."""
    d, order = _daemon()
    codec = Codec()
    for k in range(ESTABLISHED_AFTER):
        _send(d, codec, 0, k, 20 + k, 0.001 * k)
        assert _step(d)
    assert d.tracker.states[0].accepted == ESTABLISHED_AFTER
    for k in range(PENDING_PER_INJECTOR + 2):
        for inj in range(1, 8):
            _send(d, codec, inj, k, 10 + inj, 0.02 + 0.001 * k)
    assert _step(d)                                        # one of the flood is being estimated ...
    _send(d, codec, 0, ESTABLISHED_AFTER, 2, 0.03)        # ... when injector 0's next one arrives
    assert _step(d)
    assert order[ESTABLISHED_AFTER:] == [1, 0], order
    while _step(d):
        pass
    assert order.count(0) == ESTABLISHED_AFTER + 1 and d.ingest.counters.injections_shed >= 7


def test_among_new_injectors_a_flood_waits_behind_itself_and_is_shed_first():
    """A new injector 0 (not yet established) shares the worker fairly with a stranger's new ids:
    it waits one turn of each at most, never the flood's backlog."""
    d, order = _daemon()
    codec = Codec()
    _send(d, codec, 0, 0, 1, 0.0)                         # the configured injector, estimated once
    assert _step(d) and order == [0]
    for k in range(PENDING_PER_INJECTOR + 2):             # a stranger's backlog on ids 1..7
        for inj in range(1, 8):
            _send(d, codec, inj, k, 10 + inj, 0.001 * k)
    assert _step(d)                                        # one of the flood is being estimated ...
    _send(d, codec, 0, 1, 2, 0.01)                        # ... when the next legitimate injection arrives
    assert _step(d)
    while _step(d) and order.count(0) < 2:
        pass
    # at most one turn of each stranger id, then the configured injector: not after the 27 waiting ones
    between = order[1:-1]
    assert order[-1] == 0 and len(between) <= 7 and len(set(between)) == len(between) and 0 not in between, order
    while _step(d):
        pass
    shed = d.ingest.counters.injections_shed
    strangers = [i for i in order if i != 0]
    assert order.count(0) == 2 and len(strangers) + shed == 7 * (PENDING_PER_INJECTOR + 2)
    assert shed >= 7 and all(strangers.count(i) <= PENDING_PER_INJECTOR + 1 for i in range(1, 8))
    health = codec.decode(d.processor.health_frame(len(d.waiting)))
    assert isinstance(health, EstimatorHealth)
    assert health.injections_shed == shed and health.pending_injections == 0 and health.injectors == 8


def test_above_capacity_a_late_injection_is_shed_counted_and_never_published():
    """Injector 0 is established; two injections wait while the worker is a second behind: both are
    older than ``shed_after_ms``, so neither is estimated, both are counted in the health message, and
    the next injection, on time, is estimated as usual."""
    d, order = _daemon()
    codec = Codec()
    for k in range(ESTABLISHED_AFTER):
        _send(d, codec, 0, k, 20 + k, 0.001 * k)
        assert _step(d)
    for k in (ESTABLISHED_AFTER, ESTABLISHED_AFTER + 1):
        _send(d, codec, 0, k, 30 + k, 0.02 + 0.001 * k)
    while d._ingest_frames(d._listener, wait=False):
        pass
    assert d.waiting.take(time.monotonic() + 1.0) is None    # the worker comes back 1 s late
    d._count_expired()
    assert d.ingest.counters.injections_shed == 2 and len(order) == ESTABLISHED_AFTER
    health = codec.decode(d.processor.health_frame(len(d.waiting)))
    assert isinstance(health, EstimatorHealth) and health.injections_shed == 2
    _send(d, codec, 0, ESTABLISHED_AFTER + 2, 40, 0.03)
    assert _step(d) and order[-1] == 0
