"""A calibration tool's view of the running daemon: pyxcp as the XCP master over UDP on 127.0.0.1 against
``python -m estimator run`` on the loopback hub (measurements by DAQ on the injection event compared
with the CAN frames, a characteristic written and used by the next estimate, the A2L), and pyxcp's own
``xcp-info`` against it."""

from __future__ import annotations

import struct
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from estimator import __version__
from estimator.codec.frame import Frame
from estimator.codec.records import Codec, EstimatorHealth
from estimator.service.bus import open_bus
from estimator.service.xcp.a2l import a2l_bytes
from estimator.service.xcp.daq_lists import EVENT_INJECTION, injector_event, predefined_lists
from estimator.service.xcp.memory import characteristics, slot_layout
from sim_bench.benches.xcp_bench import free_udp_port, pyxcp_master
from sim_bench.hardware.procs import DaemonProcess, wait_until

from ..helpers import measured
from .test_processes import feed_and_collect

pytestmark = pytest.mark.timeout(300)
pyxcp = pytest.importorskip("pyxcp", reason="pyxcp is the test extra's XCP master")


def daq_recorder():
    from pyxcp.transport.base import FrameAcquisitionPolicy, FrameCategory

    class Recorder(FrameAcquisitionPolicy):   # the DAQ packets as they arrive: PID, timestamp, data
        def __init__(self) -> None:
            super().__init__(None)
            self.frames: list[bytes] = []

        def feed(self, category, counter, timestamp, payload) -> None:
            if category == FrameCategory.DAQ:
                self.frames.append(bytes(payload))

        def finalize(self) -> None:
            pass
    return Recorder()


def test_a_calibration_tool_measures_and_calibrates_the_running_daemon(hub, monitor, tmp_path):
    codec = Codec()
    port = free_udp_port()
    cfg = tmp_path / "e.toml"
    # not a latency test: on a machine other work keeps busy an estimate can come later than the default
    # 100 ms, and would then be "stale" where the statuses asserted below are the estimates' own
    cfg.write_text(f"[estimator]\npersist_period_s = 0.2\nstale_after_ms = 60000\n[estimator.xcp]\nmode = \"on\"\n"
                   f"port = {port}\n")
    injs = [measured(17.6, 4.4, 4000 + k, window_s=100e-6)[0] for k in range(12)]
    d = DaemonProcess(hub.spec, tmp_path / "daemon.log", state_dir=tmp_path / "state", config=cfg).start()
    try:
        d.wait_ready(monitor)
        recorder = daq_recorder()
        with warnings.catch_warnings(), pyxcp_master(port, recorder) as x, open_bus(hub.spec) as bus:
            warnings.simplefilter("ignore")
            x.connect()
            # the A2L it serves is the one the command writes
            gid = x.getId(4)
            a2l = b"".join(x.upload(min(254, gid.length - k)) for k in range(0, gid.length, 254))
            assert a2l == a2l_bytes(codec.db, __version__, ("127.0.0.1", port))
            # every characteristic as the configuration file says
            from estimator.service.config import DaemonConfig
            running = DaemonConfig.load(cfg)
            for c in characteristics():
                value = struct.unpack("<" + c.fmt, x.shortUpload(c.size, c.address))[0]
                assert value == pytest.approx(c.get(running), rel=1e-6), c.name
            # DAQ: injector 0's EstimateState on the injection event in a list of the master's own, and
            # injector 0's predefined list on its own event, both timestamped
            slot = slot_layout(codec.db)[(codec.db.get_message_by_name("EstimateState").frame_id, 0)]
            own = x.getDaqProcessorInfo().minDaq                 # the master's lists come after the predefined
            assert own == len(predefined_lists(codec.db))
            x.freeDaq()
            x.allocDaq(1)
            x.allocOdt(own, 1)
            x.allocOdtEntry(own, 0, 1)
            x.setDaqPtr(own, 0, 0)
            x.writeDaq(0xFF, 8, 0, slot)
            x.setDaqListMode(0x10, own, EVENT_INJECTION, 1, 0)
            x.startStopDaqList(2, own)
            x.setDaqListMode(0x10, 0, injector_event(0), 1, 0)
            x.startStopDaqList(2, 0)
            x.startStopSynch(1)
            got = feed_and_collect(bus, monitor, codec, injs[:6])
            # the event fires after the CAN frames are sent: wait for its DTOs before stopping DAQ
            assert wait_until(lambda: len(recorder.frames) >= 12, 10)
            x.startStopSynch(0)
            states = [got[(0, k)]["EstimateState"] for k in range(6)]
            mine = [f for f in recorder.frames if f[0] == own]
            daq = [codec.decode(Frame(0x200, f[5:13])) for f in mine]
            assert daq[-6:] == states                         # the same values as the CAN frames, in order
            stamps = [struct.unpack_from("<I", f, 1)[0] for f in mine[-6:]]
            assert stamps == sorted(stamps) and len(set(stamps)) == 6
            # the predefined list: the injection's EstimateState, EstimateQuality and ValvePrediction in a row
            ready = [f for f in recorder.frames if f[0] == 0][-6:]
            assert [codec.decode(Frame(0x200, f[5:13])) for f in ready] == states
            assert [codec.decode(Frame(0x201, f[13:25], is_fd=True)) for f in ready] == [got[(0, k)]["EstimateQuality"]
                                                                            for k in range(6)]
            assert [codec.decode(Frame(0x202, f[25:33])) for f in ready] == [got[(0, k)]["ValvePrediction"]
                                                                            for k in range(6)]
            assert all(s.status == 0 for s in states)          # ok
            # a characteristic written: the next estimates use it (sigma gate far below any sigma)
            sigma = next(c for c in characteristics() if c.name == "ident.sigma_limit_lh_um")
            x.setMta(sigma.address)
            x.download(struct.pack("<f", 0.001))
            after = feed_and_collect(bus, monitor, codec, injs[6:9], first_counter=6)
            assert after[(0, 8)]["EstimateState"].status == codec.status_code("uncertain")
            assert struct.unpack("<f", x.shortUpload(4, sigma.address))[0] == pytest.approx(0.001)
            assert monitor.wait_for(lambda m: any(h.xcp_writes >= 1 for _, h in m.recent(50)
                                                  if isinstance(h, EstimatorHealth)), 10)
            # out of range: refused as the standard says, nothing changed
            x.setMta(sigma.address)
            with pytest.raises(Exception, match="OUT_OF_RANGE"):
                x.download(struct.pack("<f", 1e9))
            x.disconnect()
        # pyxcp's own exploration tool against the daemon
        (tmp_path / "pyxcp_conf.py").write_text(
            "c = get_config()  # noqa: F821\nc.Transport.layer = 'ETH'\nc.Transport.Eth.host = '127.0.0.1'\n"
            f"c.Transport.Eth.port = {port}\nc.Transport.Eth.protocol = 'UDP'\n")
        info = subprocess.run([str(Path(sys.executable).parent / "xcp-info")], cwd=tmp_path, capture_output=True,
                              text=True, timeout=120)
        assert info.returncode == 0, info.stdout[-2000:] + info.stderr[-2000:]
        assert "injector_estimator" in info.stdout
    finally:
        assert d.stop() == 0
    assert "XCP: calibration written: ident.sigma_limit_lh_um" in (tmp_path / "daemon.log").read_text()
