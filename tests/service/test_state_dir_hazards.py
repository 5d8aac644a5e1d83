"""The state directory turned against the daemon: links, FIFOs, devices, huge files, a second
instance; and a state the estimator wrote always loads."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.ident.config import TrackerConfig
from estimator.ident.tracking import kalman
from estimator.ident.tracking.recursive import _store
from estimator.ident.tracking.tracker import Tracker, TrackerState
from estimator.ident.tracking.tracker_state import state_bounds
from estimator.service.config import DaemonConfig
from estimator.service.daemon import Daemon
from estimator.service.state_store import (
    MAX_BYTES,
    REJECTED_KEPT,
    StateDirectoryBusy,
    keep_rejected,
    load_all,
    lock_state_dir,
    read_regular,
)

from ..conftest import REPO

STATE = "estimator-state.json"


def test_a_state_file_that_is_a_link_is_not_followed_and_nothing_outside_is_written(tmp_path):
    outside = tmp_path / "outside.txt"
    outside.write_text("precious")
    state = tmp_path / "state"
    state.mkdir()
    (state / STATE).symlink_to(outside)
    (state / (STATE + ".rejected")).symlink_to(outside)
    d = Daemon(DaemonConfig(bus="virtual:unused", state_dir=state))
    d.restore()
    d.persist()
    assert outside.read_text() == "precious"
    assert not (state / STATE).is_symlink() and json.loads((state / STATE).read_text())["format"]


@pytest.mark.parametrize("kind", ["fifo", "dev-zero", "huge", "directory"])
def test_special_and_huge_state_files_are_refused_at_once_with_one_line(tmp_path, kind, caplog):
    path = tmp_path / STATE
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "dev-zero":
        path.symlink_to("/dev/zero")
    elif kind == "huge":
        with open(path, "wb") as f:
            f.truncate(100 * MAX_BYTES)   # sparse: 100 MB that cost no disk
    else:
        path.mkdir()
    t0 = time.monotonic()
    states, _cals, _learning, _drives, problems = load_all(path)
    assert time.monotonic() - t0 < 1.0 and not states and len(problems) == 1
    d = Daemon(DaemonConfig(bus="virtual:unused", state_dir=tmp_path))
    with caplog.at_level("WARNING"):
        d.restore()
    assert len([r for r in caplog.records if r.levelno >= 30]) == 1
    if kind == "huge":   # kept by rename: no copy of 100 MB
        assert (tmp_path / (STATE + ".rejected")).stat().st_size == 100 * MAX_BYTES and not path.exists()


def test_read_regular_reads_a_regular_file_and_bounds_it(tmp_path):
    p = tmp_path / "f"
    p.write_bytes(b"x" * 100)
    assert read_regular(p, 100) == b"x" * 100
    with pytest.raises(OSError, match="larger"):
        read_regular(p, 99)
    with pytest.raises(FileNotFoundError):
        read_regular(tmp_path / "none")


def test_rejected_files_are_kept_by_rename_in_bounded_generations(tmp_path):
    path = tmp_path / STATE
    for k in range(REJECTED_KEPT + 2):
        path.write_text(str(k))
        kept = keep_rejected(path)
        assert kept is not None and kept.read_text() == str(k) and not path.exists()
    kept = sorted(p.name for p in tmp_path.iterdir())
    assert len(kept) == REJECTED_KEPT


def test_a_second_estimator_on_the_state_directory_is_refused_naming_the_holder(tmp_path):
    fd = lock_state_dir(tmp_path)
    try:
        with pytest.raises(StateDirectoryBusy, match=f"pid {os.getpid()}"):
            lock_state_dir(tmp_path)
        r = subprocess.run([sys.executable, "-m", "estimator", "run", "--state-dir", str(tmp_path),
                            "--bus", "virtual:second"], capture_output=True, text=True, timeout=120, cwd=REPO)
        assert r.returncode != 0 and f"pid {os.getpid()}" in r.stderr
        assert len([line for line in r.stderr.splitlines() if line.startswith("error")]) == 1
    finally:
        os.close(fd)
    os.close(lock_state_dir(tmp_path))   # released: the next one gets it


BOX_CONFIG = TrackerConfig()


@settings(max_examples=200, deadline=None)
@given(nu=st.floats(15.0, 21.0), lh=st.floats(-0.5, 10.0), rate=st.floats(-5.0, 5.0), slope=st.floats(-2.0, 2.0),
       wear=st.floats(-1.0, 1.0), var=st.floats(1e-8, 5e-4))   # the filter caps its variances (the slope's at 9e-4)
def test_a_state_the_estimator_wrote_always_loads(nu, lh, rate, slope, wear, var):
    """Whatever the filter computed, what it stores is within the bounds its loader checks (one source)."""
    st_ = TrackerState()
    cov = np.eye(kalman.N_STATE) * var
    cov[kalman.WEAR, kalman.WEAR] = min(var, BOX_CONFIG.max_wear_um ** 2)   # the wear rate's cap
    _store(st_, np.array([nu, lh, rate, slope, wear]), cov, 1.0, 40.0, BOX_CONFIG)
    back = TrackerState.from_dict(json.loads(json.dumps(st_.to_dict())))
    tracker = Tracker(BOX_CONFIG)
    assert tracker.restore({0: back}) == []
    rate_max, lo, hi, wear_max = state_bounds(BOX_CONFIG)
    assert abs(back.x[kalman.RATE]) <= rate_max and lo <= back.x[kalman.SLOPE] <= hi
    assert abs(back.x[kalman.WEAR]) <= wear_max == BOX_CONFIG.max_wear_um
