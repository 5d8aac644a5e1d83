"""The daemon in-process on python-can's virtual bus: injections in, estimates out."""

from __future__ import annotations

import threading
import time
import uuid

import can
import pytest

from estimator.codec.injection_frames import injection_frames
from estimator.codec.records import (
    Codec,
    Command,
    EstimateQuality,
    EstimateState,
    EstimatorCommand,
    EstimatorHealth,
    EstimatorStatus,
    ValvePrediction,
)
from estimator.ident.tracking.tracker import Tracker
from estimator.io.captures import to_frame, to_message
from estimator.service.config import DaemonConfig
from estimator.service.daemon import Daemon
from estimator.service.state_store import load_states

from ..helpers import COLD_MIN_EVALUATIONS, measured


@pytest.fixture()
def running(tmp_path):
    channel = f"test-{uuid.uuid4().hex[:8]}"
    # the test's own reference estimates share the interpreter with the daemon's worker, which can hold
    # an injection past the default 100 ms on a loaded machine: staleness has its own test below
    cfg = DaemonConfig(bus=f"virtual:{channel}", state_dir=tmp_path, persist_period_s=0.2, stale_after_ms=10_000.0)
    d = Daemon(cfg)
    t = threading.Thread(target=d.run, daemon=True)
    t.start()
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    ready = collect(bus, Codec(), lambda g: any(isinstance(r, EstimatorStatus) for r in g), timeout=60.0)
    assert any(isinstance(r, EstimatorStatus) for r in ready), "daemon never sent a heartbeat"
    yield d, bus, tmp_path
    d.stop.set()
    t.join(timeout=3)
    bus.shutdown()
    assert not t.is_alive()


def collect(bus, codec, until, timeout=10.0):
    got = []
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        msg = bus.recv(0.05)
        if msg is None:
            continue
        rec = codec.decode(to_frame(msg))
        if rec is not None:
            got.append(rec)
        if until(got):
            break
    return got


def wait_for(bus, cond, timeout=10.0) -> bool:
    """Until ``cond()`` holds, checked on every frame the daemon sends (its heartbeat ticks at 10 Hz)."""
    t_end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > t_end:
            return False
        bus.recv(0.2)
    return True


def test_injections_in_estimates_out_match_the_core(running):
    _d, bus, state_dir = running
    codec = Codec()
    reference = Tracker()
    expected = []
    got = []
    for k in range(6):
        inj, _ = measured(17.4, 3.6, 2000 + k, window_s=100e-6)
        for fr in injection_frames(codec, 1, k, inj.dt_s, inj.current_a, inj.voltage_v, 28.0, 40.0):
            bus.send(to_message(fr))
        t_trailer = time.time()   # the virtual bus stamps the trailer at send: the daemon's time of this injection
        # the core on the same (quantised) samples
        q = codec.layout
        c_raw, v_raw = q.to_raw(inj.current_a, inj.voltage_v)
        from estimator.ident.measurement import Injection
        expected.append(reference.update(Injection(c_raw * q.current_scale, v_raw * q.voltage_scale, inj.dt_s,
                                                   28.0, 1, k, 40.0, t_trailer)))
        # one injection at a time: a burst of a new injector's injections behind its cold start would
        # exceed what may wait per injector and be shed (fair_queue's own tests), not what this checks
        got += collect(bus, codec, lambda g, k=k: any(isinstance(r, ValvePrediction) and r.counter == k for r in g),
                       timeout=60.0)
    states = [r for r in got if isinstance(r, EstimateState)]
    quality = [r for r in got if isinstance(r, EstimateQuality)]
    assert [s.counter for s in states] == list(range(6))
    for s, q, e in zip(states, quality, expected):
        assert s.injector_id == 1 and s.status == 0
        assert s.nu_n_per_v == pytest.approx(e.nu_n_per_v, abs=0.0005)
        assert s.lh_um == pytest.approx(e.lh_m * 1e6, abs=0.001)
        assert q.evaluations == e.evaluations
    assert abs(states[-1].lh_um - 3.6) < 0.1
    status = collect(bus, codec, lambda g: any(isinstance(r, EstimatorStatus) for r in g))
    st = [r for r in status if isinstance(r, EstimatorStatus)][-1]
    assert st.accepted == 6 and st.latency_p99_ms > 0
    path = state_dir / "estimator-state.json"
    assert wait_for(bus, lambda: 1 in load_states(path)[0] and load_states(path)[0][1].accepted == 6)
    saved, problem = load_states(path)
    assert problem is None and saved[1].accepted == 6


def test_reset_command_and_bad_frames_do_not_stop_it(running):
    d, bus, _ = running
    codec = Codec()
    inj, _ = measured(17.0, 2.0, 2100, window_s=100e-6)
    for fr in injection_frames(codec, 2, 0, inj.dt_s, inj.current_a, inj.voltage_v):
        bus.send(to_message(fr))
    first = collect(bus, codec, lambda g: all(any(isinstance(r, t) for r in g) for t in (ValvePrediction, EstimateQuality)))
    q0 = [r for r in first if isinstance(r, EstimateQuality)][-1]
    assert 2 in d.tracker.states
    bus.send(to_message(codec.encode(EstimatorCommand(2, Command.RESET))))
    bus.send(can.Message(arbitration_id=0x101, data=b"\x01\x02", is_fd=True, is_extended_id=False))  # malformed
    bus.send(can.Message(arbitration_id=0x555, data=b"\x00" * 8, is_extended_id=False))            # unknown
    assert wait_for(bus, lambda: d.ingest.counters.frames_malformed == 1 and 2 not in d.tracker.states)
    assert 2 not in d.tracker.states
    assert d.ingest.counters.frames_malformed == 1
    for fr in injection_frames(codec, 2, 1, inj.dt_s, inj.current_a, inj.voltage_v):
        bus.send(to_message(fr))
    got = collect(bus, codec, lambda g: any(isinstance(r, EstimateQuality) for r in g))
    q = [r for r in got if isinstance(r, EstimateQuality)][-1]
    # the same injection again: after the reset a cold start exactly as the first time (a warm update
    # would cost fewer simulations and report a smaller sigma, the two injections' information)
    assert (q.evaluations, q.sigma_lh_um, q.cost_uvs) == (q0.evaluations, q0.sigma_lh_um, q0.cost_uvs)
    assert q.evaluations >= COLD_MIN_EVALUATIONS


def test_an_estimate_published_late_is_stale_never_ok(tmp_path):
    """The worker held on one injection until the heartbeat (every 0.1 s, its own thread) has ticked
    three times after that injection's trailer went out (stale_after_ms = 100): that injection's
    estimate goes out as stale, is counted, and the next one, on time, is ok again."""
    channel = f"test-{uuid.uuid4().hex[:8]}"
    # the test sends from the daemon's interpreter: on a loaded machine a header and its trailer went out
    # more than the default 50 ms apart, and counter 5 was rejected by the assembly timeout (its own tests)
    d = Daemon(DaemonConfig(bus=f"virtual:{channel}", stale_after_ms=100.0, status_period_s=0.1,
                            assembly_timeout_ms=2000.0))
    tracker = d.processor.tracker
    real_update = tracker.update
    release = threading.Event()
    stalled = {"n": 0}

    def held_update(inj, *args):
        res = real_update(inj, *args)
        if inj.counter == 3:
            stalled["n"] += 1
            release.wait(30.0)     # the worker is behind until the test has seen time pass on the bus
        return res
    tracker.update = held_update
    t = threading.Thread(target=d.run, daemon=True)
    t.start()
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    codec = Codec()
    try:
        assert collect(bus, codec, lambda g: any(isinstance(r, EstimatorStatus) for r in g), timeout=60.0)
        states = []
        for k in range(6):
            inj, _ = measured(17.4, 3.6, 3000 + k, window_s=100e-6)
            for fr in injection_frames(codec, 2, k, inj.dt_s, inj.current_a, inj.voltage_v, 28.0, 40.0):
                bus.send(to_message(fr))
            if k == 3:   # three heartbeats after the trailer: at least 0.2 s of the worker held
                beats = collect(bus, codec, lambda g: sum(isinstance(r, EstimatorStatus) for r in g) >= 3,
                                timeout=30.0)
                states += [r for r in beats if isinstance(r, EstimateState)]
                release.set()
            got = collect(bus, codec, lambda g: any(isinstance(r, EstimateState) for r in g), timeout=30.0)
            states += [r for r in got if isinstance(r, EstimateState)]
        words = {r.counter: codec.status_of(r.status).value for r in states}
        assert stalled["n"] == 1 and words[3] == "stale" and words[5] == "ok", words
        assert d.ingest.counters.stale == 1
        health = collect(bus, codec, lambda g: any(isinstance(r, EstimatorHealth) for r in g), timeout=30.0)
        assert [r for r in health if isinstance(r, EstimatorHealth)][-1].stale == 1
    finally:
        release.set()
        d.stop.set()
        t.join(timeout=5)
        bus.shutdown()


def test_the_drive_corrections_deferred_work_runs_while_the_worker_is_idle(running):
    """The correction of each injection goes out at once; its table and derivative refreshes wait for
    the worker's idle time, and an idle worker does them (not only before the injector's next one)."""
    from estimator.codec.records import DriveCorrection

    d, bus, _ = running
    codec = Codec()
    assert d.processor.compensator is not None and d.processor.compensator.deferred
    valid = []
    for k in range(20):   # a new model's table is complete after four corrections (four passes of four rows)
        inj, _ = measured(17.2, 3.1, 2300 + k, window_s=100e-6)
        for fr in injection_frames(codec, 3, k, inj.dt_s, inj.current_a, inj.voltage_v, 28.0, 40.0):
            bus.send(to_message(fr))
        got = collect(bus, codec, lambda g: any(isinstance(r, DriveCorrection) for r in g))
        valid += [r for r in got if isinstance(r, DriveCorrection) and r.state == 1]
        if len(valid) == 4:
            break
    assert len(valid) == 4, f"{len(valid)} valid corrections in 20 injections"
    assert wait_for(bus, lambda: not d.processor.has_background)
    assert d.processor.compensator.last(3).table    # the last pass, done only by the idle worker


def test_the_daemons_own_process_takes_its_startup_heap_out_of_the_collector(tmp_path):
    """``run(freeze_heap=True)`` (what ``estimator run`` does): the objects built up to the warm-up leave
    the collector's generations, so a full collection no longer walks them on the worker's time."""
    import gc

    gc.unfreeze()
    channel = f"test-{uuid.uuid4().hex[:8]}"
    d = Daemon(DaemonConfig(bus=f"virtual:{channel}", state_dir=tmp_path, self_calibration=None))
    t = threading.Thread(target=d.run, kwargs={"freeze_heap": True}, daemon=True)
    t.start()
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        ready = collect(bus, Codec(), lambda g: any(isinstance(r, EstimatorStatus) for r in g), timeout=60.0)
        assert any(isinstance(r, EstimatorStatus) for r in ready), "daemon never sent a heartbeat"
        assert gc.get_freeze_count() > 10_000     # the modules, the compiled kernels, the tracker
    finally:
        d.stop.set()
        t.join(timeout=3)
        bus.shutdown()
        gc.unfreeze()
    assert not t.is_alive()
