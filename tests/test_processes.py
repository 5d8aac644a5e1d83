"""Real processes on a real bus (the loopback hub): restart after SIGKILL, replay == live, candump
format through ``python -m cantools decode``, and the three-process bench."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import can
import pytest

from estimator.codec.injection_frames import injection_frames
from estimator.codec.records import Codec, EstimateQuality, EstimateState, EstimatorStatus
from estimator.service.bus import open_bus, to_frame, to_message
from sim_bench.hub import Hub

from .conftest import REPO
from .helpers import measured

pytestmark = pytest.mark.timeout(300)


@pytest.fixture()
def hub(tmp_path):
    with Hub(log_path=tmp_path / "hub.log") as h:
        yield h


def start_daemon(hub, state_dir, tmp_path, name="daemon"):
    cfg = tmp_path / "e.toml"
    cfg.write_text("[estimator]\npersist_period_s = 0.2\n")
    return subprocess.Popen([sys.executable, "-m", "estimator", "run", "--bus", hub.spec, "--state-dir", str(state_dir),
                             "--config", str(cfg)], cwd=REPO, stderr=open(tmp_path / f"{name}.log", "w"))


def wait_ready(bus, codec, timeout=60):
    """Wait for a heartbeat of a freshly started daemon (a killed one's may still be queued)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        m = bus.recv(0.1)
        rec = codec.decode(to_frame(m)) if m is not None else None
        if isinstance(rec, EstimatorStatus) and rec.uptime_s == 0 and rec.accepted == 0:
            return
    raise AssertionError("daemon never sent a heartbeat")


def _pump(bus, codec, out, timeout, done, capture=None):
    """Receive until ``done(out)`` or timeout, collecting EstimateState/Quality by (injector, counter)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end and not done(out):
        m = bus.recv(0.1)
        if m is None:
            continue
        if capture is not None:
            capture.on_message_received(m)
        rec = codec.decode(to_frame(m))
        if isinstance(rec, (EstimateState, EstimateQuality)):
            out.setdefault((rec.injector_id, rec.counter), {})[type(rec).__name__] = rec


def feed_and_collect(bus, codec, injections, injector=0, first_counter=0, capture=None):
    out = {}
    for k, inj in enumerate(injections):
        key = (injector, first_counter + k)
        for fr in injection_frames(codec, injector, first_counter + k, inj.dt_s, inj.current_a, inj.voltage_v):
            bus.send(to_message(fr))
        # the state frame, then the quality frame that follows it
        _pump(bus, codec, out, 30, lambda o: key in o, capture)
        _pump(bus, codec, out, 5, lambda o: len(o.get(key, {})) >= 2, capture)
    return out


def test_restart_after_sigkill_resumes_from_persisted_state(hub, tmp_path):
    codec = Codec()
    state = tmp_path / "state"
    injs = [measured(17.6, 4.4, 3000 + k, window_s=100e-6)[0] for k in range(9)]
    with open_bus(hub.spec) as bus:
        d = start_daemon(hub, state, tmp_path)
        try:
            wait_ready(bus, codec)
            before = feed_and_collect(bus, codec, injs[:8])
            assert len(before) == 8
            time.sleep(0.6)                       # at least one periodic persist
            d.send_signal(signal.SIGKILL)
            d.wait(timeout=5)
            assert (state / "estimator-state.json").exists()
            d = start_daemon(hub, state, tmp_path, "daemon2")
            wait_ready(bus, codec)
            after = feed_and_collect(bus, codec, injs[8:], first_counter=8)
        finally:
            d.send_signal(signal.SIGTERM)
            d.wait(timeout=5)
    last = before[(0, 7)]["EstimateState"]
    nxt = after[(0, 8)]
    assert nxt["EstimateQuality"].evaluations < 50            # warm start from the persisted state
    assert abs(nxt["EstimateState"].lh_um - last.lh_um) < 0.1
    assert nxt["EstimateQuality"].sigma_lh_um < 0.05          # the accumulated information survived
    assert "restored the state of 1 injector" in (tmp_path / "daemon2.log").read_text()


def test_replay_of_the_capture_reproduces_the_live_estimates_and_cantools_decodes_it(hub, tmp_path):
    codec = Codec()
    capture = tmp_path / "capture.log"
    injs = [measured(16.8, 2.7, 3100 + k, window_s=100e-6)[0] for k in range(5)]
    writer = can.CanutilsLogWriter(str(capture), channel="vcan0")
    with open_bus(hub.spec) as bus:
        d = start_daemon(hub, tmp_path / "st", tmp_path)
        try:
            wait_ready(bus, codec)

            class Tee:   # record what we send, too: the hub does not echo our own frames
                def send(self, msg):
                    msg.timestamp = time.time()
                    writer.on_message_received(msg)
                    bus.send(msg)

                def recv(self, t):
                    return bus.recv(t)
            live = feed_and_collect(Tee(), codec, injs, injector=4, capture=writer)
            t_end = time.monotonic() + 0.5           # the last prediction and a heartbeat or two
            while time.monotonic() < t_end:
                m = bus.recv(0.05)
                if m is not None:
                    writer.on_message_received(m)
        finally:
            d.send_signal(signal.SIGTERM)
            d.wait(timeout=5)
            writer.stop()
    out = tmp_path / "replay.log"
    jl = tmp_path / "replay.jsonl"
    r = subprocess.run([sys.executable, "-m", "estimator", "replay", str(capture), "--out", str(out), "--json", str(jl)],
                       cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    replayed = {}
    for msg in can.LogReader(str(out)):
        rec = codec.decode(to_frame(msg))
        if isinstance(rec, (EstimateState, EstimateQuality)):
            replayed.setdefault((rec.injector_id, rec.counter), {})[type(rec).__name__] = rec
    assert set(replayed) == set(live) and len(live) == 5
    for key in live:
        assert replayed[key]["EstimateState"] == live[key]["EstimateState"]
        assert replayed[key]["EstimateQuality"] == live[key]["EstimateQuality"]
    assert len(jl.read_text().splitlines()) == 5
    # the candump -L capture decodes with cantools' own command line
    dec = subprocess.run([sys.executable, "-m", "cantools", "decode", str(REPO / "dbc" / "injector.dbc")],
                         stdin=open(capture), capture_output=True, text=True, timeout=120)
    assert dec.returncode == 0, dec.stderr
    assert dec.stdout.count("EstimateState(") == 5 and "IdleStroke:" in dec.stdout
    assert "InjectionSamples(" in dec.stdout and "EstimatorStatus(" in dec.stdout


def test_bench_three_processes_converge_and_stop_cleanly(tmp_path):
    out = tmp_path / "bench"
    r = subprocess.run([sys.executable, "-m", "sim_bench", "bench", "--scenario", "nominal", "--seconds", "7",
                        "--out", str(out), "--quiet", "--no-plots"], cwd=REPO, capture_output=True, text=True,
                       timeout=240)
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads((out / "bench-nominal.json").read_text())["score"]
    assert s["settled"] > 0 and s["max_abs_lh_um"] <= 0.2
    assert s["daemon_exit"] == 0 and s["daemon_stop_s"] < 2.0
    assert s["node"]["injections"] >= 4 * 30 and s["accepted"] >= 4 * 30
    assert (out / "capture.log").stat().st_size > 0
