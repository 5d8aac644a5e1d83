"""A synthetic production lot for the fleet path: seeded, with truth (``python -m sim_bench lot``).

Series spread: N_u ~ 17.5 ± 0.3 N/V at the measuring temperature,
L_h ~ 3.5 ± 0.6 µm (1 sigma), preload 28 N + up to 10 N rail share. About 2 % of the injectors are bad
(L_h 2.5-3.5 µm above the spread: a worn or mis-set valve) and 10 % are measured on the hysteresis plant
(model mismatch). Each injector gets ``injections`` CSV traces one second apart in ``traces/``
(``serial``, ``time_s`` metadata: the fleet command carries its state across them), or with
``captures`` one BLF capture ``captures/<serial>.blf`` of its injections one second apart (the frames
the injector node sends, at 0.2 ms intervals: a HIL campaign's or a test-fleet's log, replayed with
the daemon's pipeline); ``truth.csv`` beside that folder holds the truth.
"""

from __future__ import annotations

import csv
from pathlib import Path

import can
import numpy as np

from estimator.codec.injection_frames import injection_frames
from estimator.codec.records import Codec
from estimator.io.captures import to_message
from estimator.io.traces import write_trace
from estimator.model.drive import Drive, StandardDrive
from estimator.model.parameters import NOMINAL_PRELOAD_N
from estimator.pipeline.config import EstimatorConfig
from sim_bench.hardware.plant import Measurement, Plant, PlantConfig
from sim_bench.hardware.series_life import LotSpec, draw_lot

NU_MEAN, NU_SD = 17.5, 0.3
LH_MEAN, LH_SD = 3.5, 0.6
BAD_FRACTION, MISMATCH_FRACTION = 0.02, 0.10
CAPTURE_FRAME_DT_S = 2e-4     # between the frames of one injection in a capture
CAPTURE_SLOTS = EstimatorConfig.max_injectors   # injector ids on the bus the daemon accepts by default; serial i uses i % slots


def make_lot(out: Path, injectors: int, injections: int = 1, seed: int = 11, window_s: float = 100e-6,
             drive: Drive | None = None, captures: bool = False, series: LotSpec | None = None) -> Path:
    """Write the lot's traces into ``out`` (one file per injection; with ``captures`` one BLF capture per
    injector) and ``truth.csv``; returns the truth path. Every injector is driven with ``drive``
    (default the standard drive). The truth and the measurements do not depend on ``captures``.
    ``series``: the injectors are series parts of that lot (:mod:`sim_bench.hardware.series_life`: their own
    structure, one amplifier chain, warm-up, rail-pressure walk, wear, swaps, parts beyond tolerance)."""
    if not (1 <= injectors <= 100_000 and 1 <= injections <= 1000):
        raise ValueError(f"--injectors {injectors} must be 1..100000 and --injections {injections} 1..1000")
    if series is not None:
        return _series_lot(out, injectors, injections, seed, series, captures)
    rng = np.random.default_rng(seed)
    folder = out / ("captures" if captures else "traces")
    folder.mkdir(parents=True, exist_ok=True)
    codec = Codec() if captures else None
    drive = drive or StandardDrive()
    plants = {m: Plant(PlantConfig(drive=drive, window_s=window_s, mismatch=m)) for m in (False, True)}
    truth_path = out / "truth.csv"
    with open(truth_path, "w", newline="") as tf:
        w = csv.writer(tf)
        w.writerow(["serial", "nu_n_per_v", "lh_um", "bad", "mismatch"])
        for i in range(injectors):
            serial = f"INJ-{i:05d}"
            nu = float(np.clip(rng.normal(NU_MEAN, NU_SD), 15.2, 20.8))
            bad = bool(rng.random() < BAD_FRACTION)
            lh = float(np.clip(rng.normal(LH_MEAN, LH_SD), 0.5, 7.0)) + (float(rng.uniform(2.5, 3.5)) if bad else 0.0)
            mismatch = bool(rng.random() < MISMATCH_FRACTION)
            w.writerow([serial, f"{nu:.4f}", f"{lh:.4f}", int(bad), int(mismatch)])
            writer = can.Logger(str(folder / f"{serial}.blf")) if captures else None
            try:
                for k in range(injections):
                    f_open = NOMINAL_PRELOAD_N + float(rng.uniform(0, 10))
                    m = plants[mismatch].measure(nu, lh * 1e-6, f_open, rng)
                    if writer is not None and codec is not None:
                        frames = injection_frames(codec, i % CAPTURE_SLOTS, k, m.dt_s, m.current_a, m.voltage_v,
                                                  preload_force_n=f_open)
                        t_bus = 1000.0 + k                          # s; then a frame every 0.2 ms
                        for fr in frames:
                            t_bus += CAPTURE_FRAME_DT_S
                            writer.on_message_received(to_message(fr, timestamp=t_bus))
                    else:
                        t_s = np.arange(m.current_a.size) * m.dt_s
                        write_trace(folder / f"{serial}_{k:03d}.csv",
                                    {"t_s": t_s, "current_A": m.current_a, "voltage_V": m.voltage_v},
                                    {"serial": serial, "time_s": float(k), "counter": k,
                                     "preload_force_n": round(f_open, 4), "true_nu_n_per_v": round(nu, 6),
                                     "true_lh_um": round(lh, 6)})
            finally:
                if writer is not None:
                    writer.stop()
    return truth_path


def _write_injection(folder: Path, serial: str, slot: int, k: int, m: Measurement, writer: can.Listener | None,
                     codec: Codec | None, truth: dict) -> None:
    """One injection: into the injector's capture (``writer``), else as a CSV trace with its truth."""
    if writer is not None and codec is not None:
        t_bus = 1000.0 + k                          # s; then a frame every 0.2 ms
        for fr in injection_frames(codec, slot, k % 256, m.dt_s, m.current_a, m.voltage_v, preload_force_n=m.f_open_n):
            t_bus += CAPTURE_FRAME_DT_S
            writer.on_message_received(to_message(fr, timestamp=t_bus))
        return
    t_s = np.arange(m.current_a.size) * m.dt_s
    write_trace(folder / f"{serial}_{k:03d}.csv", {"t_s": t_s, "current_A": m.current_a, "voltage_V": m.voltage_v},
                {"serial": serial, "time_s": float(k), "counter": k, "preload_force_n": round(m.f_open_n, 4),
                 "true_nu_n_per_v": round(truth["nu_true"], 6), "true_lh_um": round(truth["lh_true_um"], 6)})


def _series_lot(out: Path, injectors: int, injections: int, seed: int, spec: LotSpec, captures: bool) -> Path:
    """:func:`make_lot` of series parts: truth.csv names each part, whether it is beyond tolerance and
    where it was swapped."""
    folder = out / ("captures" if captures else "traces")
    folder.mkdir(parents=True, exist_ok=True)
    codec = Codec() if captures else None
    truth_path = out / "truth.csv"
    rng = np.random.default_rng(seed + 1)
    with open(truth_path, "w", newline="") as tf:
        w = csv.writer(tf)
        w.writerow(["serial", "nu_n_per_v", "lh_um", "bad", "mismatch", "beyond_tolerance", "swap_at", "part"])
        for life in draw_lot(injectors, seed, spec):
            serial = f"INJ-{life.position:05d}"
            nu0, lh0 = life.truth(0, injections, 0.0)
            w.writerow([serial, f"{nu0:.4f}", f"{lh0:.4f}", 0, 0, int(life.beyond[-1]),
                        life.swap_at if life.swap_at is not None else "", life.parts[-1].describe()])
            writer = can.Logger(str(folder / f"{serial}.blf")) if captures else None
            try:
                for k in range(injections):
                    m, truth = life.measure(k, injections, rng)
                    _write_injection(folder, serial, life.position % CAPTURE_SLOTS, k, m, writer, codec, truth)
            finally:
                if writer is not None:
                    writer.stop()
    return truth_path
