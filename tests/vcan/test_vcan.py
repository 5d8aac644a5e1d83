"""The service as users run it: on SocketCAN vcan0 (CAN FD, MTU 72), watched with candump.

Runs natively where vcan0 exists (``ip link add dev vcan0 type vcan && ip link set vcan0 mtu 72 up``)
and inside the QEMU VM of ../shared/vcan-vm via ``make test-vcan``. Python there is ~16x slower,
so the suite is one scripted session with generous timeouts.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest

from estimator.codec.records import Codec, EstimateQuality, EstimateState, EstimatorStatus, SimTruth
from estimator.service.bus import to_frame

REPO = Path(__file__).resolve().parents[2]
HAVE_VCAN = Path("/sys/class/net/vcan0").exists()
HAVE_UTILS = all(shutil.which(t) for t in ("candump", "cansend"))

pytestmark = [
    pytest.mark.vcan,
    pytest.mark.timeout(1500),
    pytest.mark.skipif(not HAVE_VCAN, reason="no vcan0 on this machine (ip link add dev vcan0 type vcan && "
                       "ip link set vcan0 mtu 72 up; or run `make test-vcan`, which uses a VM)"),
    pytest.mark.skipif(not HAVE_UTILS, reason="can-utils (candump, cansend) not installed"),
]


def decode_log(path: Path, codec: Codec) -> list:
    out = []
    for msg in can.LogReader(str(path)):
        try:
            rec = codec.decode(to_frame(msg))
        except Exception:
            continue
        if rec is not None:
            out.append(rec)
    return out


def count_lines(path: Path, frame_id: str) -> int:
    """Lines of a candump -L log with this identifier (cheap: no decoding while waiting)."""
    return sum(1 for line in path.read_text().splitlines() if f" {frame_id}#" in line)


def wait_for(pred, timeout: float, step: float = 1.0) -> bool:
    """Until ``pred()`` holds (checked every ``step`` s; candump's file is all there is to watch)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(step)
    return False


def test_daemon_node_candump_cansend_replay(tmp_path):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    codec = Codec()
    capture = tmp_path / "candump.log"
    dump = subprocess.Popen(["candump", "-L", "vcan0"], stdout=open(capture, "w"), stderr=subprocess.DEVNULL)
    daemon = subprocess.Popen([sys.executable, "-m", "estimator", "run", "--bus", "socketcan:vcan0",
                               "--state-dir", str(tmp_path / "state")], cwd=REPO, env=env,
                              stderr=open(tmp_path / "daemon.log", "w"))

    def wait_estimates(n: int) -> None:
        ok = wait_for(lambda: count_lines(capture, "201") >= n, 600)
        assert ok, f"{count_lines(capture, '201')} estimates; daemon log: {(tmp_path / 'daemon.log').read_text()[-2000:]}"

    try:
        ready = wait_for(lambda: count_lines(capture, "210") > 0, 300)
        assert ready, (tmp_path / "daemon.log").read_text()
        # bad frames from outside: counted, not fatal
        subprocess.run(["cansend", "vcan0", "101#0102"], check=True)            # samples ID, classic, 2 bytes
        subprocess.run(["cansend", "vcan0", "100##1" + "00" * 12], check=True)   # header ID, FD, 12 bytes
        node = subprocess.run([sys.executable, "-m", "sim_bench", "node", "--bus", "socketcan:vcan0",
                               "--injectors", "2", "--rate", "2", "--count", "5", "--seed", "3"],
                              cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
        assert node.returncode == 0, node.stderr
        wait_estimates(10)
        # reset injector 0 with cansend: EstimatorCommand 0x220, Command=1 (bits 3-4) -> byte 0 = 0x08
        beats = count_lines(capture, "210")
        subprocess.run(["cansend", "vcan0", "220#0800000000000000"], check=True)
        # three heartbeats later the worker has taken the command from its queue (it runs them in order)
        assert wait_for(lambda: count_lines(capture, "210") >= beats + 3, 300, step=0.2)
        node2 = subprocess.run([sys.executable, "-m", "sim_bench", "node", "--bus", "socketcan:vcan0",
                                "--injectors", "1", "--rate", "2", "--count", "1", "--seed", "4"],
                               cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
        assert node2.returncode == 0, node2.stderr
        wait_estimates(11)
        beats = count_lines(capture, "210")   # a heartbeat after the last injection
        assert wait_for(lambda: count_lines(capture, "210") >= beats + 2, 300, step=0.2)
    finally:
        daemon.send_signal(signal.SIGTERM)
        try:
            daemon.wait(timeout=60)
        finally:
            if daemon.poll() is None:
                daemon.kill()
            dump.send_signal(signal.SIGINT)
            dump.wait(timeout=10)
    assert daemon.returncode == 0

    # 1. candump's capture decodes with `python -m cantools decode dbc/injector.dbc`
    dec = subprocess.run([sys.executable, "-m", "cantools", "decode", str(REPO / "dbc" / "injector.dbc")],
                         stdin=open(capture), capture_output=True, text=True, timeout=600)
    assert dec.returncode == 0, dec.stderr
    blocks = re.findall(r"EstimateState\(\n(.*?)\n\)", dec.stdout, re.S)
    truths = re.findall(r"SimTruth\(\n(.*?)\n\)", dec.stdout, re.S)
    assert len(blocks) == 11 and len(truths) == 11

    def fields(block: str) -> dict:
        return {k: float(v) for k, v in re.findall(r"(\w+): (-?[\d.]+)", block)}
    est = {(int(f["InjectorId"]), int(f["InjectionCounter"])): f for f in map(fields, blocks)}
    tru = {(int(f["InjectorId"]), int(f["InjectionCounter"])): f for f in map(fields, truths)}
    # the estimates agree with the simulated injector's truth (injector 1 had 5 injections)
    e, t = est[(1, 4)], tru[(1, 4)]
    assert abs(e["IdleStroke"] - t["TrueIdleStroke"]) < 0.3
    assert abs(e["CouplingNu"] / t["TrueNu"] - 1) < 0.01

    # 2. the reset sent with cansend was obeyed: injector 0's next injection is a cold start again
    recs = decode_log(capture, codec)
    quality0 = [r for r in recs if isinstance(r, EstimateQuality) and r.injector_id == 0]
    assert len(quality0) == 6 and quality0[4].evaluations < 60 and quality0[5].evaluations > 150

    # 3. the bad frames were counted, not fatal
    status = [r for r in recs if isinstance(r, EstimatorStatus)][-1]
    assert status.frames_malformed == 2 and status.accepted == 11

    # 4. replay of candump's capture reproduces the live estimates exactly
    out = tmp_path / "replay.log"
    r = subprocess.run([sys.executable, "-m", "estimator", "replay", str(capture), "--out", str(out)], cwd=REPO,
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    live = [(x.injector_id, x.counter, x) for x in recs if isinstance(x, (EstimateState, EstimateQuality))]
    rep = [(x.injector_id, x.counter, x) for x in decode_log(out, codec) if isinstance(x, (EstimateState, EstimateQuality))]
    assert [x for _, _, x in rep] == [x for _, _, x in live]
    assert any(isinstance(x, SimTruth) for x in recs)
