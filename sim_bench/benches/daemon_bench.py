"""Benchmarks of the daemon: ingest/decode rate, end-to-end latency, 2x overload.

The feeder sends precomputed injections (no plant simulation at run time) on absolute deadlines;
the daemon runs as its own process on vcan0 or the loopback hub. Latency is measured twice: by the
daemon itself (arrival of an injection's last frame -> its EstimateState sent, the heartbeat's
LatencyP99) and from outside (feeder's trailer send -> EstimateState received, which adds the bus).
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from estimator.codec.assembler import Completed
from estimator.codec.ingest import Ingest
from estimator.codec.injection_frames import injection_frames
from estimator.codec.records import Codec, EstimateState, EstimatorStatus, ModelCalibration
from estimator.io.captures import to_frame, to_message
from estimator.model.parameters import NOMINAL_PRELOAD_N
from estimator.service.bus import open_bus
from estimator.service.latency import STAGES, WINDOW_S
from sim_bench.benches.bench import resolve_bus
from sim_bench.benches.targets import missed
from sim_bench.hardware import series_part
from sim_bench.hardware.plant import Measurement, Plant, PlantConfig
from sim_bench.hardware.procs import DaemonProcess, rss_mb, wait_until

SERIES_PRELOADS_N = (NOMINAL_PRELOAD_N, 60.0, 100.0, 150.0, 220.0, 300.0)   # the rail pressure cycling (series pool)


def injection_pool(codec: Codec, injectors: int = 4, per_injector: int = 32, seed: int = 7,
                   series: bool = False, cycle_preload: bool | None = None) -> list[tuple[int, Measurement]]:
    """Precomputed injections (injector id, the plant's measurement), injectors interleaved; frames and
    counters are made at send time. Idle strokes 1.5-7.1 µm, inside the model's range for any count
    of injectors. ``cycle_preload``: the preload force cycling as for series parts (default: with them).
    ``series``: each injector a seeded series part (structure ±10 %, which the nominal model cannot
    explain), 200 µs sent, the preload force cycling through 28-300 N: what makes the daemon's
    self-calibration collect and calibrate."""
    rng = np.random.default_rng(seed)
    plants = [Plant(PlantConfig(window_s=200e-6), series_part.draw(rng).params) if series else Plant(PlantConfig())
              for _ in range(injectors)]
    cycle = series if cycle_preload is None else cycle_preload
    pool = []
    for k in range(per_injector):
        for i in range(injectors):
            f = SERIES_PRELOADS_N[k % len(SERIES_PRELOADS_N)] if cycle else NOMINAL_PRELOAD_N
            m = plants[i].measure(16.5 + 0.4 * i, (1.5 + 1.7 * (i % 4) + 0.5 * (i // 4)) * 1e-6, f, rng)
            pool.append((i, m))
    return pool


def rejected(st: EstimatorStatus) -> int:
    """Injections the daemon rejected so far (CRC, missing frames, timeout, invalid), from its heartbeat."""
    return int(st.rejected_crc + st.rejected_missing + st.rejected_timeout + st.rejected_invalid)


def ingest_rate(seconds: float = 2.0) -> dict:
    """Frames per second through decode + reassembly (one core, no estimation)."""
    codec = Codec()
    frames = []
    for n, (i, m) in enumerate(injection_pool(codec, 4, 8)):
        frames += injection_frames(codec, i, n % 256, m.dt_s, m.current_a, m.voltage_v)
    ing = Ingest(codec)
    count = completed = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for f in frames:
            completed += sum(isinstance(e, Completed) for e in ing.feed(f, 0.0))
        count += len(frames)
    dt = time.perf_counter() - t0
    c = ing.counters
    rejected = c.rejected_crc + c.rejected_missing + c.rejected_timeout + c.rejected_invalid
    return {"frames_per_s": count / dt, "frames": count, "completed": completed, "rejected": rejected}


class OutputWatcher(threading.Thread):
    """Receives the daemon's output on a bus of the bench's own and hands each decoded record to
    :meth:`on_record` with the time it arrived (undecodable frames are skipped); ``stop`` ends it."""

    def __init__(self, bus: Any, codec: Codec) -> None:
        super().__init__(daemon=True)
        self.bus, self.codec = bus, codec
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            m = self.bus.recv(0.05)
            if m is None:
                continue
            now = time.monotonic()
            try:
                rec = self.codec.decode(to_frame(m))
            except Exception:
                continue
            self.on_record(now, rec)

    def on_record(self, now: float, rec: Any) -> None:
        """One record of the daemon's output, received at ``now`` (monotonic s)."""


class _Watcher(OutputWatcher):
    def __init__(self, bus: Any, codec: Codec) -> None:
        super().__init__(bus, codec)
        self.sent: dict[tuple[int, int], float] = {}
        self.latency: list[float] = []
        self.status: EstimatorStatus | None = None
        self.estimates = 0
        self.calibrations: list[tuple[float, ModelCalibration]] = []
        self.got_status = threading.Event()

    def on_record(self, now: float, rec: Any) -> None:
        if isinstance(rec, EstimateState):
            self.estimates += 1
            t = self.sent.pop((rec.injector_id, rec.counter), None)
            if t is not None:
                self.latency.append(now - t)
        elif isinstance(rec, EstimatorStatus):
            self.status = rec
            self.got_status.set()
        elif isinstance(rec, ModelCalibration):
            self.calibrations.append((now, rec))


@contextlib.contextmanager
def watched_daemon(bus: str, codec: Codec, log: Path, config: Path | None = None) -> Iterator[tuple[DaemonProcess, Any, _Watcher]]:
    """A daemon on ``bus`` (``config``: its configuration file), ready (READY=1 and a heartbeat), with a
    bus of the bench's own and a watcher of the daemon's output on it; on exit the watcher ends, then
    the daemon (stop it earlier to collect its exit code)."""
    d = DaemonProcess(bus, log, config=config).start()
    try:
        with open_bus(bus) as b:
            w = _Watcher(b, codec)
            w.start()
            try:
                if not d.notify.wait_for("READY=1", 120, d.alive) or not w.got_status.wait(60):
                    raise RuntimeError(f"daemon did not start: {d.why()}")
                yield d, b, w
            finally:
                w.stop.set()
                w.join(timeout=2)
    finally:
        d.stop()


def paced(rate: float, seconds: float, start_in_s: float) -> Iterator[float]:
    """Absolute deadlines ``rate`` per second for ``seconds``, starting ``start_in_s`` from now: sleeps
    until each is due and yields how late it is served (s, 0 when on time)."""
    period = 1.0 / rate
    t0 = time.monotonic() + start_in_s
    n = 0
    while n * period < seconds:
        due = t0 + n * period
        now = time.monotonic()
        if due > now:
            time.sleep(due - now)
        yield max(0.0, now - due)
        n += 1


def _feed(bus, codec: Codec, pool, rate: float, seconds: float, watcher: _Watcher) -> dict:
    counters = [0] * 8
    k = 0
    late = 0
    for lateness in paced(rate, seconds, 0.1):
        late += lateness > 1.0 / rate
        i, m = pool[k % len(pool)]
        c = counters[i]
        counters[i] = (c + 1) % 256
        frames = injection_frames(codec, i, c, m.dt_s, m.current_a, m.voltage_v, m.f_open_n)
        for f in frames[:-1]:
            bus.send(to_message(f))
        watcher.sent[(i, c)] = time.monotonic()
        bus.send(to_message(frames[-1]))
        k += 1
    return {"offered": k, "offered_per_s": k / seconds, "feeder_late": late}


def _warm_up(b: Any, codec: Codec, pool: list, rate: float, w: _Watcher, self_calibration: bool) -> None:
    """The first injection of each injector is a cold start (grid search, ~60 ms); the heartbeat's p99
    covers the last 10 s, so the measured phases start after it. With learning: only the cold starts (a
    calibration needs a window of injections and must run while the latency is measured, not before);
    then the cold starts leave the p99's window."""
    if self_calibration:
        injectors = len({i for i, _ in pool})
        _feed(b, codec, pool, rate, injectors / rate, w)
        wait_until(lambda: w.estimates >= injectors, 60.0)
        time.sleep(WINDOW_S + 0.5)
    else:
        _feed(b, codec, pool, rate, 3.0, w)
        time.sleep(0.5)


def _phase(b: Any, codec: Codec, pool: list, rate: float, seconds: float, w: _Watcher,
           d: DaemonProcess) -> dict:
    """One measured phase at ``rate`` injections/s for ``seconds``: the latency as the listener saw it
    and as the daemon's heartbeat reports it (its stages too), drops, rejections, memory, learning."""
    w.latency.clear()
    e0 = w.estimates
    t_phase = time.monotonic()
    st0 = w.status
    peak = 0.0
    stop_rss = threading.Event()

    def sample_rss() -> None:
        nonlocal peak
        while not stop_rss.wait(0.2):
            peak = max(peak, rss_mb(d.pid))
    th = threading.Thread(target=sample_rss, daemon=True)
    th.start()
    fed = _feed(b, codec, pool, rate, seconds, w)
    # the queue drained (or what overflowed is given up on), then a heartbeat after it: its p99 covers
    # the phase's last 10 s
    target = e0 + fed["offered"]
    wait_until(lambda: w.estimates >= target, 5.0)
    w.got_status.clear()
    w.got_status.wait(2.0)
    stop_rss.set()
    st = w.status
    lat = np.array(w.latency) * 1e3
    return {
        **fed, "estimated": w.estimates - e0,
        "external_latency_p50_ms": float(np.percentile(lat, 50)) if lat.size else math.nan,
        "external_latency_p99_ms": float(np.percentile(lat, 99)) if lat.size else math.nan,
        "daemon_latency_p99_ms": st.latency_p99_ms if st else math.nan,
        "daemon_stage_p99_ms": {k: getattr(st, f"{k}_p99_ms") if st else math.nan for k in STAGES},
        "external_latency_ms": [round(float(v), 4) for v in lat],
        "frames_dropped": (st.frames_dropped - st0.frames_dropped) if st and st0 else 0,
        "rejected": (rejected(st) - rejected(st0)) if st and st0 else 0,
        "queue_depth_end": st.queue_depth if st else 0, "daemon_rss_peak_mb": peak,
        "daemon_alive": d.alive(),
        "calibration_states": [codec.calibration_state(c.state) for t, c in w.calibrations if t >= t_phase],
        "adopted_injectors": sorted({c.injector_id for _, c in w.calibrations
                                     if codec.calibration_state(c.state) == "adopted"}),
    }


def failures(ing: dict, rep: dict) -> list[str]:
    """The targets missed (``daemon-bench`` or ``daemon-bench --self-calibration`` in
    :data:`sim_bench.benches.targets.TARGETS`): at the rate asked for, not in the overload phase."""
    if rep.get("self_calibration"):
        return missed("daemon-bench --self-calibration", {
            "ingest_frames_per_s": ing["frames_per_s"],
            "learning_p99_ms": rep["nominal"]["daemon_latency_p99_ms"],
            "adopted_p99_ms": rep.get("adopted", {}).get("daemon_latency_p99_ms", math.nan)})
    return missed("daemon-bench", {"ingest_frames_per_s": ing["frames_per_s"],
                                   "daemon_p99_ms": rep["nominal"]["daemon_latency_p99_ms"],
                                   "external_p99_ms": rep["nominal"]["external_latency_p99_ms"]})


def run_latency_and_overload(out_dir: Path, rate: float = 200.0, seconds: float = 10.0,
                             overload_factor: float = 2.0, bus: str | None = None,
                             self_calibration: bool = False) -> dict:
    """Latency at ``rate`` injections/s, then ``overload_factor`` x that; returns the report.
    ``self_calibration``: series injectors and the daemon's self-calibration on, so that its
    background calibrations run while the latency is measured (the report counts them)."""
    from sim_bench.benches.speed import yardstick_fields, yardstick_us_per_candidate

    out_dir = out_dir.resolve()   # the daemon runs in another working directory
    out_dir.mkdir(parents=True, exist_ok=True)
    codec = Codec()
    pool = injection_pool(codec, series=self_calibration)
    before = yardstick_us_per_candidate(0.5)   # the machine's speed of the hour, before and after
    bus, hub = resolve_bus(bus, out_dir)
    report: dict = {"bus": bus, "rate_per_s": rate, "seconds": seconds, "self_calibration": self_calibration}
    # the daemon's default configuration: learning on (the nominal injectors never start it)
    try:
        with watched_daemon(bus, codec, out_dir / "daemon-bench.log") as (d, b, w):
            _warm_up(b, codec, pool, rate, w, self_calibration)
            phases = [("nominal", rate)] + ([("adopted", rate)] if self_calibration else []) + \
                [("overload", rate * overload_factor)]
            for phase, r in phases:
                if phase == "adopted":   # until every injector has adopted its model and had its refinement
                    report["learned_after_s"], report["learned"] = _feed_until_learned(b, codec, pool, rate, w,
                                                                                        LEARN_TIMEOUT_S)
                report[phase] = _phase(b, codec, pool, r, seconds, w, d)
            report["daemon_exit"] = d.stop(timeout=10)
        report["histogram_png"] = latency_histogram(report, out_dir / "latency-histogram.png")
    finally:
        if hub is not None:
            hub.stop()
    report.update(yardstick_fields(before, yardstick_us_per_candidate(0.5)))
    return report


LEARN_TIMEOUT_S = 90.0
LEARNED = ("monitoring", "adopted")


def _feed_until_learned(bus: Any, codec: Codec, pool: list, rate: float, w: _Watcher,
                        timeout: float) -> tuple[float, bool]:
    """Feed at ``rate`` until every injector's ModelCalibration shows its model adopted after two
    calibrations (the first window and the refinement), or ``timeout`` s; the seconds it took and
    whether they all got there."""
    injectors = {i for i, _ in pool}
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        last: dict[int, Any] = {}
        for _, c in list(w.calibrations):
            last[c.injector_id] = c
        if all(i in last and codec.calibration_state(last[i].state) in LEARNED and last[i].calibrations >= 2
               for i in injectors):
            return time.monotonic() - t0, True
        _feed(bus, codec, pool, rate, 1.0, w)
    return time.monotonic() - t0, False


def latency_histogram(rep: dict, path: Path) -> str | None:
    """A PNG of the external latencies of each phase (log counts); the path, or None without matplotlib."""
    from estimator.errors import EstimatorError
    from estimator.plots.figures import pyplot, save

    try:
        plt = pyplot()
    except EstimatorError:
        return None
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for phase in ("nominal", "adopted", "overload"):
        lat = np.array(rep.get(phase, {}).get("external_latency_ms", []))
        if lat.size:
            bins = np.logspace(np.log10(max(lat.min(), 0.1)), np.log10(max(lat.max(), 1.0)) + 0.01, 60)
            ax.hist(lat, bins=bins, histtype="step", lw=1.5,
                    label=f"{phase}: {rep[phase]['offered_per_s']:.0f}/s, p99 {np.percentile(lat, 99):.1f} ms")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("trailer sent -> EstimateState received (ms)")
    ax.set_ylabel("injections")
    ax.legend()
    ax.grid(alpha=0.3)
    return str(save(fig, path))


def format_report(ing: dict, rep: dict) -> str:
    """The daemon benchmark as a table."""
    from sim_bench.benches.speed import yardstick_text

    lines = [f"ingest (decode + reassembly, one core): {ing['frames_per_s']:,.0f} frames/s (target >= 100,000)",
             f"daemon on {rep['bus']}:",
             f"{'phase':<9} {'offered/s':>9} {'estimated':>9} {'ext p50':>8} {'ext p99':>8} {'daemon p99':>10} "
             f"{'dropped':>8} {'rejected':>8} {'RSS MB':>7} {'alive':>5}"]
    shown = [p for p in ("nominal", "adopted", "overload") if p in rep]
    for phase in shown:
        p = rep[phase]
        lines.append(f"{phase:<9} {p['offered_per_s']:>9.0f} {p['estimated']:>9} {p['external_latency_p50_ms']:>7.2f} "
                     f"{p['external_latency_p99_ms']:>7.2f} {p['daemon_latency_p99_ms']:>9.2f} "
                     f"{p['frames_dropped']:>8} {p['rejected']:>8} {p['daemon_rss_peak_mb']:>7.0f} "
                     f"{p['daemon_alive']!s:>5}")
    lines.append("daemon p99 by stage (heartbeat, ms): " + "; ".join(
        f"{phase} " + " ".join(f"{k} {rep[phase]['daemon_stage_p99_ms'][k]:.2f}" for k in STAGES)
        for phase in shown))
    if rep.get("self_calibration"):
        if rep.get("learned", True):
            lines.append(f"learning: every injector adopted its model and its refinement {rep.get('learned_after_s', 0):.1f} s "
                         "after the nominal phase (the adopted phase starts then)")
        else:
            lines.append(f"learning: not every injector had adopted its model and its refinement {rep['learned_after_s']:.1f} s "
                         "after the nominal phase (the calibration process, at idle priority, gets a core only where "
                         "nothing else wants it); the adopted phase starts then")
        for phase in shown:
            st = rep[phase]["calibration_states"]
            lines.append(f"self-calibration during {phase}: {st.count('calibrating')} calibration(s) started, "
                         f"{st.count('adopted')} adopted, {st.count('refused')} refused; injectors with their own "
                         f"model by the end: {rep[phase]['adopted_injectors']}")
    lines.append("latencies in ms; ext = trailer sent -> EstimateState received (includes the bus), "
                 "daemon = last frame arrived -> EstimateState sent (heartbeat LatencyP99, last 10 s)")
    if "yardstick_before_after" in rep:
        lines.append(yardstick_text(rep))
    if rep.get("histogram_png"):
        lines.append(f"histogram: {rep['histogram_png']}")
    return "\n".join(lines)
