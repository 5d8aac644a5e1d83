"""``python -m estimator compile``: two halves at once, checked by Tracker.warm_up, marked complete once.

The compiling itself runs for real as the first step of ``make test`` and ``make demo`` on every
fresh checkout (CI's clean clone included); here the bookkeeping around it, without compiling."""

from __future__ import annotations

from types import SimpleNamespace

from estimator.pipeline import precompile as pc


class _Child:
    def __init__(self, code: int) -> None:
        self.returncode = code

    def wait(self) -> int:
        return self.returncode


def _fake(monkeypatch, tmp_path, child_code: int = 0) -> list[str]:
    calls: list[str] = []
    monkeypatch.setattr(pc, "cache_dir", lambda: tmp_path / "numba-x")
    tracker = SimpleNamespace(warm_up=lambda: calls.append("warm_up"))
    monkeypatch.setattr(pc, "warm_cold_start", lambda t: calls.append("cold start here") if t is tracker else None)
    monkeypatch.setattr(pc.subprocess, "Popen", lambda argv: calls.append("child: " + argv[-1]) or _Child(child_code))
    monkeypatch.setattr(pc, "_tracker", lambda: tracker)
    monkeypatch.setattr(pc.os, "cpu_count", lambda: 2)
    return calls


def test_both_halves_run_then_the_check_then_the_marker_and_a_second_call_does_nothing(monkeypatch, tmp_path):
    calls = _fake(monkeypatch, tmp_path)
    logged: list[str] = []
    assert pc.precompile(log=logged.append) > 0.0
    assert calls[0].startswith("child:") and "warm_the_rest()" in calls[0]
    assert calls[1:] == ["cold start here", "warm_up"]
    assert (tmp_path / "numba-x" / pc.MARKER).exists()
    calls.clear()
    assert pc.precompile(log=logged.append) == 0.0 and calls == []


def test_serial_and_a_failed_child_still_end_with_every_entry_point_checked(monkeypatch, tmp_path):
    calls = _fake(monkeypatch, tmp_path, child_code=1)
    logged: list[str] = []
    pc.precompile(log=logged.append)
    assert calls[-1] == "warm_up" and any("exited with 1" in m for m in logged)
    (tmp_path / "numba-x" / pc.MARKER).unlink()
    calls.clear()
    pc.precompile(parallel=False, log=logged.append)
    assert calls == ["cold start here", "warm_up"]


def test_a_cache_that_cannot_be_marked_is_used_all_the_same(monkeypatch, tmp_path):
    _fake(monkeypatch, tmp_path)
    (tmp_path / "numba-x").write_text("a file where the directory should be")
    logged: list[str] = []
    assert pc.precompile(log=logged.append) > 0.0
    assert any("cannot mark the cache complete" in m for m in logged)
