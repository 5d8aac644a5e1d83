"""``python -m estimator fleet --calibrate``: electrical calibrations of a lot on Dask, and the lot's
structural spread.

``per-injector``: every injector (traces grouped by their ``serial``/``injector_key`` metadata, as in
the fleet's estimation) gets its own calibration, one Dask task each, and its own parameter file
``<key>.toml``. ``per-lot``: all traces share one structure (each injection its own N_u and L_h), one
task, one ``lot.toml``. The report shows, per structural parameter, how the calibrated values spread
over the lot (median, robust spread, range, against the typical calibration standard deviation): a
parameter whose spread is well above its standard deviation really varies from part to part.
"""

from __future__ import annotations

import csv
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimator.errors import EstimatorError
from estimator.fleet.cluster import dask_client
from estimator.fleet.inputs import expand, group
from estimator.fleet.tasks import WORKER_ENV
from estimator.units import UM_PER_M, US_PER_S

MODES = ("per-injector", "per-lot")
MIN_INJECTIONS = 3


@dataclass
class LotCalibration:
    """One row per calibration (an injector, or the lot), the files written, what could not be read."""

    mode: str
    rows: list[dict]
    files: list[Path] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def refused(self) -> list[dict]:
        """Calibrations that failed or do not explain their batch."""
        return [r for r in self.rows if not r.get("adequate")]


def calibrate_group(key: str, paths: tuple[str, ...], params_path: str | None, tolerance: float,
                    trace_options: dict[str, Any]) -> dict:
    """One calibration (a Dask task): read the traces (a bad one is named and skipped), calibrate,
    return a JSON-ready row with the parameter file's text."""
    for k, v in WORKER_ENV.items():
        os.environ.setdefault(k, v)
    from estimator.ident.learning.electrical import calibrate_electrical
    from estimator.io.mdf import read_injections
    from estimator.model.parameters import load_parameters

    found = read_injections(list(paths), trace_options.get("current_channel"), trace_options.get("voltage_channel"),
                            trace_options.get("sample_period_s"))
    injections, skipped = found.injections, found.unreadable + found.unusable
    row: dict[str, Any] = {"key": key, "injections": len(injections), "skipped": skipped, "adequate": False}
    if len(injections) < MIN_INJECTIONS:
        row["error"] = f"{len(injections)} usable injection(s), at least {MIN_INJECTIONS} needed"
        return row
    t0 = time.perf_counter()
    try:
        res = calibrate_electrical(injections, load_parameters(params_path), tolerance=tolerance)
    except ValueError as exc:
        row["error"] = str(exc)
        return row
    row.update({"seconds": time.perf_counter() - t0, "adequate": res.adequate, "misfit_z": res.misfit_z,
                "rms_before_v": res.rms_before_v, "rms_after_v": res.rms_after_v,
                "factors": {n: float(f) for n, f in zip(res.names, res.factors)},
                "sigma_rel": {n: float(s) for n, s in zip(res.names, res.sigma_rel)},
                "chain_us": {n: getattr(res.params.chain, n) * US_PER_S for n in res.chain_sigma_us},
                "nu_rel_sigma": res.params.calibration.nu_rel_sigma,
                "lh_sigma_um": res.params.calibration.lh_sigma_m * UM_PER_M,
                "weak": res.weak, "warnings": res.warnings,
                "toml": res.params.to_toml(f"electrical calibration of {key} from {len(injections)} injections "
                                           f"(python -m estimator fleet --calibrate); RMS voltage residual "
                                           f"{res.rms_before_v * 1e3:.1f} mV before, {res.rms_after_v * 1e3:.1f} mV after")})
    return row


def run_lot_calibration(inputs: list[str], out_dir: Path, mode: str = "per-injector", params: Path | None = None,
                        tolerance: float = 0.10, workers: int | None = None, scheduler: str | None = None,
                        trace_options: dict[str, Any] | None = None) -> LotCalibration:
    """Calibrate the traces of ``inputs`` ``per-injector`` or ``per-lot`` on a Dask cluster; write the
    parameter files, ``calibration.csv``, ``structure-spread.txt`` and ``structure-spread.png`` into
    ``out_dir``."""
    if mode not in MODES:
        raise EstimatorError(f"--calibrate {mode!r}: use one of {', '.join(MODES)}")
    if not (isinstance(tolerance, (int, float)) and 0 < tolerance <= 1):
        raise EstimatorError(f"--tolerance {tolerance!r}: must be within (0, 1]")
    files, missing = expand(inputs)
    traces = [f for f in files if f.suffix.lower() != ".log" and f.suffix.lower() != ".blf"]
    if mode == "per-lot":
        jobs = [("lot", tuple(str(f) for f in traces))] if traces else []
    else:
        jobs = [(g.key, g.paths) for g in group(traces) if g.key is not None]
        unkeyed = [g.paths[0] for g in group(traces) if g.key is None]
        missing += [f"{p} (no serial/injector_key in its metadata: per-injector needs one)" for p in unkeyed]
    if not jobs:
        raise EstimatorError("no traces to calibrate in " + " ".join(inputs)
                             + ("" if mode == "per-lot" else " (per-injector needs serial=... metadata)"))
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = _compute(jobs, str(params) if params else None, tolerance, trace_options or {}, workers, scheduler)
    res = LotCalibration(mode, sorted(rows, key=lambda r: r["key"]), missing=missing,
                         seconds=time.perf_counter() - t0)
    res.files = write(res, out_dir)
    return res


def _compute(jobs: list[tuple[str, tuple[str, ...]]], params: str | None, tolerance: float,
             trace_options: dict[str, Any], workers: int | None, scheduler: str | None) -> list[dict]:
    from dask.distributed import as_completed

    with dask_client(workers, scheduler, most=len(jobs)) as client:
        futures = {client.submit(calibrate_group, key, paths, params, tolerance, trace_options, pure=False): key
                   for key, paths in jobs}
        rows = []
        for fut in as_completed(futures):
            try:
                rows.append(fut.result())
            except Exception as exc:   # a worker died on this calibration: reported, the others go on
                rows.append({"key": futures[fut], "adequate": False, "injections": 0, "skipped": [],
                             "error": f"task failed: {type(exc).__name__}: {exc}"[:300]})
        return rows


def spread(rows: list[dict]) -> list[dict]:
    """Per structural parameter over the adequate calibrations: median factor, robust spread
    (1.4826 MAD, %), range and the median calibration standard deviation (%)."""
    good = [r for r in rows if r.get("adequate")]
    if not good:
        return []
    out = []
    for name in good[0]["factors"]:
        f = np.array([r["factors"][name] for r in good])
        sd = np.array([r["sigma_rel"][name] for r in good])
        med = float(np.median(f))
        mad = float(1.4826 * np.median(np.abs(f - med)))
        out.append({"parameter": name, "median": med, "spread_pct": 100 * mad / med,
                    "min": float(f.min()), "max": float(f.max()), "sigma_pct": float(100 * np.median(sd)),
                    "varies": bool(len(good) >= 3 and mad / med > 3 * np.median(sd))})
    return out


def format_report(res: LotCalibration) -> str:
    """The lot's calibrations and its structural spread as text."""
    good = [r for r in res.rows if r.get("adequate")]
    lines = [f"fleet calibration ({res.mode}): {len(res.rows)} calibration(s), {len(good)} explain their batch, "
             f"{len(res.refused)} refused; {res.seconds:.1f} s"]
    for r in res.rows:
        if r.get("adequate"):
            lines.append(f"  {r['key']}: {r['injections']} injections, residual {r['rms_before_v'] * 1e3:.0f} -> "
                         f"{r['rms_after_v'] * 1e3:.0f} mV, leaves N_u {100 * r['nu_rel_sigma']:.2f} %, "
                         f"L_h {r['lh_sigma_um']:.3f} µm")
        else:
            why = r.get("error") or f"does not explain its batch (residual structure {r.get('misfit_z', math.nan):.0f} sd)"
            lines.append(f"  {r['key']}: refused: {why}")
        lines += [f"    skipped {s}" for s in r.get("skipped", [])]
    lines += [f"  not used: {m}" for m in res.missing]
    table = spread(res.rows)
    if table:
        lines.append(f"structural spread over {len(good)} calibration(s) (factor on Tables 1-2):")
        lines.append(f"  {'parameter':<22} {'median':>7} {'spread':>7} {'min':>7} {'max':>7} {'calib sd':>9}")
        for t in table:
            lines.append(f"  {t['parameter']:<22} {t['median']:7.3f} {t['spread_pct']:6.1f}% {t['min']:7.3f} "
                         f"{t['max']:7.3f} {t['sigma_pct']:8.2f}%{'  varies across the lot' if t['varies'] else ''}")
    return "\n".join(lines)


def write(res: LotCalibration, out_dir: Path) -> list[Path]:
    """Each adequate calibration's parameter file, ``calibration.csv``, the report and its plot."""
    files = []
    for r in res.rows:
        if r.get("adequate"):
            path = out_dir / f"{_safe(r['key'])}.toml"
            path.write_text(r["toml"])
            files.append(path)
    names = next((list(r["factors"]) for r in res.rows if r.get("factors")), [])
    table = out_dir / "calibration.csv"
    with table.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["key", "injections", "adequate", "rms_before_v", "rms_after_v", "nu_rel_sigma", "lh_sigma_um",
                    *names, "error"])
        for r in res.rows:
            w.writerow([r["key"], r["injections"], r.get("adequate", False), r.get("rms_before_v", ""),
                        r.get("rms_after_v", ""), r.get("nu_rel_sigma", ""), r.get("lh_sigma_um", ""),
                        *[r.get("factors", {}).get(n, "") for n in names], r.get("error", "")])
    files.append(table)
    report = out_dir / "structure-spread.txt"
    report.write_text(format_report(res) + "\n")
    files.append(report)
    plot = plot_spread(res, out_dir / "structure-spread.png")
    if plot is not None:
        files.append(plot)
    return files


def plot_spread(res: LotCalibration, path: Path) -> Path | None:
    """Each structural parameter's calibrated factors over the lot (a dot per injector) with its
    typical calibration standard deviation; None without matplotlib or without two calibrations."""
    good = [r for r in res.rows if r.get("adequate")]
    if len(good) < 2:
        return None
    try:
        from estimator.plots.figures import pyplot, save
        plt = pyplot()
    except ImportError:
        return None
    names = list(good[0]["factors"])
    fig, ax = plt.subplots(figsize=(10, 4))
    for i, n in enumerate(names):
        f = [100 * (r["factors"][n] - 1) for r in good]
        ax.plot(np.full(len(f), i) + np.linspace(-0.15, 0.15, len(f)), f, "o", ms=3, color="C0")
        sd = 100 * float(np.median([r["sigma_rel"][n] for r in good]))
        ax.errorbar(i + 0.3, float(np.median(f)), yerr=sd, fmt="_", color="C3", capsize=3)
    ax.axhline(0, color="0.5", lw=0.8)
    ax.set_xticks(range(len(names)))
    ax.set_xticklabels([n.split(".")[1].split("_")[0] for n in names], rotation=45)
    ax.set_ylabel("calibrated value against Tables 1-2 [%]")
    ax.set_title(f"{len(good)} injectors: each dot one injector; red: typical calibration sd")
    return save(fig, path, dpi=100)


def _safe(key: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in key) or "injector"
