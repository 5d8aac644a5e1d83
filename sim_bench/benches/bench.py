"""The end-to-end bench: estimator daemon and simulated node as processes on a real bus, scored.

Bus: ``vcan0`` when it exists (and carries CAN FD), otherwise a loopback hub (python-can-remote on
127.0.0.1, started and stopped here). The bench process listens to everything like ``candump``,
writes the capture as a candump log, joins every estimate with the node's SimTruth by
(injector, counter) and scores it.
"""

from __future__ import annotations

import contextlib
import json
import math
import subprocess
import sys
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimator.codec.records import (
    Codec,
    EstimateQuality,
    EstimateState,
    EstimatorStatus,
    InjectionTrailer,
    SimTruth,
    ValvePrediction,
)
from estimator.ident.status import ESTIMATED_WORDS
from estimator.service.bus import BusSetupError, check_socketcan
from sim_bench.benches.table import verdict
from sim_bench.hardware import scenarios
from sim_bench.hardware.hub import Hub
from sim_bench.hardware.procs import BusMonitor, DaemonProcess, check_stop, rss_mb, spawn, stop_process

SETTLE = scenarios.SETTLE


@dataclass
class Capture:
    """What the listener saw, decoded."""

    truth: dict = field(default_factory=dict)          # (inj, counter) -> SimTruth (latest)
    trailer_t: dict = field(default_factory=dict)      # (inj, counter) -> monotonic time of the trailer
    rows: list = field(default_factory=list)           # joined estimate rows
    pending: dict = field(default_factory=dict)        # (inj, counter) -> partial row
    awaiting: dict = field(default_factory=dict)       # (inj, counter) -> complete row waiting for its SimTruth
    status: EstimatorStatus | None = None
    frames: int = 0
    seen_per_injector: dict = field(default_factory=lambda: defaultdict(int))


def default_bus() -> tuple[str, bool]:
    """('socketcan:vcan0', False) if vcan0 can carry CAN FD, else ('', True): start a hub."""
    try:
        check_socketcan("vcan0")
        return "socketcan:vcan0", False
    except BusSetupError:
        return "", True


def resolve_bus(bus: str | None, out_dir: Path) -> tuple[str, Hub | None]:
    """The bus to use: as given, else vcan0, else a loopback hub started here (returned for stopping)."""
    if bus is not None:
        return bus, None
    spec, need_hub = default_bus()
    if not need_hub:
        return spec, None
    hub = Hub(log_path=out_dir / "hub.log").start()
    return hub.spec, hub


class Listener(BusMonitor):
    """Receives everything, writes the candump log, joins estimates with truth (the bench's monitor)."""

    def __init__(self, bus_spec: str, log_path: Path, codec: Codec) -> None:
        super().__init__(bus_spec, codec, capture=log_path, keep=1)
        self.cap = Capture()
        self.lock = self.cond        # the bench reads cap under it
        self.heartbeat = self.cond   # notified on every frame; heartbeats are counted
        self.heartbeats_seen = 0

    def on_record(self, now: float, rec) -> None:
        self._handle(rec, now)

    def _handle(self, rec, now: float) -> None:
        c = self.cap
        c.frames += 1
        if isinstance(rec, InjectionTrailer):
            key = (rec.injector_id, rec.counter)
            c.trailer_t[key] = now
            c.truth.pop(key, None)        # counters wrap: never join with the truth of 256 injections ago
        elif isinstance(rec, SimTruth):
            key = (rec.injector_id, rec.counter)
            c.truth[key] = rec
            row = c.awaiting.pop(key, None)
            if row is not None:           # the estimate was faster than the node's SimTruth
                self._join(row, rec)
        elif isinstance(rec, EstimatorStatus):
            c.status = rec
            self.heartbeats_seen += 1
        elif isinstance(rec, (EstimateState, EstimateQuality, ValvePrediction)):
            key = (rec.injector_id, rec.counter)
            row = c.pending.setdefault(key, {"injector": rec.injector_id, "counter": rec.counter})
            if isinstance(rec, EstimateState):
                t_tr = c.trailer_t.get(key)
                word = self.codec.status_of(rec.status)
                row.update(nu=rec.nu_n_per_v, lh_um=rec.lh_um, status=word.value if word else rec.status, t=now,
                           latency_ms=(now - t_tr) * 1e3 if t_tr is not None else float("nan"))
            elif isinstance(rec, EstimateQuality):
                row.update(sigma_lh_um=rec.sigma_lh_um, evaluations=rec.evaluations, cost_uvs=rec.cost_uvs,
                           robust=rec.robust)
            else:
                row.update(t_open_us=rec.opening_us, stroke_um=rec.stroke_um, t_contact_us=rec.contact_us)
            if {"nu", "sigma_lh_um", "t_open_us"} <= row.keys():
                del c.pending[key]
                tr = c.truth.get(key)
                if tr is not None:
                    self._join(row, tr)
                else:
                    c.awaiting[key] = row

    def _join(self, row: dict, tr: SimTruth) -> None:
        c = self.cap
        c.seen_per_injector[tr.injector_id] += 1
        row.update(k=c.seen_per_injector[tr.injector_id], nu_true=tr.nu_n_per_v, lh_true_um=tr.lh_um,
                   t_open_true_us=tr.opening_us, stroke_true_um=tr.stroke_um, temperature_c=tr.temperature_c)
        c.rows.append(row)

    def wait_idle(self, timeout: float) -> bool:
        """Until two heartbeats in a row show an empty queue and unchanged counters: the daemon has
        published everything it received (True), or ``timeout`` s (False)."""
        t_end = time.monotonic() + timeout
        last = None
        with self.lock:
            seen = self.heartbeats_seen
            while time.monotonic() < t_end:
                self.heartbeat.wait(min(0.5, max(t_end - time.monotonic(), 0.0)))
                if self.heartbeats_seen == seen or self.cap.status is None:
                    continue
                seen = self.heartbeats_seen
                st = self.cap.status
                now = (st.accepted, st.rejected_crc, st.rejected_missing, st.rejected_timeout, st.rejected_invalid,
                       st.rejected_outlier, st.queue_depth)
                if st.queue_depth == 0 and now == last:
                    return True
                last = now
        return False


def _rms(x) -> float:
    x = np.asarray([v for v in x if v is not None and math.isfinite(v)])
    return float(np.sqrt(np.mean(x ** 2))) if x.size else float("nan")


def score(rows: list[dict], status: EstimatorStatus | None, scenario: str) -> dict:
    """Scores of a run: errors over time and after settling, prediction errors, latency, counters."""
    sc = scenarios.SCENARIOS[scenario]
    ok = [r for r in rows if r.get("status") in ESTIMATED_WORDS]   # every published estimate of its injection

    def judged(r: dict) -> bool:   # settled, and not the swapped injector while its new part is learned
        swap = sc.swap_at
        return r["k"] > sc.settle and not (swap is not None and r["injector"] == 1
                                           and swap < r["k"] <= swap + scenarios.SWAP_SETTLE)
    settled = [r for r in ok if judged(r)]
    ok_far = [(r["injector"], r["k"]) for r in rows if r.get("status") == "ok"
              and not abs(r["lh_um"] - r["lh_true_um"]) <= sc.ok_within_um]
    e_lh = [r["lh_um"] - r["lh_true_um"] for r in settled]
    e_nu = [100 * (r["nu"] / r["nu_true"] - 1) for r in settled]
    e_to = [r["t_open_us"] - r["t_open_true_us"] for r in settled if r["t_open_true_us"] > 0]
    e_st = [r["stroke_um"] - r["stroke_true_um"] for r in settled if r["stroke_true_um"] > 0]
    lat = [r["latency_ms"] for r in rows if math.isfinite(r.get("latency_ms", float("nan")))]
    lat_settled = [r["latency_ms"] for r in rows if r.get("k", 0) > sc.settle and math.isfinite(r.get("latency_ms", float("nan")))]
    s: dict[str, Any] = {
        "scenario": scenario, "estimates": len(rows), "settled": len(settled),
        "max_abs_lh_um": float(np.max(np.abs(e_lh))) if e_lh else float("nan"), "rms_lh_um": _rms(e_lh),
        "max_abs_nu_pct": float(np.max(np.abs(e_nu))) if e_nu else float("nan"), "rms_nu_pct": _rms(e_nu),
        "rms_t_open_us": _rms(e_to), "rms_stroke_um": _rms(e_st),
        "latency_p50_ms": float(np.percentile(lat, 50)) if lat else float("nan"),
        "latency_p99_ms": float(np.percentile(lat, 99)) if lat else float("nan"),
        "latency_settled_p50_ms": float(np.percentile(lat_settled, 50)) if lat_settled else float("nan"),
        "latency_settled_p99_ms": float(np.percentile(lat_settled, 99)) if lat_settled else float("nan"),
    }
    if status is not None:
        s.update({k: getattr(status, k) for k in ("accepted", "rejected_crc", "rejected_missing", "rejected_timeout",
                                                  "rejected_invalid", "rejected_outlier", "frames_dropped",
                                                  "frames_malformed")})
    targets = scenarios.SCENARIOS[scenario].targets
    lh_t, nu_t = targets.lh_um, targets.nu_pct
    fails = []
    if lh_t is not None and not (s["max_abs_lh_um"] <= lh_t):
        fails.append(f"max |L_h error| {s['max_abs_lh_um']:.3f} µm > {lh_t} µm")
    if nu_t is not None and not (s["max_abs_nu_pct"] <= nu_t):
        fails.append(f"max |N_u error| {s['max_abs_nu_pct']:.3f} % > {nu_t} %")
    if lh_t is not None and not settled:
        fails.append("no settled estimates")
    s["ok_far"] = len(ok_far)
    if ok_far:
        fails.append(f"{len(ok_far)} published ok with L_h more than {sc.ok_within_um} µm off (first: injector, "
                     f"injection {ok_far[0]})")
    s["targets"] = {"lh_um": lh_t, "nu_pct": nu_t, "settle": sc.settle,
                    "ok_within_um": sc.ok_within_um if math.isfinite(sc.ok_within_um) else None}
    s["failures"] = fails
    return s


def format_score(s: dict) -> str:
    """The final table of one run."""
    settle = s["targets"].get("settle", SETTLE)
    rows = [(f"estimates (settled after {settle}/injector)", f"{s['estimates']} ({s['settled']})"),
            ("L_h error max / rms [µm]", f"{s['max_abs_lh_um']:.3f} / {s['rms_lh_um']:.3f}"),
            ("N_u error max / rms [%]", f"{s['max_abs_nu_pct']:.3f} / {s['rms_nu_pct']:.3f}"),
            ("opening time / stroke prediction rms", f"{s['rms_t_open_us']:.2f} µs / {s['rms_stroke_um']:.3f} µm"),
            ("latency p50 / p99 [ms], all (after settling)", f"{s['latency_p50_ms']:.2f} / {s['latency_p99_ms']:.2f} "
             f"({s['latency_settled_p50_ms']:.2f} / {s['latency_settled_p99_ms']:.2f})"),
            ("throughput [estimates/s]", f"{s.get('throughput_per_s', float('nan')):.1f}")]
    if "accepted" in s:
        rows.append(("accepted / rejected crc,missing,timeout,invalid,outlier",
                     f"{s['accepted']} / {s['rejected_crc']},{s['rejected_missing']},{s['rejected_timeout']},"
                     f"{s['rejected_invalid']},{s['rejected_outlier']}"))
        rows.append(("frames dropped / malformed", f"{s['frames_dropped']} / {s['frames_malformed']}"))
    if "node" in s:
        rows.append(("node: injections, faults, late", f"{s['node'].get('injections')}, "
                     f"{s['node'].get('faults')}, {s['node'].get('late')}"))
    if "daemon_rss_mb" in s:
        rows.append(("daemon memory [MB] / exit code / stop time", f"{s['daemon_rss_mb']:.0f} / "
                     f"{s['daemon_exit']} / {s['daemon_stop_s']:.2f} s"))
    t = s["targets"]
    outcome = verdict(s)
    lines = [f"bench {s['scenario']} - targets: |L_h error| <= {t['lh_um']} µm, |N_u error| <= {t['nu_pct']} % "
             f"after {settle} injections per injector" + (f"; ok only within {t['ok_within_um']} µm"
                                                            if t.get("ok_within_um") is not None else "")]
    w = max(len(a) for a, _ in rows)
    lines += [f"  {a:<{w}}  {b}" for a, b in rows]
    lines.append(f"  {outcome}")
    return "\n".join(lines)


def run_bench(scenario_name: str, bus: str | None, seconds: float | None, out_dir: Path, seed: int = 0,
              progress: bool = True, plots: bool = True, capture_format: str = "log",
              drive: str | None = None) -> dict:
    """Run one scenario end to end (its node on the named ``drive`` if given, see
    :data:`estimator.model.drive.DRIVES`); returns the score dict (also written to out_dir)."""
    sc = scenarios.get(scenario_name, seconds=seconds)
    out_dir.mkdir(parents=True, exist_ok=True)
    bus, hub = resolve_bus(bus, out_dir)
    codec = Codec()
    state_dir = out_dir / "state"
    if state_dir.exists():
        for f in state_dir.iterdir():
            f.unlink()
    daemon: DaemonProcess | None = None
    node = None
    listener = None
    try:
        listener = Listener(bus, out_dir / f"capture.{capture_format}", codec)
        listener.start()
        daemon = DaemonProcess(bus, out_dir / "daemon.log", state_dir=state_dir).start()
        # ready: READY=1 on the notify socket, then the first heartbeat on the bus
        if not daemon.notify.wait_for("READY=1", 120, daemon.alive):
            raise RuntimeError(f"estimator daemon did not start: {daemon.why()}")
        with listener.lock:
            if not listener.heartbeat.wait_for(lambda: listener.cap.status is not None, 60):
                raise RuntimeError(f"estimator daemon sent no heartbeat: {daemon.why()}")
        node = spawn(["-m", "sim_bench", "node", "--bus", bus, "--scenario", sc.name, "--seconds", str(sc.seconds),
                      "--seed", str(seed), *(["--drive", drive] if drive else [])], out_dir / "node.log",
                     stdout=subprocess.PIPE)
        t0 = time.monotonic()
        peak_rss = 0.0
        while node.poll() is None:
            check_stop()                 # a stop signal that landed while the node was starting
            with contextlib.suppress(subprocess.TimeoutExpired):
                node.wait(timeout=0.5)   # the progress line ticks while the node runs
            peak_rss = max(peak_rss, rss_mb(daemon.pid))
            if progress:
                print(_progress_line(listener, time.monotonic() - t0, sc.seconds), end="", flush=True, file=sys.stderr)
        node_out = node.stdout.read() if node.stdout else ""
        if progress:
            print(file=sys.stderr)
        listener.wait_idle(timeout=15.0)   # the last estimates and a final heartbeat
        duration = time.monotonic() - t0
        t_stop = time.monotonic()
        daemon_exit = daemon.stop(timeout=10)
        stop_s = time.monotonic() - t_stop
    finally:
        stop_process(node)
        if daemon is not None:
            daemon.stop()
        if listener is not None:
            listener.close()
        if hub is not None:
            hub.stop()
    with listener.lock:
        rows = list(listener.cap.rows)
        status = listener.cap.status
    s = score(rows, status, sc.name)
    try:
        s["node"] = json.loads(node_out.strip().splitlines()[-1])["node"]
    except (ValueError, IndexError, KeyError):
        s["node"] = {}
    s.update(bus=bus, seconds=sc.seconds, seed=seed, throughput_per_s=len(rows) / max(duration, 1e-9),
             daemon_exit=daemon_exit, daemon_stop_s=stop_s, daemon_rss_mb=peak_rss,
             description=sc.description)
    return _finish_score(s, rows, sc, out_dir, seed, plots)


def _progress_line(listener: Listener, elapsed_s: float, seconds: float) -> str:
    """The bench's progress line: estimates, the latest L_h error, latency p99, drops, rejections."""
    with listener.lock:
        rows = list(listener.cap.rows[-200:])
        count = len(listener.cap.rows)
        st = listener.cap.status
    e = [abs(r["lh_um"] - r["lh_true_um"]) for r in rows[-20:]]
    lat = [r["latency_ms"] for r in rows if math.isfinite(r["latency_ms"])]
    return (f"\r[{elapsed_s:5.1f}/{seconds:.0f} s] estimates {count:5d}  "
            f"|dL_h| now {max(e) if e else float('nan'):.3f} µm  p99 {np.percentile(lat, 99) if lat else 0:.1f} ms"
            f"  dropped {st.frames_dropped if st else 0}  rejected "
            f"{(st.rejected_crc + st.rejected_missing + st.rejected_timeout + st.rejected_invalid) if st else 0}")


def _finish_score(s: dict, rows: list[dict], sc: scenarios.Scenario, out_dir: Path, seed: int, plots: bool) -> dict:
    """The daemon's exit and stop time judged, the rows and score written, the figures drawn."""
    if s["daemon_exit"] != 0:
        s["failures"].append(f"daemon exit code {s['daemon_exit']}")
    if s["daemon_stop_s"] > 2.0:
        s["failures"].append(f"daemon took {s['daemon_stop_s']:.2f} s to stop")
    (out_dir / f"bench-{sc.name}.json").write_text(json.dumps({"score": s, "rows": rows}, indent=1, default=float))
    if plots:
        try:
            from sim_bench.benches.bench_plots import plot_bench
            s["plots"] = [str(p) for p in plot_bench(rows, sc, out_dir, seed)]
        except ImportError:
            s["plots"] = []
    return s
