"""The simulated injector node: the hybrid model on the bus as a stand-in for an amplifier.

One scheduler loop on absolute monotonic deadlines (injection k of the whole node is due at
t0 + k / (rate * injectors), injectors in turn); no thread per frame. Per injection it sends the
header, the sample blocks, the trailer and SimTruth, with faults injected at the scenario's rates.
It reports (rate-limited) when it falls behind its deadlines.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import Counter
from dataclasses import dataclass, field, replace

import numpy as np

from estimator.codec.frame import Frame
from estimator.codec.injection_frames import injection_frames
from estimator.codec.records import Codec, DriveCorrection, DriveCorrectionRow, SimTruth
from estimator.drive.correction import Correction, Table
from sim_bench.hardware.amplifiers import Amplifier, Scaled
from sim_bench.hardware.plant import Measurement, Plant, PlantConfig
from sim_bench.hardware.scenarios import Scenario

log = logging.getLogger(__name__)


@dataclass
class NodeStats:
    """What the node did: counts of injections, frames and every injected fault."""

    injections: int = 0
    frames: int = 0
    faults: Counter = field(default_factory=Counter)
    late: int = 0
    max_lateness_s: float = 0.0
    send_errors: int = 0

    def to_dict(self) -> dict:
        return {"injections": self.injections, "frames": self.frames, "faults": dict(self.faults),
                "late": self.late, "max_lateness_ms": round(self.max_lateness_s * 1e3, 3),
                "send_errors": self.send_errors}


class InjectionSource:
    """Simulated measurements per injector and time, seeded (reproducible)."""

    def __init__(self, scenario: Scenario, seed: int) -> None:
        self.scenario = scenario
        self.rng = np.random.default_rng(seed)
        self.plant = Plant(PlantConfig(drive=scenario.drive, mismatch=scenario.mismatch, window_s=scenario.window_s))
        self._pool: dict[int, list[tuple[Measurement, float]]] = {}
        # drive corrections the estimator published (``--apply-corrections``), applied as an amplifier
        # would: the standard drive's plateau current scaled, its start of charging offset
        self.corrections: dict[int, Correction] = {}
        self.offset_us: dict[int, float] = {}     # the offset applied to each injector's last injection
        # DriveCorrectionTable rows: (rows, preload N, scale, offset µs, σ stroke µm, σ opening µs) by row
        self.table_rows: dict[int, dict[int, tuple[int, float, float, float, float, float]]] = {}
        self.applied = 0                          # injections driven with a correction
        self.lives = []
        if scenario.series_lot:
            from sim_bench.hardware.series_life import LotSpec, draw_lot

            amp = Amplifier("scenario", scenario.drive)   # the scenario's standard drive, scaled by a correction
            spec = LotSpec(swap_at=scenario.swap_at, swapped=(1,), window_s=scenario.window_s, amplifier=amp)
            self.lives = draw_lot(scenario.injectors, seed, spec)
            self._life_length = int(round(scenario.seconds * scenario.rate_hz))

    def measure(self, injector: int, n: int, t: float) -> tuple[Measurement, float]:
        """The measurement of injection n of an injector at time t (s), and the temperature (degC)."""
        sc = self.scenario
        if sc.pool:
            pool = self._pool.setdefault(injector, [])
            if len(pool) < sc.pool:
                pool.append(self._fresh(injector, n, t))
            return pool[n % sc.pool]
        return self._fresh(injector, n, t)

    def _scale_for(self, injector: int):
        """The plateau current scale at a preload force (N) from the injector's correction, recording
        the offset applied; None without a valid correction (the standard drive)."""
        corr = self.corrections.get(injector)
        self.offset_us[injector] = 0.0
        if corr is None or not corr.valid:
            return None

        def scale_for(f_open_n: float) -> float:
            scale, offset = corr.at(f_open_n)
            self.offset_us[injector] = offset
            self.applied += 1
            return scale
        return scale_for

    def _fresh(self, injector: int, n: int, t: float) -> tuple[Measurement, float]:
        scale_for = self._scale_for(injector)
        if self.lives:   # a series part of the lot: its own structure, warm-up and rail pressure
            return self.lives[injector].measure(n, self._life_length, self.rng, scale_for)[0], float("nan")
        tr = self.scenario.truth(injector, n, t, self.rng)
        drive = Scaled(self.plant.cfg.drive, scale_for(tr.f_open_n)) if scale_for is not None else None
        return self.plant.measure(tr.nu_n_per_v, tr.lh_um * 1e-6, tr.f_open_n, self.rng, drive), tr.temperature_c


def _table(rows: dict[int, tuple[int, float, float, float, float, float]]) -> Table:
    """The drive-correction table once every row of it has arrived (else none: the sensitivities)."""
    if not rows:
        return ()
    n = next(iter(rows.values()))[0]
    if n < 2 or any(i not in rows for i in range(n)):
        return ()
    return tuple(rows[i][1:] for i in range(n))


def apply_faults(frames: list[Frame], sc: Scenario, rng: np.random.Generator, stats: NodeStats) -> list[Frame]:
    """Drop, duplicate, reorder or corrupt frames at the scenario's per-frame rates (counted)."""
    f = sc.faults
    if not (f.drop or f.duplicate or f.reorder or f.corrupt):
        return frames
    out: list[Frame] = []
    for fr in frames:
        u = rng.random(4)
        if u[0] < f.drop:
            stats.faults["drop"] += 1
            continue
        if u[3] < f.corrupt and fr.is_fd and len(fr.data) == 64:
            d = bytearray(fr.data)
            d[int(rng.integers(3, 63))] ^= 1 << int(rng.integers(0, 8))
            fr = Frame(fr.arbitration_id, bytes(d), fr.is_fd)
            stats.faults["corrupt"] += 1
        out.append(fr)
        if u[1] < f.duplicate:
            out.append(fr)
            stats.faults["duplicate"] += 1
    for i in range(len(out) - 1):
        if rng.random() < f.reorder:
            out[i], out[i + 1] = out[i + 1], out[i]
            stats.faults["reorder"] += 1
    return out


def nan0(x: float) -> float:
    """NaN -> 0 for the wire (SimTruth has no validity bits; 0 µs means 'did not happen')."""
    return x if math.isfinite(x) else 0.0


class InjectorNode:
    """Sends the scenario's injections on a bus (anything with ``send(Frame)``)."""

    def __init__(self, send, scenario: Scenario, seed: int = 0, codec: Codec | None = None,
                 clock=time.monotonic) -> None:
        self.send = send
        self.clock = clock                  # monotonic seconds; a test may pass its own
        self.scenario = scenario
        self.codec = codec or Codec()
        self.source = InjectionSource(scenario, seed)
        self.fault_rng = np.random.default_rng(seed + 1_000_003)
        self.stats = NodeStats()
        self.counters = [0] * scenario.injectors

    def take_correction(self, rec: DriveCorrection | DriveCorrectionRow) -> None:
        """A DriveCorrection or a row of its table from the bus: the injector's next injections are
        driven with it, the table's rows interpolated at each injection's preload force once every row
        has arrived (the SimTruth opening instant then counts from the standard drive's start of charging)."""
        if self.scenario.pool:
            return   # pooled measurements are replayed, not simulated again: nothing to correct
        iid = rec.injector_id
        rows = self.source.table_rows.setdefault(iid, {})
        if isinstance(rec, DriveCorrectionRow):
            if rows and next(iter(rows.values()))[0] != rec.rows:
                rows.clear()      # a table of another length: start again
            rows[rec.row] = (rec.rows, rec.preload_n, rec.scale, rec.offset_us, rec.sigma_stroke_um,
                             rec.sigma_opening_us)
            rec_c = self.source.corrections.get(iid)
            if rec_c is not None:
                self.source.corrections[iid] = replace(rec_c, table=_table(rows))
            return
        self.source.corrections[iid] = Correction(
            rec.scale, rec.offset_us, rec.stroke_um, rec.opening_us, rec.sigma_stroke_um, rec.sigma_opening_us,
            scale_per_kn=rec.scale_per_kn, offset_per_kn_us=rec.offset_per_kn_us, preload_n=rec.preload_n,
            valid=rec.state in (1, 2), held=rec.state == 2, at_limit=bool(rec.at_limit),
            trust_limited=bool(rec.trust_limited), table=_table(rows))

    def frames_for(self, injector: int, n: int, t: float) -> list[Frame]:
        """All frames of injection n of an injector at time t, faults applied, SimTruth last."""
        sc = self.scenario
        m, temp = self.source.measure(injector, n, t)
        dec = max(1, sc.decimation)
        cnt = self.counters[injector]
        self.counters[injector] = (cnt + 1) % 256
        frames = injection_frames(self.codec, injector, cnt, m.dt_s * dec, m.current_a[::dec], m.voltage_v[::dec],
                                  m.f_open_n, temp)
        frames = apply_faults(frames, sc, self.fault_rng, self.stats)
        truth = SimTruth(injector, cnt, m.nu_n_per_v, m.lh_m * 1e6, nan0(m.t_contact_s * 1e6),
                         nan0(m.t_open_s * 1e6 + self.source.offset_us.get(injector, 0.0)), nan0(m.stroke_m * 1e6), temp, m.f_open_n)
        frames.append(self.codec.encode(truth))
        return frames

    def run(self, stop: threading.Event, seconds: float | None = None, count: int | None = None) -> NodeStats:
        """The scheduler loop; returns the statistics. ``count``: injections per injector."""
        sc = self.scenario
        self.source.plant.warm_up()
        period = 1.0 / (sc.rate_hz * sc.injectors)
        duration = seconds if seconds is not None else sc.seconds
        t0 = self.clock() + 0.05
        next_stall = sc.faults.stall_every_s or math.inf
        k = 0
        last_warn = -math.inf
        while not stop.is_set():
            due = t0 + k * period
            elapsed = due - t0
            if elapsed >= duration or (count is not None and k >= count * sc.injectors):
                break
            if elapsed >= next_stall:
                stop.wait(sc.faults.stall_s)           # the bus stalls: nothing is sent
                self.stats.faults["stall"] += 1
                next_stall += sc.faults.stall_every_s
            now = self.clock()
            if due > now:
                if stop.wait(due - now):
                    break
            else:
                lateness = now - due
                self.stats.max_lateness_s = max(self.stats.max_lateness_s, lateness)
                if lateness > period:
                    self.stats.late += 1
                    if now - last_warn > 5.0:
                        log.warning("node behind its schedule by %.1f ms (%d late injections so far)",
                                    lateness * 1e3, self.stats.late)
                        last_warn = now
            inj = k % sc.injectors
            for fr in self.frames_for(inj, k // sc.injectors, elapsed):
                try:
                    self.send(fr)
                    self.stats.frames += 1
                except OSError as exc:   # includes can.CanOperationError
                    self.stats.send_errors += 1
                    if self.stats.send_errors in (1, 10, 100, 1000):
                        log.error("send error: %s (%d so far)", exc, self.stats.send_errors)
            self.stats.injections += 1
            k += 1
        return self.stats

    def summary_json(self) -> str:
        """One JSON line with the node's statistics."""
        return json.dumps({"node": {**self.stats.to_dict(), "corrections_applied": self.source.applied},
                           "scenario": self.scenario.name})
