"""Service parts: configuration, state persistence, sd_notify, bus spec checks."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import uuid

import pytest

from estimator.ident.tracking.tracker import TrackerState
from estimator.service.bus import BusSetupError, BusSpec, check_socketcan
from estimator.service.config import ConfigError, DaemonConfig
from estimator.service.state_store import load_states, save_states

from ..conftest import REPO


def test_config_file_and_overrides(tmp_path):
    p = tmp_path / "e.toml"
    p.write_text('[estimator]\nqueue_frames = 100\n[estimator.ident]\nwindow_s = 1.2e-4\n')
    cfg = DaemonConfig.load(p, bus="virtual:x")
    assert cfg.queue_frames == 100 and cfg.ident.window_s == 1.2e-4 and cfg.bus == "virtual:x"
    p.write_text('[estimator]\nqueue = 100\n')
    with pytest.raises(ConfigError, match="unknown key"):
        DaemonConfig.load(p)
    with pytest.raises(ConfigError, match="max_injectors"):
        DaemonConfig(max_injectors=9)
    with pytest.raises(ConfigError, match="window_s"):
        DaemonConfig.from_mapping({"ident": {"window_s": float("nan")}})


def test_bus_spec_and_fd_mtu_check(tmp_path):
    assert BusSpec.parse("socketcan:vcan0") == BusSpec("socketcan", "vcan0")
    with pytest.raises(BusSetupError, match="use INTERFACE:CHANNEL"):
        BusSpec.parse("vcan0")
    assert BusSpec.parse("pcan:PCAN_USBBUS1", bitrate=500000) == BusSpec("pcan", "PCAN_USBBUS1", bitrate=500000)
    with pytest.raises(BusSetupError, match=r"python-can supports: .*kvaser.*socketcan"):
        BusSpec.parse("pcann:PCAN_USBBUS1")
    (tmp_path / "vcan9").mkdir()
    (tmp_path / "vcan9" / "mtu").write_text("16\n")
    with pytest.raises(BusSetupError, match="ip link set vcan9 mtu 72"):
        check_socketcan("vcan9", tmp_path)
    (tmp_path / "vcan9" / "mtu").write_text("72\n")
    check_socketcan("vcan9", tmp_path)
    with pytest.raises(BusSetupError, match="ip link add dev vcan8 type vcan"):
        check_socketcan("vcan8", tmp_path)
    with pytest.raises(BusSetupError, match="ip link set can0 type can bitrate 500000 dbitrate 2000000 fd on"):
        check_socketcan("can0", tmp_path)          # real hardware gets real-hardware advice
    (tmp_path / "can1").mkdir()
    (tmp_path / "can1" / "mtu").write_text("16\n")
    with pytest.raises(BusSetupError, match=r"type can bitrate .* fd on"):
        check_socketcan("can1", tmp_path)


def test_bus_options_the_python_can_way(monkeypatch, tmp_path):
    """--bus shorthand, python-can's -i/-c/-b/--data-bitrate/--bus-kwargs, and its configuration."""
    import argparse

    import can

    from estimator.service.bus import add_arguments, open_bus, resolve, spec_from_args
    p = argparse.ArgumentParser()
    add_arguments(p)
    s = spec_from_args(p.parse_args(["-i", "virtual", "-c", "x1", "-b", "500000", "--data-bitrate", "2000000",
                                     "--bus-kwargs", "preserve_timestamps=True"]))
    assert s == BusSpec("virtual", "x1", True, 500000, 2000000, {"preserve_timestamps": True})
    with pytest.raises(BusSetupError, match="not both"):
        spec_from_args(p.parse_args(["--bus", "virtual:a", "-c", "b"]))
    with pytest.raises(BusSetupError, match="go together"):
        spec_from_args(p.parse_args(["-c", "b"]))
    # nothing given: python-can's environment decides ...
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "from-env")
    monkeypatch.setattr(can.util, "CONFIG_FILES", [str(tmp_path / "none.ini")])
    r = resolve(spec_from_args(p.parse_args([])))
    assert (r.interface, r.channel) == ("virtual", "from-env")
    with open_bus(r) as bus:
        assert bus.channel_info.startswith("Virtual")
    # ... and its config file
    monkeypatch.delenv("CAN_INTERFACE")
    monkeypatch.delenv("CAN_CHANNEL")
    ini = tmp_path / "can.ini"
    ini.write_text("[default]\ninterface = virtual\nchannel = from-file\n")
    monkeypatch.setattr(can.util, "CONFIG_FILES", [str(ini)])
    r = resolve(None)
    assert (r.interface, r.channel) == ("virtual", "from-file")
    # none at all: vcan0
    monkeypatch.setattr(can.util, "CONFIG_FILES", [str(tmp_path / "none.ini")])
    assert resolve(None) == BusSpec("socketcan", "vcan0")
    # every interface name in the config is checked against python-can's list
    cfg = tmp_path / "e.toml"
    cfg.write_text('[estimator]\nbus = "nosuch:x"\n')
    with pytest.raises(ConfigError, match="python-can supports"):
        DaemonConfig.load(cfg)
    cfg.write_text('[estimator]\nbus = "pcan:PCAN_USBBUS1"\nbitrate = 500000\ndata_bitrate = 2000000\n'
                   '[estimator.bus_options]\nstate = "ACTIVE"\n')
    spec = DaemonConfig.load(cfg).bus_spec()
    assert spec == BusSpec("pcan", "PCAN_USBBUS1", True, 500000, 2000000, {"state": "ACTIVE"})


def test_state_store_atomic_and_defensive(tmp_path):
    path = tmp_path / "s.json"
    st = TrackerState().with_prior(17.0, 3.0)
    save_states(path, {3: st})
    loaded, problem = load_states(path)
    assert problem is None and loaded[3].x[:2] == [17.0, 3.0]
    assert list(tmp_path.iterdir()) == [path]             # no temporary file left behind
    path.write_text(path.read_text()[:40])                 # truncated
    loaded, problem = load_states(path)
    assert loaded == {} and "unreadable" in problem
    path.write_text(json.dumps({"format": "something-else", "version": 1}))
    loaded, problem = load_states(path)
    assert loaded == {} and "not a piezo-injector-estimator-state" in problem
    doc = {"format": "piezo-injector-estimator-state", "version": 1,
           "injectors": {"1": st.to_dict(), "2": {"version": 1, "x": "bad"}, "12": st.to_dict()}}
    path.write_text(json.dumps(doc))
    loaded, problem = load_states(path)
    assert list(loaded) == [1] and "injector 2" in problem and "injector 12" in problem
    path.write_text(json.dumps({"format": "piezo-injector-estimator-state", "version": 1, "injectors": [1, 2]}))
    loaded, problem = load_states(path)
    assert loaded == {} and "not an object" in problem
    bad = {**st.to_dict(), "accepted": "many", "x": [100.0, 500.0, 0.0, 0.06]}   # type and range poison
    path.write_text(json.dumps({"format": "piezo-injector-estimator-state", "version": 1, "injectors": {"1": bad}}))
    loaded, problem = load_states(path)
    assert loaded == {} and "injector 1" in problem


def test_daemon_sd_notify_and_sigterm(tmp_path):
    addr = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(addr)
    sock.settimeout(30)
    env = dict(os.environ, NOTIFY_SOCKET=addr, WATCHDOG_USEC="400000")
    p = subprocess.Popen([sys.executable, "-m", "estimator", "run", "--bus", f"virtual:sd{uuid.uuid4().hex[:6]}"],
                         cwd=REPO, env=env, stderr=subprocess.PIPE, text=True)
    got = []
    try:
        while "WATCHDOG=1" not in got:
            got.append(sock.recv(256).decode())
        assert got[0] == "READY=1"
        p.send_signal(signal.SIGTERM)
        t0 = time.monotonic()
        p.wait(timeout=5)
        assert time.monotonic() - t0 < 2.0 and p.returncode == 0
        sock.settimeout(1)
        rest = []
        try:
            while True:
                rest.append(sock.recv(256).decode())
        except TimeoutError:
            pass
        assert "STOPPING=1" in rest
    finally:
        if p.poll() is None:
            p.kill()
        sock.close()


def test_pipeline_runs_on_the_pool_it_is_given_even_an_empty_one():
    """The fleet hands a worker's pool to each capture pipeline: a fresh pool has no simulators yet
    (len 0) and must still be the one used, not replaced by a second pool that builds its tables again."""
    from estimator.pipeline import build_pool
    from estimator.pipeline.estimates import new_pipeline
    from estimator.service.config import DaemonConfig
    cfg = DaemonConfig()
    pool = build_pool(cfg)
    assert len(pool) == 0
    _, _, processor, _ = new_pipeline(cfg, pool)
    assert processor.tracker.pool is pool


def test_sd_notify_never_blocks_on_a_receiver_that_does_not_read(tmp_path):
    """Linux queues 10 datagrams per unix socket by default: a daemon that sent STATUS= every 5 s to a
    receiver that did not read blocked after 50 s, and then could not stop (SIGKILL after 10 s)."""
    import socket
    import time

    from estimator.service.sdnotify import SdNotify

    path = str(tmp_path / "notify.sock")
    receiver = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    receiver.bind(path)
    try:
        sd = SdNotify(path)
        t0 = time.monotonic()
        for k in range(40):
            sd.notify(f"STATUS=line {k}")
        sd.notify("STOPPING=1")
        assert time.monotonic() - t0 < 3.0
        receiver.settimeout(1.0)
        assert receiver.recv(100) == b"STATUS=line 0"     # what fitted in the queue arrived, in order
    finally:
        receiver.close()
