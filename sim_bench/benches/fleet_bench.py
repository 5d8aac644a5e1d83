"""``python -m sim_bench fleet-bench``: a synthetic lot through the fleet command at 1 and 2 workers:
throughput, scaling, per-injection cost, accuracy against the truth and bad-injector detection."""

from __future__ import annotations

import csv
import math
import time
from pathlib import Path

import numpy as np

from estimator.fleet.run import run_fleet
from sim_bench.hardware.lot import make_lot


def _serial(ident: str, truth: dict) -> str:
    """The lot serial of a row's or a summary's injector (a trace's key, or a capture's path): the key
    itself, else the capture's file name."""
    return ident if ident in truth else Path(ident).stem


def simulation_floor(rows: list[dict], kernel_seconds: float = 1.0) -> dict:
    """How much of a worker's time the simulations alone must take: the simulations per injection
    (the rows' ``evaluations``: every candidate simulated, the valve prediction as one) times the
    simulator's best cost per candidate (:func:`sim_bench.benches.speed.measure` at batch 256, 100 µs window,
    timed for ``kernel_seconds``), and the injections/s per core that leaves at most, whatever the
    rest of the pipeline costs and however the candidates of several injectors were batched."""
    from sim_bench.benches.speed import measure

    ev = np.array([r["evaluations"] for r in rows if isinstance(r.get("evaluations"), (int, float))], dtype=float)
    us = measure((256,), seconds=kernel_seconds)["results"][0]["us_per_candidate"]
    mean = float(ev.mean()) if ev.size else math.nan
    return {"simulations_per_injection_mean": mean,
            "simulations_per_injection_median": float(np.median(ev)) if ev.size else math.nan,
            "kernel_us_per_simulation_batch256": us, "simulation_ms_per_injection": mean * us / 1e3,
            "simulation_bound_per_core_per_s": 1e6 / (mean * us) if ev.size else math.nan}


def run(out: Path, injectors: int = 1000, workers: tuple[int, ...] = (1, 2), seed: int = 11,
        injections: int = 1, captures: bool = False) -> dict:
    """Make the lot (once; ``injections`` traces per injector, carried through one tracker, or with
    ``captures`` one BLF capture per injector through the replay pipeline), run the fleet per worker
    count, score every row against truth.csv; ``simulation_floor`` of the last run's rows."""
    name = f"lot-{injectors}-{seed}" if injections == 1 else f"lot-{injectors}x{injections}-{seed}"
    lot = out / (name + ("-blf" if captures else ""))
    if not (lot / "truth.csv").exists():
        t0 = time.perf_counter()
        make_lot(lot, injectors, injections, seed, captures=captures)
        print(f"lot of {injectors} injectors x {injections} written in {time.perf_counter() - t0:.1f} s")
    with open(lot / "truth.csv", newline="") as f:
        truth = {r["serial"]: r for r in csv.DictReader(f)}
    report: dict = {"benchmark": "fleet", "injectors": injectors, "injections_per_injector": injections,
                    "inputs": "captures" if captures else "traces", "runs": []}
    for n in workers:
        t0 = time.perf_counter()
        tag = ("" if injections == 1 else f"-x{injections}") + ("-blf" if captures else "")
        res = run_fleet([str(lot / ("captures" if captures else "traces"))], out / f"fleet-{n}w{tag}.parquet",
                        workers=n)
        wall = time.perf_counter() - t0
        rows = [r for r in res.rows if r.get("status") != "error"]
        e_lh, e_nu, flagged_bad, flagged_good, bad = [], [], 0, 0, 0
        flags = {_serial(s["injector"], truth): s["outlier"] for s in res.summary}
        for r in rows:
            t = truth.get(_serial(r.get("injector_key") or r["source"], truth))
            if t is None or r.get("lh_um") is None or t["mismatch"] == "1":
                continue
            e_lh.append(r["lh_um"] - float(t["lh_um"]))
            e_nu.append(100 * (r["nu_n_per_v"] / float(t["nu_n_per_v"]) - 1))
        for serial, t in truth.items():
            bad += t["bad"] == "1"
            if flags.get(serial):
                flagged_bad += t["bad"] == "1"
                flagged_good += t["bad"] != "1"
        # from every worker ready to the last result (the cluster's start and its closing apart)
        work = max(res.seconds - res.seconds_start - res.seconds_stop, 1e-9)
        run_ = {"workers": n, "seconds_tasks": res.seconds, "seconds_wall": wall, "injections": len(rows),
                "seconds_start": res.seconds_start, "seconds_stop": res.seconds_stop, "seconds_work": work,
                "work_per_worker_per_s": len(rows) / work / n,
                "errors": res.errors, "injections_per_s": len(rows) / res.seconds,
                "per_worker_per_s": len(rows) / res.seconds / n, "ms_per_injection_per_worker": 1e3 * res.seconds * n /
                max(len(rows), 1), "rms_lh_um": float(np.sqrt(np.mean(np.square(e_lh)))) if e_lh else math.nan,
                "max_abs_lh_um": float(np.max(np.abs(e_lh))) if e_lh else math.nan,
                "rms_nu_pct": float(np.sqrt(np.mean(np.square(e_nu)))) if e_nu else math.nan,
                "bad_injectors": bad, "bad_flagged": flagged_bad, "good_flagged": flagged_good}
        report["runs"].append(run_)
    report["simulation_floor"] = simulation_floor(rows)
    r1 = next((r for r in report["runs"] if r["workers"] == 1), None)
    for r in report["runs"]:
        r["scaling_efficiency"] = (r["injections_per_s"] / r1["injections_per_s"] / r["workers"]) if r1 else math.nan
        # the same once ready: the cluster's start (≈ 2 s) does not shrink with more workers
        r["scaling_efficiency_ready"] = (r["work_per_worker_per_s"] / r1["work_per_worker_per_s"]) if r1 else math.nan
    return report


def format_report(rep: dict) -> str:
    """The table."""
    per = rep.get("injections_per_injector", 1)
    if rep.get("inputs") == "captures":
        head = (f"a BLF capture of {per} injection{'s' if per > 1 else ''} each (the first a cold start"
                f"{', the rest warm updates' if per > 1 else ''})")
    else:
        head = ("one trace each (cold start per injection)" if per == 1 else
                f"{per} traces each (the first a cold start, the rest warm updates)")
    lines = [f"fleet-bench: {rep['injectors']} injectors, {head}",
             "  (inj/s over the whole run; 'start': cluster start and worker warm-up, 'stop': closing it, once"
             " per run; 'ready/worker': injections/s per worker from ready to the last result)",
             f"  {'workers':>7} {'inj/s':>8} {'per worker':>10} {'ms/inj':>7} {'start[s]':>8} {'stop[s]':>7} {'ready/worker':>12} "
             f"{'scaling':>7} {'ready':>5} {'L_h rms/max [µm]':>17} {'N_u rms [%]':>11} {'bad flagged':>11} {'good flagged':>12}"]
    for r in rep["runs"]:
        lines.append(f"  {r['workers']:>7} {r['injections_per_s']:>8.1f} {r['per_worker_per_s']:>10.1f} "
                     f"{r['ms_per_injection_per_worker']:>7.1f} {r['seconds_start']:>8.2f} {r['seconds_stop']:>7.2f} "
                     f"{r['work_per_worker_per_s']:>12.1f} {r['scaling_efficiency']:>7.2f} {r['scaling_efficiency_ready']:>5.2f} "
                     f"{r['rms_lh_um']:>8.3f}/{r['max_abs_lh_um']:<8.3f} {r['rms_nu_pct']:>11.3f} "
                     f"{r['bad_flagged']:>5}/{r['bad_injectors']:<5} {r['good_flagged']:>12}")
    fl = rep.get("simulation_floor")
    if fl:
        lines.append(f"  simulations per injection: mean {fl['simulations_per_injection_mean']:.1f}, median "
                     f"{fl['simulations_per_injection_median']:.0f}; at the simulator's best "
                     f"{fl['kernel_us_per_simulation_batch256']:.1f} µs each (batch 256) that alone is "
                     f"{fl['simulation_ms_per_injection']:.2f} ms per injection: at most "
                     f"{fl['simulation_bound_per_core_per_s']:.0f} injections/s per core")
    return "\n".join(lines)
