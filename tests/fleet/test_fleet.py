"""The fleet path on a real dask.distributed LocalCluster (2 worker processes, 127.0.0.1): results equal
the per-input pipeline (identify/track state for a serial's traces, replay for a capture); a corrupt
input is reported and the rest processed."""

from __future__ import annotations

import csv
import subprocess
import sys

import can
import pytest

pytest.importorskip("distributed")
pd = pytest.importorskip("pandas")

from estimator.errors import EstimatorError  # noqa: E402
from estimator.fleet.run import run_fleet  # noqa: E402
from estimator.pipeline import build_tracker  # noqa: E402
from estimator.pipeline.estimates import iter_estimates  # noqa: E402
from estimator.service.config import DaemonConfig  # noqa: E402
from sim_bench.hardware.lot import make_lot  # noqa: E402

from ..conftest import REPO  # noqa: E402
from ..helpers import COLD_MIN_EVALUATIONS, WARM_MAX_EVALUATIONS, injection_messages  # noqa: E402

pytestmark = pytest.mark.timeout(400)


@pytest.fixture(scope="module")
def lot(tmp_path_factory):
    d = tmp_path_factory.mktemp("lot")
    make_lot(d, injectors=4, injections=2, seed=3)
    traces = d / "traces"
    (traces / "corrupt.csv").write_bytes(b"# serial=INJ-99999\nt_s,current_A,voltage_V\n0,1,\xff\xfe\n")
    with can.Logger(str(traces / "bench.blf")) as w:
        for m in injection_messages(5, 3, 40):
            w.on_message_received(m)
    return d


def expected(lot) -> dict:
    """The same inputs without Dask: a serial's traces in time order through one tracker; the capture
    through the replay pipeline."""
    cfg = DaemonConfig()
    rows = {}
    traces = lot / "traces"
    for serial in sorted({p.name.split("_")[0] for p in traces.glob("INJ-*_*.csv")}):
        tracker = build_tracker(cfg)
        for path in sorted(traces.glob(f"{serial}_*.csv")):
            for r in iter_estimates(path, cfg, tracker=tracker):
                rows[(str(path), r["counter"])] = r
    for r in iter_estimates(traces / "bench.blf", cfg):
        rows[(str(traces / "bench.blf"), r["counter"])] = r
    return rows


def test_fleet_on_a_local_cluster_equals_the_per_input_pipeline(lot, tmp_path):
    """Three groups per task (the corrupt input shares its task with two injectors): the rows are the
    per-input pipeline's."""
    out = tmp_path / "res.parquet"
    res = run_fleet([str(lot / "traces")], out, workers=2, groups_per_task=3)
    assert res.workers == 2
    df = pd.read_parquet(out)
    assert len(df) == len(res.rows) == 8 + 3 + 1
    errors = df[df.status == "error"]
    assert list(errors.source) == [str(lot / "traces" / "corrupt.csv")] and "UTF-8" in errors.reason.iloc[0]
    want = expected(lot)
    got = {(r["source"], r["counter"]): r for r in res.rows if r["status"] != "error"}
    assert set(got) == set(want)
    for key, w in want.items():
        g = got[key]
        for k in ("status", "nu_n_per_v", "lh_um", "sigma_lh_um", "t_open_us", "raw_lh_um"):
            assert g[k] == w[k], (key, k)
    # the second trace of each serial was a warm start from the first (state carried across inputs)
    second = [r for r in res.rows if r["source"].endswith("_001.csv")]
    assert second and all(r["evaluations"] < 40 for r in second)   # cold starts: 48-131
    # the per-injector summary and the report are written beside the rows
    summary = list(csv.DictReader(open(tmp_path / "res-summary.csv")))
    assert {s["injector"] for s in summary} >= {"INJ-00000", "INJ-00003"}
    assert "1 input(s) failed" in (tmp_path / "res-report.txt").read_text()


def test_fleet_capture_rows_equal_replay_csv(lot, tmp_path):
    cap = lot / "traces" / "bench.blf"
    table = tmp_path / "replay.csv"
    r = subprocess.run([sys.executable, "-m", "estimator", "replay", str(cap), "--csv", str(table)], cwd=REPO,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    replayed = list(csv.DictReader(open(table)))
    out = tmp_path / "f.csv"
    r = subprocess.run([sys.executable, "-m", "estimator", "fleet", str(cap), str(lot / "nothing-*.csv"), "--out",
                        str(out), "--workers", "1"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and "matched nothing" in r.stdout       # a pattern without files is reported
    fleet = list(csv.DictReader(open(out)))
    assert [(f["counter"], f["lh_um"], f["status"]) for f in fleet] == \
        [(x["counter"], x["lh_um"], x["status"]) for x in replayed]


def test_groups_per_task_keep_every_worker_busy_and_tasks_few():
    from estimator.fleet.run import MAX_GROUPS_PER_TASK, task_chunks, task_sizes
    assert task_sizes(6, 2) == [1] * 6                  # few inputs: a task each
    assert task_sizes(0, 0) == []
    for n, workers in ((1000, 1), (1000, 2), (100, 2), (10_000, 2), (7, 3)):
        sizes = task_sizes(n, workers)
        assert sum(sizes) == n and max(sizes) <= MAX_GROUPS_PER_TASK
        assert sizes == sorted(sizes, reverse=True)     # the tasks shrink towards the end of the run
        assert sizes[-1] == 1                           # the last ones are single groups: the workers finish together
    assert task_sizes(1000, 1)[:4] == [MAX_GROUPS_PER_TASK] * 4
    assert len(task_sizes(1000, 1)) == 29 and len(task_sizes(1000, 2)) == 44   # not 63 tasks of 16, or 1,000
    assert task_sizes(100, 2)[:3] == [13, 11, 10]       # still about four tasks per worker's share
    groups = list(range(10))
    assert [len(c) for c in task_chunks(groups, 2, 3)] == [3, 3, 3, 1]
    assert [g for chunk in task_chunks(groups, 2) for g in chunk] == groups    # every group once, in order
    with pytest.raises(EstimatorError):
        task_chunks(groups, 2, 0)


def test_a_worker_reuses_freed_memory_despite_the_nannys_trim_threshold():
    """Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536, which makes glibc map and unmap every
    array of 128 KiB or more (a page fault per page touched: 20 against 12.6 ms per lot file). After
    tasks.keep_heap() such arrays come from the heap again: counted in page faults, not time."""
    if not sys.platform.startswith("linux"):
        pytest.skip("glibc only")
    code = ("import resource, numpy as np\n"
            "from estimator.fleet.tasks import keep_heap\n"
            "def faults():\n"
            "    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
            "    for _ in range(200):\n"
            "        a = np.ones(65536)\n"          # 512 KiB, as the cold start's grid arrays
            "    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0\n"
            "before = faults(); ok = keep_heap(); faults(); print(before, ok, faults())\n")
    env = dict(__import__("os").environ, MALLOC_TRIM_THRESHOLD_="65536")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    before, ok, after = r.stdout.split()
    assert ok == "True"
    assert int(before) > 100 * 200 and int(after) < 2000, r.stdout     # ≈ 128 faults per array before, ≈ 0 after


def test_fleet_bench_scores_a_lot_with_several_traces_per_injector(tmp_path):
    """fleet-bench's lot with two traces per injector: every row scored against the truth, and the
    second trace of each injector a warm update (its own lot directory, beside the one-trace lot)."""
    from sim_bench.benches import fleet_bench
    rep = fleet_bench.run(tmp_path, injectors=3, workers=(1,), seed=4, injections=2)
    run = rep["runs"][0]
    assert rep["injections_per_injector"] == 2 and run["injections"] == 6 and run["errors"] == 0
    assert run["rms_lh_um"] < 0.5 and (tmp_path / "lot-3x2-4" / "truth.csv").exists()
    rows = pd.read_parquet(tmp_path / "fleet-1w-x2.parquet")
    second = rows[rows.source.str.endswith("_001.csv")]
    plain = second.status != "model_mismatch"    # a mismatched injector's warm update also sizes its model error
    assert (second[plain].evaluations <= WARM_MAX_EVALUATIONS).all()   # warm
    assert (second[~plain].evaluations < COLD_MIN_EVALUATIONS).all()
    assert "2 traces each" in fleet_bench.format_report(rep)
    fl = rep["simulation_floor"]      # the mean of a cold start and a warm update
    assert 15 < fl["simulations_per_injection_mean"] < 90 and 1 < fl["kernel_us_per_simulation_batch256"] < 200
    assert fl["simulation_bound_per_core_per_s"] == pytest.approx(
        1e6 / (fl["simulations_per_injection_mean"] * fl["kernel_us_per_simulation_batch256"]))
    assert "simulations per injection: mean" in fleet_bench.format_report(rep)


def test_fleet_bench_scores_a_lot_of_captures(tmp_path):
    """fleet-bench's capture lot (one BLF per injector, its injections as the node's frames): every
    injection scored against the truth, the rows of a capture equal its replay (the worker's shared
    codec and simulator pool carry no state between captures), later injections warm updates."""
    from sim_bench.benches import fleet_bench
    rep = fleet_bench.run(tmp_path, injectors=3, workers=(1,), seed=4, injections=3, captures=True)
    run = rep["runs"][0]
    assert rep["inputs"] == "captures" and run["injections"] == 9 and run["errors"] == 0
    assert run["rms_lh_um"] < 0.5
    caps = sorted((tmp_path / "lot-3x3-4-blf" / "captures").glob("*.blf"))
    assert [c.stem for c in caps] == ["INJ-00000", "INJ-00001", "INJ-00002"]
    rows = pd.read_parquet(tmp_path / "fleet-1w-x3-blf.parquet")
    for cap in caps:
        got = rows[rows.source == str(cap)].sort_values("counter")
        want = list(iter_estimates(cap, DaemonConfig()))
        assert list(got.counter) == [w["counter"] for w in want] == [0, 1, 2]
        assert list(got.lh_um) == [w["lh_um"] for w in want] and list(got.status) == [w["status"] for w in want]
        assert (got.evaluations.iloc[1:] < 40).all()                                    # warm (cold: 48-131)
    assert "a BLF capture of 3 injections each" in fleet_bench.format_report(rep)


@pytest.mark.slow
def test_a_series_lot_is_learned_on_the_cluster_and_its_part_beyond_tolerance_reported(tmp_path):
    """sim_bench lot --series: three series parts (one beyond tolerance) through the fleet with its
    default configuration: every injector learns its own model (rows and summary carry the learning
    state), the part beyond tolerance is in the lot report's reject line, the others are not."""
    from sim_bench.hardware.series_life import LotSpec

    truth = make_lot(tmp_path / "lot", 3, 24, seed=21, series=LotSpec(beyond_fraction=0.34))
    rows = list(csv.DictReader(open(truth)))
    beyond = [r["serial"] for r in rows if r["beyond_tolerance"] == "1"]
    assert len(beyond) == 1
    out = tmp_path / "res.csv"
    res = run_fleet([str(tmp_path / "lot" / "traces")], out, workers=1)
    assert {s["learning"] for s in res.summary} <= {"adopted", "monitoring", "calibrating"}
    report = out.with_name("res-report.txt").read_text()
    line = next(x for x in report.splitlines() if "out of tolerance" in x)
    assert beyond[0] in line and all(r["serial"] not in line for r in rows if r["serial"] not in beyond)
    for s in res.summary:
        true_lh = float(next(r["lh_um"] for r in rows if r["serial"] == s["injector"]))
        assert abs(s["lh_um"] - true_lh) < 0.2
