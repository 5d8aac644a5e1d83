"""The daemon's capacity: the highest offered rate it holds, swept, with learning and the drive
correction on (the default configuration), the rail pressure cycling 28-300 N. The injectors are
ones the model explains, so no calibration runs during the sweep (``series``: parts it does not,
which learn meanwhile; ``daemon-bench --self-calibration`` measures the latency while they learn).

A rate is *held* when, over a phase of :data:`~estimator.service.latency.WINDOW_S` seconds, the
daemon's own p99 (last frame arrived -> EstimateState sent, from its heartbeat) stays within
:data:`P99_LIMIT_MS`, and every injection offered was estimated: nothing shed, no frame dropped,
nothing rejected. Above capacity the daemon sheds by its rule (``shed_after_ms``); the table shows
how many it shed and the p99 of those it estimated.

The figure must be the daemon's, not the bench's: the injections are sent by a process of their own
that replays frames encoded before the sweep (no plant simulation, no encoding at run time), and the
table gives what every process cost per second of the phase (the daemon with its calibration
process, the sender, the watcher, the loopback hub) and the interface's part of the daemon's: a
process that only receives the bus as the daemon does is timed per frame before the sweep. A rate the sender could not offer on time is
marked bench-limited, and the capacity is then "at least" the highest rate held. The machine's speed
of the hour is the fast simulator's µs per candidate, measured in the same run.

``cpu_share`` holds the daemon (and its calibration process) to that share of one core
(:mod:`sim_bench.hardware.cpu_share`): a bench computer that many times slower.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from estimator.codec.injection_frames import injection_frames
from estimator.codec.records import Codec, EstimateState, EstimatorHealth, EstimatorStatus
from estimator.io.captures import to_message
from estimator.service.bus import open_bus
from estimator.service.latency import STAGES, WINDOW_S
from sim_bench.benches.bench import resolve_bus
from sim_bench.benches.daemon_bench import OutputWatcher, injection_pool, paced, rejected
from sim_bench.hardware.cpu_share import cpu_seconds, cpu_share, descendants
from sim_bench.hardware.procs import DaemonProcess, wait_until

RATES_PER_S = (50.0, 100.0, 200.0, 500.0, 1000.0, 2000.0, 3000.0, 5000.0)
PAST_CAPACITY = 2       # the sweep ends after this many rates in a row not held (the rule shown above capacity)
INJECTORS = 8
P99_LIMIT_MS = 5.0
DRAIN_S = 3.0           # after a phase: what is still waiting is estimated (or shed) within this
ON_TIME = 0.95          # the sender offered at least this share of the rate asked for
START_IN_S = 0.05       # the sender's first injection of a phase, after the phase is asked for


# ---- the bus's own cost: a process that only receives -----------------------------------------
def _receiver_main(bus_spec: str, conn: Any) -> None:
    """Child process: receive every frame on the bus and drop it, until told to stop; what it costs
    is what the daemon pays to the interface before its own work begins."""
    import can

    with open_bus(bus_spec) as bus:
        counted = [0]

        class _Count(can.Listener):
            def on_message_received(self, msg: can.Message) -> None:
                counted[0] += 1
        notifier = can.Notifier(bus, [_Count()], timeout=0.05)   # as the daemon receives
        conn.send("ready")
        try:
            while not (conn.poll(0.2) and conn.recv() is None):
                pass
        finally:
            notifier.stop()
        conn.send(counted[0])


# ---- the sender: a process of its own replaying encoded frames -------------------------------
def _sender_main(bus_spec: str, injections: list[tuple[int, int, list]], conn: Any) -> None:
    """Child process: for each (rate, seconds) received, send ``injections`` in turn on absolute
    deadlines; reply with what was sent (injector, counter, trailer time) and how late it ran."""
    with open_bus(bus_spec) as bus:
        conn.send("ready")
        k = 0
        while True:
            job = conn.recv()
            if job is None:
                return
            rate, seconds = job
            sent: list[tuple[int, int, float]] = []
            t0 = time.monotonic()
            late_s = 0.0
            frames = 0
            c0 = time.process_time()
            for lateness in paced(rate, seconds, START_IN_S):
                late_s = max(late_s, lateness)
                i, c, msgs = injections[k % len(injections)]
                for m in msgs[:-1]:
                    bus.send(m)
                sent.append((i, c, time.monotonic()))
                bus.send(msgs[-1])
                frames += len(msgs)
                k += 1
            conn.send({"sent": sent, "elapsed_s": time.monotonic() - t0 - START_IN_S, "cpu_s": time.process_time() - c0,
                       "late_max_s": late_s, "frames": frames})


def encoded_injections(codec: Codec, injectors: int, seed: int = 7, series: bool = False) -> list[tuple[int, int, list]]:
    """256 injections per injector, interleaved, as python-can messages (counters 0..255, the rail
    pressure cycling; ``series``: series parts): encoded once, replayed by the sender."""
    pool = injection_pool(codec, injectors=injectors, per_injector=32, seed=seed, series=series, cycle_preload=True)
    per = len(pool) // injectors
    out = []
    for c in range(256):
        for i in range(injectors):
            _, m = pool[(c % per) * injectors + i]
            frames = injection_frames(codec, i, c, m.dt_s, m.current_a, m.voltage_v, m.f_open_n)
            out.append((i, c, [to_message(f) for f in frames]))
    return out


class _Watcher(OutputWatcher):
    """The daemon's output: when each EstimateState arrived, its heartbeats (status and health)."""

    def __init__(self, bus: Any, codec: Codec) -> None:
        super().__init__(bus, codec)
        self.received: dict[tuple[int, int], list[float]] = {}   # (injector, counter) -> arrival times
        self.status: EstimatorStatus | None = None
        self.health: EstimatorHealth | None = None
        self.beat = threading.Condition()
        self.beats = 0

    def on_record(self, now: float, rec: Any) -> None:
        if isinstance(rec, EstimateState):
            self.received.setdefault((rec.injector_id, rec.counter), []).append(now)
        elif isinstance(rec, EstimatorHealth):
            self.health = rec
        elif isinstance(rec, EstimatorStatus):
            with self.beat:
                self.status = rec
                self.beats += 1
                self.beat.notify_all()

    def next_beat(self, timeout_s: float) -> bool:
        """Wait for the heartbeat after this call (and its health frame, sent with it)."""
        with self.beat:
            n = self.beats
            ok = self.beat.wait_for(lambda: self.beats > n + 1, timeout_s)
        return ok


def _costs(procs: dict[str, list[int]]) -> dict[str, float]:
    return {k: cpu_seconds(v) for k, v in procs.items()}


def _phase(conn: Any, w: _Watcher, rate: float, seconds: float, procs: dict[str, list[int]]) -> dict:
    st0, h0 = w.status, w.health
    cpu0, t0 = _costs(procs), time.monotonic()
    w.received.clear()      # counters repeat every 256 injections of an injector
    conn.send((rate, seconds))
    job = conn.recv()
    sent = job["sent"]
    shed0 = h0.injections_shed if h0 else 0
    # every injection estimated, or shed (counted), or the drain ends
    wait_until(lambda: sum(len(v) for v in list(w.received.values()))
               + (w.health.injections_shed if w.health else 0) - shed0 >= len(sent), DRAIN_S)
    w.next_beat(5.0)
    wall = time.monotonic() - t0
    cpu1 = _costs(procs)
    st, h = w.status, w.health
    lat = np.array(_match(sent, w.received)) * 1e3
    est = int(lat.size)
    offered_per_s = len(sent) / job["elapsed_s"]
    shed = (h.injections_shed - h0.injections_shed) if h and h0 else 0
    dropped = (st.frames_dropped - st0.frames_dropped) if st and st0 else 0
    rejects = (rejected(st) - rejected(st0)) if st and st0 else 0
    p99 = st.latency_p99_ms if st else math.nan
    cpu = {k: (cpu1[k] - cpu0[k]) / wall for k in procs}
    cpu["sender"] = job["cpu_s"] / job["elapsed_s"]
    bench_limited = offered_per_s < ON_TIME * rate
    return {"rate_per_s": rate, "offered": len(sent), "offered_per_s": offered_per_s, "estimated": est,
            "shed": int(shed), "frames_dropped": int(dropped), "rejected": rejects,
            "daemon_p99_ms": p99, "daemon_stage_p99_ms": {k: getattr(st, f"{k}_p99_ms") for k in STAGES} if st else {},
            "external_p50_ms": float(np.percentile(lat, 50)) if est else math.nan,
            "external_p99_ms": float(np.percentile(lat, 99)) if est else math.nan,
            "frames_per_s": job["frames"] / job["elapsed_s"],
            "sender_late_max_ms": job["late_max_s"] * 1e3, "bench_limited": bench_limited,
            "cpu_per_s": cpu,
            "held": bool(not bench_limited and p99 <= P99_LIMIT_MS and est == len(sent) and shed == 0
                         and dropped == 0 and rejects == 0)}


def _match(sent: list[tuple[int, int, float]], received: dict[tuple[int, int], list[float]]) -> list[float]:
    """Latencies (s): each injection sent (injector, counter, trailer time) paired with the first
    EstimateState of its key after it and before the key's next sending (counters repeat every 256)."""
    by_key: dict[tuple[int, int], list[float]] = {}
    for i, c, t in sent:
        by_key.setdefault((i, c), []).append(t)
    out = []
    for key, times in by_key.items():
        got = sorted(received.get(key, []))
        j = 0
        for n, t in enumerate(times):
            nxt = times[n + 1] if n + 1 < len(times) else float("inf")
            while j < len(got) and got[j] < t:
                j += 1
            if j < len(got) and got[j] < nxt:
                out.append(got[j] - t)
                j += 1
    return out


def capacity(phases: list[dict]) -> tuple[float, bool]:
    """(the highest rate held with every lower rate held too, whether the true capacity may be higher
    because the sender could not offer the next rate)."""
    best, at_least = 0.0, False
    for p in phases:
        if not p["held"]:
            at_least = p["bench_limited"]
            break
        best = p["rate_per_s"]
    else:
        at_least = True
    return best, at_least


def _interface_cost(ctx: Any, bus: str, sender: Any, rate: float, seconds: float = 3.0) -> float:
    """µs of CPU per frame received through the bus interface: a process that only receives, while the
    sender offers ``rate`` for ``seconds`` before the daemon starts (so it perturbs nothing measured)."""
    conn, child = ctx.Pipe()
    receiver = ctx.Process(target=_receiver_main, args=(bus, child), daemon=True)
    receiver.start()
    try:
        if not conn.poll(60) or conn.recv() != "ready":
            raise RuntimeError("the bare receiver did not open the bus")
        c0 = cpu_seconds([receiver.pid])
        sender.send((rate, seconds))
        sender.recv()
        time.sleep(0.2)
        used = cpu_seconds([receiver.pid]) - c0
        conn.send(None)
        frames = conn.recv() if conn.poll(10) else 0
    finally:
        receiver.join(5)
        if receiver.is_alive():
            receiver.kill()
    return used / frames * 1e6 if frames else math.nan


def run(out_dir: Path, rates: tuple[float, ...] = RATES_PER_S, seconds: float = WINDOW_S,
        injectors: int = INJECTORS, bus: str | None = None, share: float | None = None,
        series: bool = False) -> dict:
    """Sweep ``rates`` (injections/s, all injectors) for ``seconds`` each; the report."""
    from sim_bench.benches.speed import yardstick_us_per_candidate

    out_dir = out_dir.resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    codec = Codec()
    encoded = encoded_injections(codec, injectors, series=series)
    bus, hub = resolve_bus(bus, out_dir)
    report: dict[str, Any] = {"bus": bus, "injectors": injectors, "seconds": seconds, "cpu_share": share, "series": series,
                              "p99_limit_ms": P99_LIMIT_MS, "yardstick_us_per_candidate": yardstick_us_per_candidate()}
    ctx = multiprocessing.get_context("fork")
    parent, child = ctx.Pipe()
    sender = ctx.Process(target=_sender_main, args=(bus, encoded, child), daemon=True)
    sender.start()
    try:
        if not parent.poll(60) or parent.recv() != "ready":
            raise RuntimeError("the sender did not open the bus")
        report["interface_us_per_frame"] = _interface_cost(ctx, bus, parent, min(rates[0], 200.0))
        d = DaemonProcess(bus, out_dir / "capacity-daemon.log").start()
        try:
            with open_bus(bus) as b, contextlib.ExitStack() as stack:
                w = _Watcher(b, codec)
                w.start()
                stack.callback(w.join, 2)
                stack.callback(w.stop.set)
                if not d.notify.wait_for("READY=1", 120, d.alive) or not w.next_beat(60):
                    raise RuntimeError(f"daemon did not start: {d.why()}")
                if share is not None:
                    stack.enter_context(cpu_share(d.pid, share))
                # warm-up: every injector's cold start and first learning window, out of the p99's window
                parent.send((min(rates[0], 200.0), 3.0))
                parent.recv()
                time.sleep(1.0)
                procs = {"daemon": descendants(d.pid), "bench": [os.getpid()],
                         "hub": [hub.proc.pid] if hub is not None and hub.proc is not None else []}
                phases = []
                for rate in rates:
                    procs["daemon"] = descendants(d.pid)   # the calibration process, when it has started
                    p = _phase(parent, w, rate, seconds, procs)
                    p["daemon_alive"] = d.alive()
                    phases.append(p)
                    if not p["daemon_alive"] or (len(phases) >= PAST_CAPACITY
                                                 and not any(q["held"] for q in phases[-PAST_CAPACITY:])):
                        break
                report["phases"] = phases
            report["daemon_exit"] = d.stop(timeout=10)
        finally:
            d.stop()
    finally:
        with contextlib.suppress(Exception):
            parent.send(None)
        sender.join(5)
        if sender.is_alive():
            sender.kill()
        if hub is not None:
            hub.stop()
    report["capacity_per_s"], report["capacity_at_least"] = capacity(report["phases"])
    return report


def failures(rep: dict) -> list[str]:
    """What the sweep missed besides its capacity target: a daemon that died or exited non-zero, or,
    above capacity, a p99 of what it estimated beyond the limit (the rule sheds instead)."""
    out = []
    for p in rep["phases"]:
        if not p["daemon_alive"]:
            out.append(f"daemon died at {p['rate_per_s']:.0f}/s")
        if not p["held"] and not p["bench_limited"] and p["daemon_p99_ms"] > P99_LIMIT_MS:
            out.append(f"above capacity at {p['rate_per_s']:.0f}/s: p99 of the estimated {p['daemon_p99_ms']:.1f} ms "
                       f"> {P99_LIMIT_MS:g} ms")
    if rep.get("daemon_exit") not in (0, None):
        out.append(f"daemon exit {rep['daemon_exit']}")
    return out


def format_report(rep: dict) -> str:
    """The sweep as a table."""
    share = f", the daemon at {rep['cpu_share']:g} of a core" if rep.get("cpu_share") else ""
    kind = "series injectors that learn" if rep.get("series") else "injectors"
    lines = [f"daemon capacity on {rep['bus']}: {rep['injectors']} {kind}, learning and drive correction on{share}; {rep['seconds']:g} s per rate; yardstick {rep['yardstick_us_per_candidate']:.1f} µs/candidate",
             f"{'rate/s':>7} {'offered/s':>9} {'estimated':>9} {'shed':>6} {'dropped':>7} {'daemon p99':>10} "
             f"{'ext p50':>8} {'ext p99':>8} {'CPU s/s: daemon':>15} {'receiving':>9} {'sender':>6} {'watcher':>7} "
             f"{'hub':>5}  held"]
    per_frame_s = rep.get("interface_us_per_frame", math.nan) * 1e-6
    for p in rep["phases"]:
        c = p["cpu_per_s"]
        held = "yes" if p["held"] else ("bench-limited" if p["bench_limited"] else "no")
        lines.append(f"{p['rate_per_s']:>7.0f} {p['offered_per_s']:>9.0f} {p['estimated']:>9} {p['shed']:>6} "
                     f"{p['frames_dropped']:>7} {p['daemon_p99_ms']:>10.2f} {p['external_p50_ms']:>8.2f} "
                     f"{p['external_p99_ms']:>8.2f} {c['daemon']:>15.2f} {p['frames_per_s'] * per_frame_s:>9.2f} {c['sender']:>6.2f} {c['bench']:>7.2f} "
                     f"{c['hub']:>5.2f}  {held}")
    at = "at least " if rep["capacity_at_least"] else ""
    lines.append(f"capacity: {at}{rep['capacity_per_s']:.0f} injections/s (p99 <= {rep['p99_limit_ms']:g} ms, "
                 "every injection estimated)")
    lines.append("daemon p99: last frame arrived -> EstimateState sent (heartbeat, the phase's 10 s); ext: the "
                 "sender's trailer -> EstimateState at the watcher (adds the hub); watcher = the bench's own process; "
                 f"receiving = the daemon's frames/s x {rep.get('interface_us_per_frame', math.nan):.0f} µs, what a "
                 "process that only receives the bus as the daemon does paid per frame before the sweep (the "
                 "interface's part of the daemon's CPU)")
    return "\n".join(lines)
