"""Reliability bench: the daemon as a child process on a real bus, under faults a bus, a disk and a
loaded machine produce; prints a table and writes JSON (``python -m sim_bench reliability``).

Faults: injections with 300 distinct sample periods (memory, heartbeat gaps), SIGSTOP between
header and trailer (live vs replay of the same capture), a flood of hostile frames on the input
identifiers, a poisoned state file, commands under the default policy, SIGHUP with a broken
config. Each row says what traffic was held and what was lost.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import can
import numpy as np

from estimator.codec.injection_frames import injection_frames
from estimator.codec.records import Codec, Command, EstimateState, EstimatorCommand, EstimatorHealth, EstimatorStatus
from estimator.ident.measurement import Injection
from estimator.io.captures import to_message
from estimator.model.parameters import NOMINAL_PRELOAD_N
from estimator.service.bus import open_bus
from sim_bench.benches.bench import resolve_bus
from sim_bench.hardware.plant import Plant, PlantConfig
from sim_bench.hardware.procs import REPO, BusMonitor, DaemonProcess, rss_mb, watched_daemon


def _injections(n: int, seed: int) -> list[Injection]:
    plant = Plant(PlantConfig(window_s=100e-6))
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        m = plant.measure(17.0, 3.0e-6, NOMINAL_PRELOAD_N, rng)
        out.append(Injection(m.current_a, m.voltage_v, m.dt_s, m.f_open_n))
    return out


def _hb(mon: BusMonitor) -> EstimatorStatus:
    return mon.heartbeats[-1][1]


def _handled(hb: EstimatorStatus) -> int:
    return (hb.accepted + hb.rejected_crc + hb.rejected_missing + hb.rejected_timeout + hb.rejected_invalid
            + hb.rejected_outlier)


def marker_message(codec: Codec) -> can.Message:
    """An EstimatorCommand set_prior of injector 7, which the default policy (reset-only) refuses:
    harmless, and counted in the heartbeat's CommandsRefused once the worker has taken it (and, frames
    being handled in order, all before it)."""
    msg = codec.db.get_message_by_name("EstimatorCommand")
    data = msg.encode({"InjectorId": 7, "Command": int(Command.SET_PRIOR), "PriorNu": 17.0, "PriorIdleStroke": 3.0})
    return can.Message(arbitration_id=msg.frame_id, data=data, is_fd=False, is_extended_id=False)


# stall faults: a header-to-trailer timeout and a silent-bus guard far above the time our own sending
# and the marker's round trip can take on a loaded machine, a stall well beyond the timeout, and a
# fast heartbeat for the marker
STALL_CONFIG = "[estimator]\nassembly_timeout_ms = 1000.0\nsilent_bus_s = 5.0\nstatus_period_s = 0.02\n"
STALL_S = 1.5


def _handled_at_least(n: int) -> Callable[[BusMonitor], bool]:
    """A monitor predicate: the heartbeat counts ``n`` injections handled."""
    return lambda m: bool(m.heartbeats) and _handled(_hb(m)) >= n


def _taken_at_least(n: int) -> Callable[[BusMonitor], bool]:
    """A monitor predicate: the heartbeat counts ``n`` injections accepted or timed out."""
    return lambda m: bool(m.heartbeats) and _hb(m).accepted + _hb(m).rejected_timeout >= n


def stalled_injection(bus: can.BusABC, daemon: DaemonProcess, mon: BusMonitor, codec: Codec, frames: list,
                      marks: int, stop_s: float = STALL_S) -> None:
    """Header and blocks, then the marker; once the heartbeat shows the daemon took them (``marks``
    markers so far), SIGSTOP, the trailer, ``stop_s`` of stall (the fault itself), SIGCONT."""
    for fr in frames[:-1]:
        bus.send(to_message(fr))
    bus.send(marker_message(codec))
    if not mon.wait_for(lambda m: m.heartbeats and _hb(m).commands_refused >= marks, 60, daemon.alive):
        raise RuntimeError(f"daemon never took the marker: {daemon.why()}")
    daemon.send_signal(signal.SIGSTOP)
    bus.send(to_message(frames[-1]))
    time.sleep(stop_s)
    daemon.send_signal(signal.SIGCONT)


def _send(bus, codec: Codec, injector: int, counter: int, inj: Injection, period_s: float | None = None) -> None:
    for fr in injection_frames(codec, injector, counter, period_s or inj.dt_s, inj.current_a, inj.voltage_v):
        bus.send(to_message(fr))


def periods(bus_spec: str, out: Path, n: int = 300) -> dict:
    """Injections that differ only in SamplePeriod (500..500+n-1 ns)."""
    codec = Codec()
    inj = _injections(1, 1)[0]
    with watched_daemon(bus_spec, out / "periods-daemon.log") as (d, mon):
        rss = []
        with open_bus(bus_spec) as bus:
            for k in range(n):
                _send(bus, codec, k % 8, k % 256, inj, (500 + k) * 1e-9)
                if k % 8 == 7:
                    mon.wait_for(_handled_at_least(k - 8), 120, d.alive)
                    rss.append(rss_mb(d.pid))
            mon.wait_for(lambda m: len(m.of_type(EstimateState)) >= n, 120, d.alive)
        t = np.array([t for t, _ in mon.heartbeats])
        return {"fault": f"{n} distinct sample periods", "injections": n,
                "published": len(mon.of_type(EstimateState)),
                "rss_first_mb": rss[0], "rss_max_mb": max(rss), "rss_growth_mb": max(rss) - rss[0],
                "heartbeat_max_gap_s": float(np.diff(t).max()), "daemon_exit": d.stop()}


def stall(bus_spec: str, out: Path, n: int = 10, stop_s: float = STALL_S) -> dict:
    """SIGSTOP after the blocks, trailer sent meanwhile, SIGCONT after ``stop_s``; then replay."""
    codec = Codec()
    cfg = out / "stall.toml"
    cfg.write_text(STALL_CONFIG)
    capture = out / "stall-capture.log"
    with watched_daemon(bus_spec, out / "stall-daemon.log", capture=capture, config=cfg) as (d, mon):
        with open_bus(bus_spec) as bus:
            for k, inj in enumerate(_injections(n, 2)):
                frames = injection_frames(codec, 3, k, inj.dt_s, inj.current_a, inj.voltage_v)
                stalled_injection(bus, d, mon, codec, frames, k + 1, stop_s)
                mon.wait_for(_taken_at_least(k + 1), 60, d.alive)
        live = _hb(mon)
        code = d.stop()
    jl = out / "stall-replay.jsonl"
    r = subprocess.run([sys.executable, "-m", "estimator", "replay", str(capture), "--json", str(jl), "--config",
                        str(cfg)], cwd=REPO, capture_output=True, text=True, timeout=300)
    rows = [json.loads(x) for x in jl.read_text().splitlines()] if jl.exists() else []
    return {"fault": f"SIGSTOP {stop_s * 1e3:.0f} ms between header and trailer", "injections": n,
            "live_accepted": live.accepted, "live_timeouts": live.rejected_timeout, "replay_accepted": len(rows),
            "replay_ok": r.returncode == 0, "daemon_exit": code}


def flood(bus_spec: str, out: Path, frames: int = 5000, seed: int = 3) -> dict:
    """Random bytes on the input identifiers (and random identifiers), then five good injections."""
    codec = Codec()
    rng = random.Random(seed)
    ids = [0x100, 0x101, 0x102, 0x220]
    with watched_daemon(bus_spec, out / "flood-daemon.log") as (d, mon):
        with open_bus(bus_spec) as bus:
            for _ in range(frames):
                fd = rng.random() < 0.7
                n = rng.choice([0, 1, 2, 8, 12, 16, 20, 24, 32, 48, 64]) if fd else rng.randint(0, 8)
                arb = rng.choice(ids) if rng.random() < 0.8 else rng.randint(0, 0x7FF)
                bus.send(can.Message(arbitration_id=arb, data=bytes(rng.getrandbits(8) for _ in range(n)), is_fd=fd,
                                     is_extended_id=False))
            good = _injections(5, 4)
            for k, inj in enumerate(good):
                _send(bus, codec, 5, k, inj)
            ok = mon.wait_for(lambda m: sum(1 for r in m.of_type(EstimateState) if r.injector_id == 5) >= 5, 120, d.alive)
        t0 = time.monotonic()
        mon.wait_for(lambda m: sum(t > t0 for t, _ in m.heartbeats) >= 2, 30, d.alive)
        hb = _hb(mon)
        return {"fault": f"{frames} random frames on the input identifiers", "malformed": hb.frames_malformed,
                "unknown_commands": hb.commands_unknown, "good_after": 5, "good_estimated": 5 if ok else 0,
                "rss_mb": rss_mb(d.pid), "daemon_exit": d.stop()}


def poisoned_state(bus_spec: str, out: Path) -> dict:
    """A state file with one good injector and three poisoned ones; the daemon must start and serve."""
    from estimator.ident.tracking.tracker import Tracker

    state = out / "state"
    state.mkdir(parents=True, exist_ok=True)
    t = Tracker()
    for inj in _injections(4, 5):
        t.update(inj)
    good = t.states[0].to_dict()
    bad_type = dict(good, accepted="many")
    bad_range = dict(good, x=[100.0, 500.0, 0.0, 0.06])
    doc = {"format": "piezo-injector-estimator-state", "version": 1, "saved_at": 0,
           "injectors": {"0": good, "1": bad_type, "2": bad_range, "3": [1, 2]}}
    (state / "estimator-state.json").write_text(json.dumps(doc))
    codec = Codec()
    with watched_daemon(bus_spec, out / "state-daemon.log", state_dir=state) as (d, mon):
        with open_bus(bus_spec) as bus:
            for k, inj in enumerate(_injections(3, 6)):
                for inj_id in (0, 1, 2, 3):
                    _send(bus, codec, inj_id, k, inj)
            mon.wait_for(lambda m: len(m.of_type(EstimateState)) >= 12, 120, d.alive)
        code = d.stop()
    saved = json.loads((state / "estimator-state.json").read_text())["injectors"]
    return {"fault": "state file: 1 good entry, 3 poisoned (type, range, shape)", "estimates": 12,
            "published": len(mon.of_type(EstimateState)), "restored_good": "0" in saved,
            "kept_copy": (state / "estimator-state.json.rejected").exists(), "daemon_exit": code}


def commands(bus_spec: str, out: Path) -> dict:
    """Default policy (reset-only): set_prior refused and counted (twice: the marker is one too)."""
    codec = Codec()
    with watched_daemon(bus_spec, out / "commands-daemon.log") as (d, mon):
        with open_bus(bus_spec) as bus:
            bus.send(to_message(codec.encode(EstimatorCommand(0, Command.SET_PRIOR, 17.0, 14.9))))
            bus.send(marker_message(codec))
            mon.wait_for(lambda m: m.heartbeats and _hb(m).commands_refused >= 2, 30, d.alive)
        hb = _hb(mon)
        return {"fault": "set_prior L_h 14.9 µm + set_prior marker (commands = reset-only)",
                "refused": hb.commands_refused, "unknown": hb.commands_unknown, "daemon_exit": d.stop()}


FLOOD_S, FLOOD_PERIODS_NS = 5.0, (7900, 8000, 8100, 8200, 8300, 8400)
LEGIT_HZ = 25.0
LEAD_S = 1.0          # normal operation before an attack begins
FLOOD_PER_S = 350.0   # the stranger's injections per second (three frames each)


def _health(mon: BusMonitor) -> EstimatorHealth:
    got = mon.of_type(EstimatorHealth)
    return got[-1] if got else EstimatorHealth()


def under_attack(bus_spec: str, out: Path, name: str, fault: str, attack, seconds: float = FLOOD_S,
                 config: str | None = None) -> dict:
    """Injector 0 sends its injections at 25 Hz (500 ns); after ``LEAD_S`` of normal operation
    ``attack(bus_spec, stop, ctx)`` runs for ``seconds`` in a process of its own (returning how many
    things it sent): the legitimate injector's latency (its trailer sent -> its EstimateState
    received) and losses, what the heartbeat and the health
    message counted meanwhile, the log's growth and the memory."""
    codec = Codec()
    legit = _injections(8, 9)
    cfg = None
    if config is not None:
        cfg = out / f"{name}.toml"
        cfg.write_text(config)
    log_path = out / f"{name}-daemon.log"
    watched = tuple(codec.messages[r].frame_id for r in (EstimateState, EstimatorStatus, EstimatorHealth))
    with watched_daemon(bus_spec, log_path, config=cfg, only=watched) as (d, mon):
        mon.wait_for(lambda m: m.of_type(EstimatorHealth), 30, d.alive)
        rss0, hb0, health0 = rss_mb(d.pid), _hb(mon), _health(mon)
        log0 = log_path.stat().st_size
        sent: dict[int, float] = {}
        mp = multiprocessing.get_context("spawn")
        ready, go, stop, count = mp.Event(), mp.Event(), mp.Event(), mp.Value("q", 0)
        stranger = mp.Process(target=_stranger, args=(attack, bus_spec, ready, go, stop, count,
                                                      {"pid": d.pid, "config": str(cfg)}), daemon=True)
        stranger.start()
        if not ready.wait(120):
            raise RuntimeError("the stranger's process did not start")
        rss = [rss0]
        with open_bus(bus_spec) as bus:
            t0 = time.monotonic()
            n = 0
            while time.monotonic() - t0 < LEAD_S + seconds:
                if n == int(LEAD_S * LEGIT_HZ):   # the stranger appears on a bus in normal operation
                    go.set()
                inj = legit[n % len(legit)]
                for fr in injection_frames(codec, 0, n % 256, inj.dt_s, inj.current_a, inj.voltage_v):
                    bus.send(to_message(fr))
                sent[n % 256] = time.monotonic()
                n += 1
                rss.append(rss_mb(d.pid))
                time.sleep(max(0.0, t0 + n / LEGIT_HZ - time.monotonic()))
            stop.set()
            stranger.join(timeout=60)
        attacks = [count.value]
        mon.wait_for(lambda m: sum(1 for _, r in m.records if isinstance(r, EstimateState) and r.injector_id == 0) >= n,
                     60, d.alive)
        t1 = time.monotonic()
        mon.wait_for(lambda m: sum(t > t1 for t, _ in m.heartbeats) >= 3, 30, d.alive)
        got = {}
        for t, r in list(mon.records):
            if isinstance(r, EstimateState) and r.injector_id == 0 and r.counter in sent and r.counter not in got:
                got[r.counter] = (t - sent[r.counter]) * 1e3
        hb, health = _hb(mon), _health(mon)
        lat = np.array(list(got.values()))
        return {"fault": fault, "legit_sent": n, "legit_estimated": len(got),
                "legit_p99_ms": float(np.percentile(lat, 99)) if lat.size else float("nan"),
                "legit_max_ms": float(lat.max()) if lat.size else float("nan"),
                "attacker_sent": attacks[0] if attacks else 0,
                "attacker_counted": int(_handled(hb) - _handled(hb0) - n
                                        + health.injections_shed - health0.injections_shed),
                "shed": health.injections_shed - health0.injections_shed,
                "commands_applied": health.commands_applied - health0.commands_applied,
                "malformed": hb.frames_malformed - hb0.frames_malformed,
                "dropped": hb.frames_dropped - hb0.frames_dropped,
                "log_growth_kb": (log_path.stat().st_size - log0) / 1024,
                "daemon_stage_p99_ms": {k: getattr(hb, f"{k}_p99_ms") for k in ("queue", "assembly", "estimation", "send")},
                "rss_growth_mb": max(rss) - rss0, "daemon_exit": d.stop()}


def _paced(stop, per_s: float, send_one) -> int:
    """Call ``send_one(k)`` ``per_s`` times a second until ``stop``; returns how many were sent."""
    k = 0
    t0 = time.monotonic()
    while not stop.is_set():
        time.sleep(max(0.0, t0 + k / per_s - time.monotonic()))
        send_one(k)
        k += 1
    return k


# ---- the strangers: each runs in a process of its own, as a stranger on the bus would -------------
# well-formed injections per second (a reset and 17 frames each): what is left of a CAN FD bus at
# 500 kbit/s / 2 Mbit/s (a 64-byte frame ≈ 0.39 ms, a classic 8-byte one ≈ 0.22 ms) besides the
# legitimate injector's 425 frames a second
FULL_PER_S = 120.0
SIGHUPS, SIGHUP_S = 50, 1.0
RELOAD_CONFIG = "[estimator]\nlog_level = \"INFO\"\n"
COMMANDS_PER_S = 1000.0


def _period_attack(spec: str, stop, ctx: dict) -> int:
    """Cheap injections (header, one block of 15 samples, trailer) on ids 1-7, six sample periods."""
    codec = Codec()
    rng = np.random.default_rng(5)
    short = [(rng.normal(0.0, 1.0, 15), rng.normal(0.0, 1.0, 15)) for _ in range(8)]
    with open_bus(spec) as bus:
        def one(k: int) -> None:
            cur, volt = short[k % len(short)]
            period = FLOOD_PERIODS_NS[k % len(FLOOD_PERIODS_NS)] * 1e-9
            for fr in injection_frames(codec, 1 + k % 7, k % 256, period, cur, volt):
                bus.send(to_message(fr))
        return _paced(stop, FLOOD_PER_S, one)


def _full_attack(spec: str, stop, ctx: dict) -> int:
    """Well-formed injections at the legitimate sample period on ids 1-7, each after a reset of its id."""
    codec = Codec()
    pool = _injections(16, 11)
    with open_bus(spec) as bus:
        def one(k: int) -> None:
            inj = pool[k % len(pool)]
            iid = 1 + k % 7
            bus.send(to_message(codec.encode(EstimatorCommand(iid, Command.RESET))))
            for fr in injection_frames(codec, iid, k % 256, inj.dt_s, inj.current_a, inj.voltage_v):
                bus.send(to_message(fr))
        return _paced(stop, FULL_PER_S, one)


def _sighup_attack(spec: str, stop, ctx: dict) -> int:
    """SIGHUPs to the daemon, its configuration file's log level toggled every other time."""
    cfg = Path(ctx["config"])

    def one(k: int) -> None:
        if k < SIGHUPS:
            cfg.write_text(RELOAD_CONFIG.replace("INFO", "DEBUG") if k % 2 else RELOAD_CONFIG)
            os.kill(ctx["pid"], signal.SIGHUP)
    return min(_paced(stop, SIGHUPS / SIGHUP_S, one), SIGHUPS)


def _command_attack(spec: str, stop, ctx: dict) -> int:
    """Reset commands on the unused id 5."""
    msg = to_message(Codec().encode(EstimatorCommand(5, Command.RESET)))
    with open_bus(spec) as bus:
        return _paced(stop, COMMANDS_PER_S, lambda k: bus.send(msg))


def _stranger(attack, spec: str, ready, go, stop, sent, ctx: dict) -> None:
    """A stranger's process: ready, then waits for ``go``, attacks until ``stop``, reports what it sent."""
    ready.set()
    go.wait()
    sent.value = attack(spec, stop, ctx)


def period_flood(bus_spec: str, out: Path, seconds: float = FLOOD_S) -> dict:
    """A stranger's cheap injections on the unused ids 1-7, rotating among six sample periods near 8 µs,
    350 a second."""
    return under_attack(bus_spec, out, "period-flood", f"{seconds:g} s of {FLOOD_PER_S:.0f}/s 15-sample injections, "
                        "ids 1-7, periods near 8 µs", _period_attack, seconds)


def full_flood(bus_spec: str, out: Path, seconds: float = FLOOD_S) -> dict:
    """A stranger's well-formed injections, as an amplifier sends them (the legitimate sample period,
    200 samples), on the unused ids 1-7, each preceded by a reset of its id (the default policy allows
    resets), so that every one is a cold start: as many as the rest of the bus carries."""
    return under_attack(bus_spec, out, "full-flood", f"{seconds:g} s of {FULL_PER_S:.0f}/s reset + full injection, "
                        "ids 1-7, 500 ns", _full_attack, seconds)


def sighup_burst(bus_spec: str, out: Path, seconds: float = 3.0) -> dict:
    """50 SIGHUPs in one second (the configuration file's log level toggled every other time)."""
    return under_attack(bus_spec, out, "sighup-burst", f"{SIGHUPS} SIGHUPs in {SIGHUP_S:g} s (log level toggled)",
                        _sighup_attack, seconds, config=RELOAD_CONFIG)


def command_flood(bus_spec: str, out: Path, seconds: float = FLOOD_S) -> dict:
    """1,000 reset commands a second on the unused id 5 (the default policy applies resets)."""
    return under_attack(bus_spec, out, "command-flood", f"{seconds:g} s of {COMMANDS_PER_S:.0f}/s reset commands, id 5",
                        _command_attack, seconds)


HAZARD_READY_S = 5.0   # a hazard may not delay the start beyond this (READY, from the process's start)
HAZARDS = ("state file a link outside", "rejected file a link outside", "state file a FIFO",
           "state file a link to /dev/zero", "state file 100 MB (sparse)", "second daemon on the directory")


def _hazard(kind: str, state: Path, outside: Path) -> None:
    """Lay one hazard in the (empty) state directory ``state``."""
    name = "estimator-state.json"
    if kind == HAZARDS[0]:
        (state / name).symlink_to(outside)
    elif kind == HAZARDS[1]:
        (state / name).write_text("{not json")
        (state / (name + ".rejected")).symlink_to(outside)
    elif kind == HAZARDS[2]:
        os.mkfifo(state / name)
    elif kind == HAZARDS[3]:
        (state / name).symlink_to("/dev/zero")
    elif kind == HAZARDS[4]:
        with open(state / name, "wb") as f:
            f.truncate(100 << 20)


def state_dir_hazards(bus_spec: str, out: Path) -> dict:
    """Each hazard in a state directory of its own: the daemon starts (READY, time to it), writes nothing
    outside, logs one line about it; a second daemon on a held directory exits non-zero naming the holder."""
    results = []
    for kind in HAZARDS:
        state = out / f"hazard-{HAZARDS.index(kind)}"
        shutil.rmtree(state, ignore_errors=True)
        state.mkdir(parents=True)
        outside = out / f"outside-{HAZARDS.index(kind)}.txt"
        outside.write_text("precious")
        _hazard(kind, state, outside)
        row: dict = {"hazard": kind}
        log_path = out / f"hazard-{HAZARDS.index(kind)}.log"
        d = DaemonProcess(bus_spec, log_path, state_dir=state).start()
        try:
            t0 = time.monotonic()
            ready = d.notify.wait_for("READY=1", 60, d.alive)
            row["ready_s"] = time.monotonic() - t0 if ready else None
            if kind == HAZARDS[5] and ready:
                t1 = time.monotonic()
                r = subprocess.run([sys.executable, "-m", "estimator", "run", "--bus", bus_spec, "--state-dir", str(state)],
                                   cwd=REPO, capture_output=True, text=True, timeout=120)
                row.update(second_exit=r.returncode, second_line=r.stderr.strip().splitlines()[-1] if r.stderr else "",
                           second_s=time.monotonic() - t1, names_holder=f"pid {d.pid}" in r.stderr)
            row["rss_mb"] = rss_mb(d.pid)
        finally:
            row["daemon_exit"] = d.stop()
        text = log_path.read_text(errors="replace")
        row["warnings"] = sum(1 for line in text.splitlines() if "WARNING" in line)
        row["outside_untouched"] = outside.read_text() == "precious" and not outside.is_symlink()
        results.append(row)
    return {"fault": "state-directory hazards", "hazards": results}


ROWS: dict[str, Callable[[str, Path], dict]] = {"periods": periods, "stall": stall, "flood": flood, "poisoned-state": poisoned_state, "commands": commands,
        "state-dir": state_dir_hazards, "period-flood": period_flood, "full-flood": full_flood,
        "sighup-burst": sighup_burst, "command-flood": command_flood}
ATTACKS = ("period-flood", "full-flood", "sighup-burst", "command-flood")   # rows of :func:`under_attack`
ATTACK_P99_MS = 20.0      # the legitimate injector's p99 under any attack
SIGHUP_STALL_MS = 20.0    # and its worst latency during a SIGHUP burst
COMMAND_LOG_KB = 64.0     # the log's growth under the command flood


def run_all(out: Path, bus: str | None = None, only: tuple[str, ...] = ()) -> dict:
    """Every fault (or the ``only`` ones, by :data:`ROWS` name) on one bus (a loopback hub unless
    ``bus`` or vcan0)."""
    out = out.resolve()   # the daemons run in another working directory
    out.mkdir(parents=True, exist_ok=True)
    unknown = [n for n in only if n not in ROWS]
    if unknown:
        raise ValueError(f"unknown reliability row(s) {', '.join(unknown)}; choose from {', '.join(ROWS)}")
    spec, hub = resolve_bus(bus, out)
    try:
        rows = {name: fn(spec, out) for name, fn in ROWS.items() if not only or name in only}
    finally:
        if hub is not None:
            hub.stop()
    return {"benchmark": "reliability", "bus": spec, "rows": rows}


def _attack_line(r: dict) -> str:
    extra = []
    if r["shed"]:
        extra.append(f"shed {r['shed']}")
    if r["commands_applied"]:
        extra.append(f"commands applied {r['commands_applied']}")
    return (f"legitimate: {r['legit_estimated']}/{r['legit_sent']} estimated, p99 {r['legit_p99_ms']:.1f} ms (max "
            f"{r['legit_max_ms']:.1f}); attacker {r['attacker_sent']} sent, {r['attacker_counted']} counted"
            + "".join(f", {e}" for e in extra) + f"; frames dropped {r['dropped']}; log +{r['log_growth_kb']:.0f} KB; "
            f"memory +{r['rss_growth_mb']:.0f} MB; exit {r['daemon_exit']}")


_LINES = {   # what each fault's row says, after the fault
    "periods": lambda p: (f"published {p['published']}/{p['injections']}, RSS {p['rss_first_mb']:.0f} -> "
                          f"{p['rss_max_mb']:.0f} MB (+{p['rss_growth_mb']:.1f}), heartbeat gap max "
                          f"{p['heartbeat_max_gap_s']:.2f} s, exit {p['daemon_exit']}"),
    "stall": lambda s: (f"live accepted {s['live_accepted']}/{s['injections']} (timeouts {s['live_timeouts']}), "
                        f"replay accepted {s['replay_accepted']}, exit {s['daemon_exit']}"),
    "flood": lambda f: (f"malformed {f['malformed']}, unknown commands {f['unknown_commands']}, good after: "
                        f"{f['good_estimated']}/{f['good_after']}, RSS {f['rss_mb']:.0f} MB, exit {f['daemon_exit']}"),
    "poisoned-state": lambda st: (f"published {st['published']}/{st['estimates']}, good entry kept "
                                  f"{st['restored_good']}, original kept {st['kept_copy']}, exit {st['daemon_exit']}"),
    "commands": lambda c: f"refused {c['refused']}, unknown {c['unknown']}, exit {c['daemon_exit']}",
}


def format_report(rep: dict) -> str:
    """One line per fault: what was sent, what the daemon did, what was lost."""
    lines = [f"reliability on {rep['bus']}"]
    rows = rep["rows"]
    for name, line in _LINES.items():
        if name in rows:
            lines.append(f"  {rows[name]['fault']:<58} {line(rows[name])}")
    for h in rows.get("state-dir", {}).get("hazards", []):
        ready = f"READY in {h['ready_s']:.1f} s" if h["ready_s"] is not None else "never READY"
        extra = (f", second daemon exit {h['second_exit']} in {h['second_s']:.1f} s ('{h['second_line'][:70]}')"
                 if "second_exit" in h else "")
        lines.append(f"  {'state dir: ' + h['hazard']:<58} {ready}, warnings {h['warnings']}, outside untouched "
                     f"{h['outside_untouched']}, RSS {h['rss_mb']:.0f} MB{extra}, exit {h['daemon_exit']}")
    for name in ATTACKS:
        if name in rows:
            lines.append(f"  {rows[name]['fault']:<58} {_attack_line(rows[name])}")
    return "\n".join(lines)


def _attack_failures(name: str, r: dict) -> list[str]:
    out = []
    if not (r["legit_p99_ms"] <= ATTACK_P99_MS and r["legit_estimated"] == r["legit_sent"]):
        out.append(f"{name}: legitimate p99 {r['legit_p99_ms']:.1f} ms, {r['legit_estimated']}/{r['legit_sent']} "
                   f"estimated")
    if r["rss_growth_mb"] > 50:
        out.append(f"{name}: memory +{r['rss_growth_mb']:.0f} MB")
    if name in ("period-flood", "full-flood") and r["attacker_counted"] < r["attacker_sent"]:
        out.append(f"{name}: attacker {r['attacker_counted']}/{r['attacker_sent']} counted")
    if name == "sighup-burst" and r["legit_max_ms"] > SIGHUP_STALL_MS:
        out.append(f"{name}: the legitimate injector stalled {r['legit_max_ms']:.0f} ms")
    if name == "command-flood" and (r["commands_applied"] < r["attacker_sent"] or r["log_growth_kb"] > COMMAND_LOG_KB):
        out.append(f"{name}: {r['commands_applied']}/{r['attacker_sent']} commands counted, log +"
                   f"{r['log_growth_kb']:.0f} KB")
    return out


def failures(rep: dict) -> list[str]:
    """What makes the bench exit 1."""
    rows = rep["rows"]
    out = []
    p = rows.get("periods")
    if p and (p["rss_growth_mb"] >= 50 or p["heartbeat_max_gap_s"] >= 2.0 or p["published"] < p["injections"]):
        out.append("sample periods: memory, heartbeat or handling")
    s = rows.get("stall")
    if s and (s["live_accepted"] != s["replay_accepted"] or not s["replay_ok"]):
        out.append("stall: live != replay")
    f = rows.get("flood")
    if f and f["good_estimated"] != f["good_after"]:
        out.append("flood: good injections lost")
    st = rows.get("poisoned-state")
    if st and (st["published"] < st["estimates"] or not st["restored_good"] or not st["kept_copy"]):
        out.append("state: not served or not kept")
    c = rows.get("commands")
    if c and c["refused"] < 2:
        out.append("commands: not counted")
    for h in rows.get("state-dir", {}).get("hazards", []):
        if h["ready_s"] is None or h["ready_s"] > HAZARD_READY_S or not h["outside_untouched"] or h["daemon_exit"] != 0:
            out.append(f"state dir {h['hazard']}: not served safely")
        if "second_exit" in h and (h["second_exit"] == 0 or not h["names_holder"]):
            out.append("a second daemon on the state directory was not refused")
        if h["hazard"] != HAZARDS[5] and h["warnings"] != 1:
            out.append(f"state dir {h['hazard']}: {h['warnings']} warnings (one expected)")
    for name in ATTACKS:
        if name in rows:
            out += _attack_failures(name, rows[name])
    if any(row.get("daemon_exit", 0) != 0 for row in rows.values()):
        out.append("a daemon did not exit 0")
    return out
