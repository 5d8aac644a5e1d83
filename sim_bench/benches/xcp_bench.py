"""``python -m sim_bench xcp-bench``: the daemon with its XCP slave on, measured as a calibration tool
uses it. At 200 injections/s from four injectors: the daemon's p99 without a client, then with one
pyxcp master running DAQ of the four injectors' estimates on the injection event in a list of its own,
and each injector's predefined list on that injector's event (every estimate's two DAQ packets
received, none lost by the slave); then 10,000 random and malformed datagrams from another
peer, in batches, the master answering after each: every datagram counted by the slave (its
own counters, read over XCP), the daemon serving on, and its p99 after the flood.
"""

from __future__ import annotations

import logging
import math
import socket
import struct
import time
import warnings
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from estimator.codec.records import Codec
from estimator.service.xcp import protocol as xp
from estimator.service.xcp.daq_lists import injector_event
from estimator.service.xcp.memory import SLAVE_COUNTERS, STATS_BASE, slot_layout
from sim_bench.benches.daemon_bench import _phase, _warm_up, injection_pool, watched_daemon
from sim_bench.benches.table import keyed, render
from sim_bench.benches.targets import missed

HOSTILE = 10_000      # datagrams
BATCH = 100           # hostile datagrams between two round trips of the master


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 free now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class _Raw:
    """A raw XCP master: one command, one response (or a timeout)."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(5.0)
        self.address = ("127.0.0.1", port)
        self.ctr = 0

    def __call__(self, packet: bytes) -> bytes:
        self.sock.sendto(xp.frame(self.ctr, packet), self.address)
        self.ctr += 1
        while True:
            data, _ = self.sock.recvfrom(65535)
            got = xp.packets(data)
            if got and got[0][1][0] in (xp.RES, xp.ERR):
                return got[0][1]

    def counters(self) -> dict[str, int]:
        n = 4 * len(SLAVE_COUNTERS)
        r = self(bytes((xp.SHORT_UPLOAD, n, 0, 0)) + struct.pack("<I", STATS_BASE))
        return dict(zip((name for name, _ in SLAVE_COUNTERS), struct.unpack(f"<{len(SLAVE_COUNTERS)}I", r[1:])))


def pyxcp_master(port: int, policy: Any = None) -> Any:
    """A pyxcp master for the slave on UDP 127.0.0.1:``port``, its DAQ packets to ``policy``."""
    from pyxcp.config import create_application_from_config
    from pyxcp.master import Master

    app = create_application_from_config({"Transport": {"Eth": {"host": "127.0.0.1", "port": port,
                                                                "protocol": "UDP"}}}, log_level=logging.WARNING)
    app.transport.layer = "ETH"
    return Master("eth", config=app, policy=policy)


def _recorder() -> Any:
    from pyxcp.transport.base import FrameAcquisitionPolicy, FrameCategory

    class Recorder(FrameAcquisitionPolicy):
        def __init__(self) -> None:
            super().__init__(None)
            self.pids: Counter[int] = Counter()    # DAQ packets by PID (a list's first ODT's)

        def feed(self, category: Any, counter: int, timestamp: int, payload: bytes) -> None:
            if category == FrameCategory.DAQ and payload:
                self.pids[payload[0]] += 1

        def finalize(self) -> None:
            pass
    return Recorder()


def run(out_dir: Path, rate: float = 200.0, seconds: float = 10.0, bus: str | None = None) -> dict:
    """The three phases; the report."""
    from sim_bench.benches.bench import resolve_bus
    from sim_bench.benches.speed import yardstick_us_per_candidate

    out_dir = out_dir.resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    codec = Codec()
    pool = injection_pool(codec)
    injectors = sorted({i for i, _ in pool})
    bus, hub = resolve_bus(bus, out_dir)
    port = free_udp_port()
    cfg = out_dir / "xcp.toml"
    cfg.write_text(f"[estimator.xcp]\nmode = \"on\"\nport = {port}\n")
    rep: dict = {"benchmark": "xcp-bench", "bus": bus, "rate_per_s": rate, "seconds": seconds, "port": port,
                 "yardstick_us_per_candidate": yardstick_us_per_candidate()}
    try:
        with watched_daemon(bus, codec, out_dir / "xcp-bench.log", cfg) as (d, b, w):
            _warm_up(b, codec, pool, rate, w, False)
            rep["without_client"] = _slim(_phase(b, codec, pool, rate, seconds, w, d))
            recorder = _recorder()
            with warnings.catch_warnings(), pyxcp_master(port, recorder) as x:
                warnings.simplefilter("ignore")
                x.connect()
                slots = slot_layout(codec.db)
                state = codec.db.get_message_by_name("EstimateState").frame_id
                own = x.getDaqProcessorInfo().minDaq    # the master's list, after the predefined ones
                x.freeDaq()
                x.allocDaq(1)
                x.allocOdt(own, 1)
                x.allocOdtEntry(own, 0, len(injectors))
                x.setDaqPtr(own, 0, 0)
                for i in injectors:
                    x.writeDaq(0xFF, 8, 0, slots[(state, i)])
                x.setDaqListMode(0x10, own, 0, 1, 0)
                own_pid = x.startStopDaqList(2, own).firstPid
                ready_pids = []
                for i in injectors:                    # and each injector's predefined list on its own event
                    x.setDaqListMode(0x10, i, injector_event(i), 1, 0)
                    ready_pids.append(x.startStopDaqList(2, i).firstPid)
                x.startStopSynch(1)
                e0, d0 = w.estimates, recorder.pids.copy()
                rep["daq"] = _slim(_phase(b, codec, pool, rate, seconds, w, d))
                time.sleep(0.2)    # DAQ packets of the last estimates in flight (UDP on loopback)
                rep["daq"]["estimates"] = w.estimates - e0
                rep["daq"]["daq_packets"] = recorder.pids[own_pid] - d0[own_pid]
                rep["daq"]["ready_packets"] = sum(recorder.pids[pid] - d0[pid] for pid in ready_pids)
                x.startStopSynch(0)
                x.disconnect()
            raw = _Raw(port)
            raw(bytes((xp.CONNECT, 0)))
            before = raw.counters()
            rep["hostile"] = _flood(raw, port)
            after = raw.counters()
            rep["hostile"]["counted"] = after["datagrams"] - before["datagrams"] - rep["hostile"]["round_trips"] - 1
            rep["slave"] = after
            rep["after_flood"] = _slim(_phase(b, codec, pool, rate, seconds, w, d))
            raw(bytes((xp.DISCONNECT,)))
            rep["daemon_alive"] = d.alive()
            rep["daemon_exit"] = d.stop(timeout=10)
    finally:
        if hub is not None:
            hub.stop()
    rep["failures"] = failures(rep)
    return rep


def _flood(raw: _Raw, port: int) -> dict:
    """``HOSTILE`` seeded random datagrams from another peer, half of them framed as XCP packets (so the
    commands behind the header are tried), in batches; the master reconnects after each (a hostile
    CONNECT takes the connection over, as a second master would)."""
    rng = np.random.default_rng(11)
    hostile = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    hostile.bind(("127.0.0.1", 0))
    sent = trips = 0
    t0 = time.monotonic()
    try:
        while sent < HOSTILE:
            for _ in range(min(BATCH, HOSTILE - sent)):
                n = int(rng.integers(0, 300))
                data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
                if n and rng.uniform() < 0.5:
                    data = xp.frame(int(rng.integers(0, 65536)), data[:xp.MAX_CTO])
                hostile.sendto(data, ("127.0.0.1", port))
                sent += 1
            raw(bytes((xp.CONNECT, 0)))
            trips += 1
    finally:
        hostile.close()
    return {"sent": sent, "round_trips": trips, "seconds": time.monotonic() - t0}


def _slim(phase: dict) -> dict:
    """A phase without its per-estimate latencies."""
    return {k: v for k, v in phase.items() if k != "external_latency_ms"}


def failures(rep: dict) -> list[str]:
    """The targets missed (``xcp-bench`` in :data:`sim_bench.benches.targets.TARGETS`)."""
    daq = rep.get("daq", {})
    lost = (max(daq.get("estimates", 0) - daq.get("daq_packets", 0), 0)
            + max(daq.get("estimates", 0) - daq.get("ready_packets", daq.get("estimates", 0)), 0))
    return missed("xcp-bench", {
        "daq_p99_ms": daq.get("daemon_latency_p99_ms", math.nan),
        "daq_lost": float(lost + rep.get("slave", {}).get("overruns", 0)),
        "hostile_uncounted": float(rep["hostile"]["sent"] - rep["hostile"]["counted"]) if "hostile" in rep else math.nan,
        "after_flood_p99_ms": rep.get("after_flood", {}).get("daemon_latency_p99_ms", math.nan),
        "daemon_down": 0.0 if rep.get("daemon_alive") and rep.get("daemon_exit") == 0 else 1.0})


def format_report(rep: dict) -> str:
    """The table."""
    cols = [keyed("phase", "", "<15", "phase"), keyed("offered/s", "", ">10.0f", "offered_per_s"),
            keyed("daemon p99", "ms", ">11.2f", "daemon_latency_p99_ms"),
            keyed("external p99", "ms", ">13.2f", "external_latency_p99_ms"),
            keyed("estimates", "", ">10", "estimated"), keyed("DAQ packets", "", ">12", "daq_packets")]
    rows = [{"daq_packets": "-", **rep.get(name, {}), "phase": name.replace("_", " "), "failures": []}
            for name in ("without_client", "daq", "after_flood")]
    h = rep.get("hostile", {})
    return "\n".join([
        f"daemon with its XCP slave on, {rep['rate_per_s']:.0f} injections/s from four injectors, "
        f"{rep['seconds']:.0f} s a phase (daq: one pyxcp master, a list of its own on the injection event "
        f"and each injector's predefined list on its own event: {rep.get('daq', {}).get('ready_packets', 0)} "
        "packets of those)",
        render(cols, rows, lambda r: ""),
        f"hostile datagrams: {h.get('sent', 0)} sent, {h.get('counted', 0)} counted by the slave "
        f"({h.get('seconds', math.nan):.1f} s); daemon alive {rep.get('daemon_alive')}, exit {rep.get('daemon_exit')}",
        f"slave counters: {rep.get('slave', {})}",
        f"machine yardstick: {rep.get('yardstick_us_per_candidate', math.nan):.1f} µs a candidate simulation at "
        "batch 256, measured before the daemon started"])
