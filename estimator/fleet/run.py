"""``python -m estimator fleet``: inputs -> Dask tasks -> one row per injection, a per-injector summary
and a lot report (Table-3 style, with the L_h and N_u distributions and outliers flagged).

The default cluster is a local one on this machine (``workers`` processes, one thread each, bound to
127.0.0.1, no dashboard); ``scheduler`` attaches to an existing one (``tcp://HOST:PORT``).
"""

from __future__ import annotations

import contextlib
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from estimator.errors import EstimatorError
from estimator.fleet.cluster import dask_client
from estimator.fleet.inputs import Group, expand, group
from estimator.fleet.tasks import process_groups, warm_worker
from estimator.ident.status import ESTIMATED_WORDS
from estimator.pipeline.config import EstimatorConfig
from estimator.pipeline.estimates import FIELDS

COLUMNS = (*FIELDS, "injector_key")
MAX_GROUPS_PER_TASK = 64   # groups (an injector's traces, or one input) sent to a worker in one Dask task at most
TASKS_PER_WORKER = 4       # each task takes at most 1/(this x workers) of the groups not yet given out
OUTLIER_MADS = 4.0      # |x - lot median| beyond this many robust sigmas (1.4826 MAD) is flagged


@dataclass
class FleetResult:
    """Rows, the per-injector summary, the files written, and what could not be processed."""

    rows: list[dict]
    summary: list[dict]
    files: list[Path] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    errors: int = 0
    seconds: float = 0.0         # the whole run: the cluster's start, the workers' warm-up and the work
    seconds_start: float = 0.0   # of that, until every worker was ready (started, kernels loaded)
    seconds_stop: float = 0.0    # of that, closing the client and the local cluster after the last result
    workers: int = 0


def run_fleet(inputs: list[str], out: Path, cfg: EstimatorConfig | None = None, workers: int | None = None,
              scheduler: str | None = None, trace_options: dict[str, Any] | None = None,
              progress: bool = False, groups_per_task: int | None = None) -> FleetResult:
    """Process every input on a Dask cluster; write ``out`` (.parquet or .csv) and its companions.
    ``groups_per_task``: how many groups (:func:`group`) one Dask task processes (default: see
    :func:`task_sizes`); the rows do not depend on it."""
    if out.suffix.lower() not in (".parquet", ".csv"):
        raise EstimatorError(f"--out {out}: use .parquet or .csv")
    files, missing = expand(inputs)
    if not files:
        raise EstimatorError(f"no input files in {' '.join(inputs)}")
    groups = group(files)
    cfg = cfg or EstimatorConfig()
    t0 = time.perf_counter()
    rows, n_workers, ready, finished = _compute(groups, cfg, trace_options or {}, workers, scheduler, progress,
                                                groups_per_task)
    seconds = time.perf_counter() - t0
    rows.sort(key=lambda r: (r.get("injector_key") or "", r["source"], _num(r.get("time_s")), r.get("counter") or 0))
    summary = summarise(rows)
    res = FleetResult(rows, summary, missing=missing, errors=sum(r.get("status") == "error" for r in rows),
                      seconds=seconds, seconds_start=ready - t0, seconds_stop=t0 + seconds - finished, workers=n_workers)
    res.files = write(res, out)
    return res


def task_sizes(n_groups: int, n_workers: int) -> list[int]:
    """Groups per Dask task, in the order the tasks are submitted (and run): guided self-scheduling.
    Each task takes 1/(:data:`TASKS_PER_WORKER` x workers) of the groups still to be given out (at
    least one, at most :data:`MAX_GROUPS_PER_TASK`), so the tasks shrink towards the end of the run and
    the workers finish together. A task costs ≈ 2.8 ms of a worker's core (Dask's messages for it and
    its result; measured on this 2-core machine as 1/587 - 1/673 s per lot file with 16 files a task
    against 125), so 1,000 lot files (≈ 1.45 ms each) as 63 tasks of 16 spent 12 % of the workers' time
    on tasks; as these (29 tasks on one worker, 44 on two) 6-8 %."""
    sizes: list[int] = []
    left = max(n_groups, 0)
    share = TASKS_PER_WORKER * max(n_workers, 1)
    while left > 0:
        k = max(1, min(MAX_GROUPS_PER_TASK, -(-left // share)))
        sizes.append(k)
        left -= k
    return sizes


def task_chunks(groups: list[Group], n_workers: int, groups_per_task: int | None = None) -> list[list[Group]]:
    """``groups`` cut into the Dask tasks' shares: :func:`task_sizes`, or ``groups_per_task`` each."""
    if groups_per_task is not None:
        if not 1 <= groups_per_task <= 10_000:
            raise EstimatorError(f"groups per task {groups_per_task} must be within 1..10000")
        sizes = [groups_per_task] * -(-len(groups) // groups_per_task)
    else:
        sizes = task_sizes(len(groups), n_workers)
    chunks, i = [], 0
    for k in sizes:
        chunks.append(groups[i:i + k])
        i += k
    return chunks


def _compute(groups: list[Group], cfg: EstimatorConfig, trace_options: dict, workers: int | None,
             scheduler: str | None, progress: bool, groups_per_task: int | None = None
             ) -> tuple[list[dict], int, float, float]:
    """The rows, the number of workers, and when (``perf_counter``) every worker was ready and the last
    result had come (before the client and the local cluster are closed)."""
    from dask.distributed import as_completed

    with dask_client(workers, scheduler) as client:
        n_workers = len(client.scheduler_info()["workers"])
        client.run(warm_worker, cfg)   # every worker: pool, codec, kernels (else its first task pays for them)
        ready = time.perf_counter()
        chunks = task_chunks(groups, n_workers, groups_per_task)
        futures = [client.submit(process_groups, tuple((g.key, g.paths) for g in c), cfg, trace_options, pure=False)
                   for c in chunks]
        task_of = {f.key: c for f, c in zip(futures, chunks)}
        total = sum(len(g.paths) for g in groups)
        rows: list[dict] = []
        done = 0
        for fut in as_completed(futures):
            try:
                rows.extend(fut.result())
            except Exception as exc:   # a worker died on this task: its inputs are reported, the run goes on
                rows.extend({"source": p, "injector_key": g.key, "status": "error",
                             "reason": f"task failed: {type(exc).__name__}: {exc}"[:300]}
                            for g in task_of[fut.key] for p in g.paths)
            done += sum(len(g.paths) for g in task_of[fut.key])
            if progress:
                print(f"\r[{done}/{total}] inputs, {len(rows)} injections", end="", file=sys.stderr, flush=True)
        if progress:
            print(file=sys.stderr)
        return rows, n_workers, ready, time.perf_counter()


def _num(v: Any) -> float:
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else math.inf


def summarise(rows: list[dict]) -> list[dict]:
    """Per injector (key, else source + injector id): counts, the last filtered estimate, the median raw
    one, and an outlier flag against the lot (robust: median and MAD of the injectors' L_h and N_u)."""
    import numpy as np

    by: dict[tuple, list[dict]] = {}
    for r in rows:
        ident = (r.get("injector_key") or r["source"], r.get("injector_id"))
        by.setdefault(ident, []).append(r)
    out = []
    for (ident, inj_id), rs in by.items():
        ok = [r for r in rs if r.get("status") in ESTIMATED_WORDS and r.get("lh_um") is not None]
        last = ok[-1] if ok else {}
        out.append({"injector": ident, "injector_id": inj_id, "injections": len(rs), "estimated": len(ok),
                    "errors": sum(r.get("status") == "error" for r in rs),
                    "model_mismatch": sum(r.get("status") == "model_mismatch" for r in rs),
                    "nu_n_per_v": last.get("nu_n_per_v"), "lh_um": last.get("lh_um"),
                    "sigma_lh_um": last.get("sigma_lh_um"), "t_open_us": last.get("t_open_us"),
                    "raw_lh_um_median": float(np.median([r["raw_lh_um"] for r in ok if r.get("raw_lh_um") is not None]))
                    if ok else None,
                    "learning": rs[-1].get("learning"), "last_status": rs[-1].get("status"),
                    # the electronic trim: the drive correction the part needs (its last valid one)
                    "drive_scale": next((r["drive_scale"] for r in reversed(rs) if r.get("drive_scale") is not None),
                                        None),
                    "drive_offset_us": next((r["drive_offset_us"] for r in reversed(rs)
                                             if r.get("drive_offset_us") is not None), None),
                    "out_of_tolerance": next((r["out_of_tolerance"] for r in reversed(rs) if r.get("out_of_tolerance")),
                                             "")})
    for name in ("lh_um", "nu_n_per_v"):
        vals = np.array([s[name] for s in out if s[name] is not None], dtype=float)
        if vals.size < 5:
            continue
        med = float(np.median(vals))
        mad = 1.4826 * float(np.median(np.abs(vals - med))) or 1e-9
        for s in out:
            if s[name] is not None and abs(s[name] - med) > OUTLIER_MADS * mad:
                s["outlier"] = (s.get("outlier", "") + f" {name}").strip()
    for s in out:
        s.setdefault("outlier", "no estimate" if s["lh_um"] is None else "")
    return out


def write(res: FleetResult, out: Path) -> list[Path]:
    """``out`` (rows), ``<stem>-summary.csv``, ``<stem>-report.txt`` and ``<stem>-lot.png`` (if matplotlib)."""
    import pandas as pd

    out.parent.mkdir(parents=True, exist_ok=True)
    df = pd.DataFrame(res.rows, columns=list(COLUMNS))
    if out.suffix.lower() == ".parquet":
        df.to_parquet(out, index=False)
    else:
        df.to_csv(out, index=False)
    files = [out]
    summary = out.with_name(out.stem + "-summary.csv")
    pd.DataFrame(res.summary).to_csv(summary, index=False)
    report = out.with_name(out.stem + "-report.txt")
    report.write_text(format_report(res) + "\n")
    files += [summary, report]
    with contextlib.suppress(EstimatorError):
        files.append(plot_lot(res, out.with_name(out.stem + "-lot.png")))
    return files


def format_report(res: FleetResult) -> str:
    """The lot in the style of the paper's Table 3: L_h and N_u per injector, with the lot statistics,
    and the drive trim each part needs (current scale, start-of-charge offset µs: the last valid
    drive correction)."""
    import numpy as np

    est = [s for s in res.summary if s["lh_um"] is not None]
    lines = [f"fleet: {len(res.rows)} injections from {len({r['source'] for r in res.rows})} inputs, "
             f"{len(res.summary)} injectors, {res.errors} input(s) failed, {res.seconds:.1f} s on {res.workers} "
             f"worker(s)"]
    if res.missing:
        lines.append(f"matched nothing: {', '.join(res.missing)}")
    lines.append(f"  {'injector':<40} {'id':>2} {'n':>5} {'N_u [N/V]':>10} {'L_h [µm]':>9} {'σ(L_h)':>7} {'mism':>5} "
                 f"{'learning':<11} {'trim':>7} {'[µs]':>7} flag")
    for s in res.summary:
        nu = f"{s['nu_n_per_v']:.4f}" if s["nu_n_per_v"] is not None else "-"
        lh = f"{s['lh_um']:.3f}" if s["lh_um"] is not None else "-"
        sg = f"{s['sigma_lh_um']:.3f}" if s["sigma_lh_um"] is not None else "-"
        trim = f"{s['drive_scale']:.4f}" if s.get("drive_scale") is not None else "-"
        shift = f"{s['drive_offset_us']:+.2f}" if s.get("drive_offset_us") is not None else "-"
        lines.append(f"  {str(s['injector'])[-40:]:<40} {s['injector_id'] if s['injector_id'] is not None else '-':>2} "
                     f"{s['injections']:>5} {nu:>10} {lh:>9} {sg:>7} {s.get('model_mismatch', 0):>5} "
                     f"{s.get('learning') or '-':<11} {trim:>7} {shift:>7} {s['outlier']}"
                     + (f" out_of_tolerance: {s['out_of_tolerance']}" if s.get("out_of_tolerance") else ""))
    if est:
        lh_lot = np.array([s["lh_um"] for s in est])
        nu_lot = np.array([s["nu_n_per_v"] for s in est])
        lines.append(f"  lot: L_h mean {lh_lot.mean():.3f} µm, std {lh_lot.std():.3f} µm; N_u mean {nu_lot.mean():.4f} N/V, "
                     f"std {nu_lot.std():.4f} N/V; flagged {sum(bool(s['outlier']) for s in res.summary)}; "
                     f"model mismatch at the last injection of {sum(s.get('last_status') == 'model_mismatch' for s in res.summary)} "
                     f"injector(s) (their model cannot explain their samples: see their learning state), at some "
                     f"injection of {sum(bool(s.get('model_mismatch')) for s in res.summary)}")
    reject = [s for s in res.summary if s.get("out_of_tolerance")]
    if reject:
        lines.append(f"  out of tolerance (parts to reject): {len(reject)}: "
                     + "; ".join(f"{s['injector']} ({s['out_of_tolerance']})" for s in reject[:50]))
    for r in [r for r in res.rows if r.get("status") == "error"][:20]:
        lines.append(f"  error: {r['source']}: {r['reason']}")
    return "\n".join(lines)


def plot_lot(res: FleetResult, path: Path) -> Path:
    """Histograms of the lot's L_h and N_u, outliers marked."""
    from estimator.plots.figures import pyplot, save

    plt = pyplot()
    est = [s for s in res.summary if s["lh_um"] is not None]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for a, key, unit in ((ax[0], "lh_um", "L_h [µm]"), (ax[1], "nu_n_per_v", "N_u [N/V]")):
        a.hist([s[key] for s in est], bins=30, color="C0")
        for s in est:
            if s["outlier"]:
                a.axvline(s[key], color="C3", lw=1)
        a.set_xlabel(unit)
        a.set_ylabel("injectors")
    ax[0].set_title(f"{len(est)} injectors; outliers in red")
    return save(fig, path, dpi=100)
