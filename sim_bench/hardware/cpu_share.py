"""A share of one core for a process tree: the kernel's CFS bandwidth control, so a daemon on this
machine stands in for a bench computer that many times slower.

The quota is the kernel's shortest, 1 ms, and the period follows from the share: at a quarter of a
core the daemon runs at most 1 ms of every 4 ms. Over any interval longer than a period it gets the
CPU time a four times slower computer would give it; unlike that computer it may wait up to 3 ms
for its share, which the latency it reports includes (a coarser period, systemd's ``CPUQuota=`` uses
100 ms, would stall it for 75 ms at a time). Needs a writable cgroup ``cpu`` controller (cgroup v1 ``/sys/fs/cgroup/cpu``, or v2 with
``cpu.max``): root, or a delegated cgroup.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from estimator.errors import EstimatorError

QUOTA_US = 1000                       # CFS bandwidth quota (µs): the kernel's minimum
V1_ROOT = Path("/sys/fs/cgroup/cpu")
V2_ROOT = Path("/sys/fs/cgroup")


class CpuShareError(EstimatorError):
    """The CPU share cannot be set on this machine (no writable cgroup cpu controller)."""


def _stat_fields(stat: Path) -> list[str]:
    """The fields of a /proc/PID/stat after the command name (state first); [] if the process is gone."""
    try:
        return stat.read_text().rsplit(")", 1)[1].split()
    except OSError:
        return []


def descendants(pid: int) -> list[int]:
    """``pid`` and every process below it (from /proc; a process gone meanwhile is left out)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        fields = _stat_fields(stat)
        if fields:
            children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += children.get(p, [])
    return out


def cpu_seconds(pids: list[int]) -> float:
    """User + system CPU time (s) the processes ``pids`` have used so far (a process gone counts 0)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0
    for pid in pids:
        fields = _stat_fields(Path(f"/proc/{pid}/stat"))
        if fields:
            total += int(fields[11]) + int(fields[12])     # utime, stime (fields 14 and 15 of stat)
    return total / tick


@contextlib.contextmanager
def cpu_share(pid: int, share: float, name: str = "injector-estimator-bench") -> Iterator[Path]:
    """Hold the process tree of ``pid`` (and whatever it starts later) to ``share`` of one core;
    the cgroup's directory is yielded and removed on exit."""
    if not 0.01 <= share <= 1.0:
        raise CpuShareError(f"cpu share {share}: must be in 0.01 ... 1")
    quota, period = QUOTA_US, int(round(QUOTA_US / share))
    if V1_ROOT.is_dir() and (V1_ROOT / "cpu.cfs_quota_us").exists():
        group, files, parent = V1_ROOT / f"{name}-{os.getpid()}", {"cpu.cfs_period_us": str(period),
                                                                    "cpu.cfs_quota_us": str(quota)}, V1_ROOT
    elif (V2_ROOT / "cgroup.controllers").exists() and "cpu" in (V2_ROOT / "cgroup.controllers").read_text():
        group, files, parent = V2_ROOT / f"{name}-{os.getpid()}", {"cpu.max": f"{quota} {period}"}, V2_ROOT
    else:
        raise CpuShareError("no cgroup cpu controller on this machine (need /sys/fs/cgroup/cpu or cgroup v2 cpu.max)")
    try:
        group.mkdir(exist_ok=True)
        for f, v in files.items():
            (group / f).write_text(v)
        for _ in range(10):   # a process forked while the tree moves may stay behind: move until none is
            inside = set((group / "cgroup.procs").read_text().split())
            outside = [p for p in descendants(pid) if str(p) not in inside]
            if not outside:
                break
            for p in outside:
                with contextlib.suppress(ProcessLookupError, OSError):
                    (group / "cgroup.procs").write_text(str(p))
    except OSError as exc:
        with contextlib.suppress(OSError):
            group.rmdir()
        raise CpuShareError(f"cannot set a cpu share in {group}: {exc.strerror or exc} (needs root or a delegated "
                            "cgroup)") from None
    try:
        yield group
    finally:
        with contextlib.suppress(OSError):
            for member in (group / "cgroup.procs").read_text().split():
                with contextlib.suppress(OSError):
                    (parent / "cgroup.procs").write_text(member)
            group.rmdir()
