"""``daemon-bench --sweep``: how it pairs what was sent with what the daemon published, what it calls
the capacity, and the CPU share that stands in for a slower computer (a real cgroup where this
machine lets the tests make one). A short real sweep runs on the loopback hub."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from sim_bench.benches.capacity import _match, capacity, failures
from sim_bench.hardware.cpu_share import V1_ROOT, CpuShareError, cpu_share, descendants
from sim_bench.hardware.procs import wait_until


def test_each_injection_sent_is_paired_with_its_own_estimate_though_counters_repeat():
    sent = [(0, 5, 1.0), (0, 5, 2.0), (1, 5, 1.5), (0, 6, 3.0)]
    received = {(0, 5): [1.002, 2.010], (1, 5): [1.4]}      # (1, 5) arrived before it was sent: not its own
    assert sorted(round(x, 6) for x in _match(sent, received)) == [0.002, 0.01]


def _phase(rate: float, held: bool, limited: bool = False, p99: float = 1.0) -> dict:
    return {"rate_per_s": rate, "held": held, "bench_limited": limited, "daemon_p99_ms": p99, "daemon_alive": True}


def test_the_capacity_is_the_highest_rate_held_with_every_lower_one():
    assert capacity([_phase(200, True), _phase(500, True), _phase(1000, False), _phase(2000, True)]) == (500, False)
    assert capacity([_phase(200, True), _phase(500, False, limited=True)]) == (200, True)   # the bench could not offer
    assert capacity([_phase(200, True), _phase(500, True)]) == (500, True)                 # never exceeded
    rep = {"phases": [_phase(200, True), _phase(500, False, p99=9.0)], "daemon_exit": 0}
    assert failures(rep) == ["above capacity at 500/s: p99 of the estimated 9.0 ms > 5 ms"]


def _can_make_cgroups() -> bool:
    return os.geteuid() == 0 and os.access(V1_ROOT, os.W_OK)


@pytest.mark.skipif(not _can_make_cgroups(), reason="needs a writable cgroup v1 cpu controller (root)")
def test_a_quarter_core_is_a_1_ms_quota_every_4_ms_for_the_whole_tree_and_is_removed():
    child = subprocess.Popen([sys.executable, "-c", "import subprocess, sys; "
                              "subprocess.run([sys.executable, '-c', 'import sys; sys.stdin.read()'])"],
                             stdin=subprocess.PIPE)
    try:
        assert wait_until(lambda: len(descendants(child.pid)) == 2, 30)     # the grandchild has started
        with cpu_share(child.pid, 0.25) as group:
            assert (group / "cpu.cfs_quota_us").read_text().strip() == "1000"
            assert (group / "cpu.cfs_period_us").read_text().strip() == "4000"
            inside = {int(p) for p in (group / "cgroup.procs").read_text().split()}
            assert child.pid in inside and set(descendants(child.pid)) <= inside
        assert not group.exists()
    finally:
        child.kill()
        child.wait()


def test_an_impossible_share_is_refused_with_a_clear_error():
    with pytest.raises(CpuShareError, match="must be in"), cpu_share(os.getpid(), 2.0):
        pass


def test_a_short_sweep_on_the_loopback_hub_reports_every_rate(tmp_path: Path):
    """The real thing, briefly: a sender process, a daemon, a watcher; each rate reported with what the
    bench's processes cost, and the JSON written. Whether a rate is held depends on the machine's
    load, so only the report's consistency is asserted."""
    out = tmp_path / "cap.json"
    r = subprocess.run([sys.executable, "-m", "sim_bench", "daemon-bench", "--sweep", "--rates", "50", "100",
                        "--seconds", "2", "--out", str(tmp_path), "--json-out", str(out)],
                       capture_output=True, text=True, timeout=600, cwd=tmp_path,
                       env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])})
    assert r.returncode in (0, 1), r.stderr[-2000:]
    rep = json.loads(out.read_text())
    assert [p["rate_per_s"] for p in rep["phases"]] == [50.0, 100.0]
    assert rep["daemon_exit"] == 0 and rep["yardstick_us_per_candidate"] > 0 and rep["interface_us_per_frame"] > 0
    for p in rep["phases"]:
        assert p["offered"] > 0 and p["estimated"] + p["shed"] <= p["offered"]
        assert set(p["cpu_per_s"]) == {"daemon", "bench", "hub", "sender"} and p["cpu_per_s"]["daemon"] > 0
    assert "capacity:" in r.stdout
