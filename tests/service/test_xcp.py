"""The XCP slave in-process, on a real UDP socket on 127.0.0.1: the commands, their errors, the pages,
the A2L (checked by a2ltool), and hostile datagrams (estimator.service.xcp)."""

from __future__ import annotations

import shutil
import socket
import struct
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from estimator.codec.records import Codec
from estimator.service.config import DaemonConfig
from estimator.service.xcp import protocol as p
from estimator.service.xcp.a2l import a2l_bytes, render
from estimator.service.xcp.daq_lists import EVENTS, injector_event, predefined_lists
from estimator.service.xcp.memory import CAL_BASE, apply_page, characteristics, measurements, page_bytes, slot_layout
from estimator.service.xcp.slave import XcpSlave

pytestmark = pytest.mark.timeout(120)
CODEC = Codec()


class Client:
    """A raw XCP-on-UDP master: one request, one response (or None on timeout)."""

    def __init__(self, address: tuple[str, int]) -> None:
        self.address = address
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(10.0)
        self.ctr = 0

    def __call__(self, *packet: int | bytes) -> bytes:
        raw = b"".join(bytes((x,)) if isinstance(x, int) else x for x in packet)
        self.sock.sendto(p.frame(self.ctr, raw), self.address)
        self.ctr += 1
        data, _ = self.sock.recvfrom(65535)
        got = p.packets(data)
        assert got is not None and len(got) == 1
        return got[0][1]

    def close(self) -> None:
        self.sock.close()


@pytest.fixture()
def slave():
    applied: list[DaemonConfig] = []
    cfg = DaemonConfig()
    s = XcpSlave(CODEC.db, lambda: applied[-1] if applied else cfg, cfg, applied.append,
                 lambda address: a2l_bytes(CODEC.db, "t", address), port=0)
    s.applied = applied   # type: ignore[attr-defined]
    s.start()
    yield s
    s.close()


@pytest.fixture()
def client(slave):
    c = Client(slave.address)
    yield c
    c.close()


def err(code: int) -> bytes:
    return bytes((p.ERR, code))


def set_mta(client, address: int) -> None:
    assert client(p.SET_MTA, b"\0\0\0", struct.pack("<I", address)) == b"\xff"


def char(name: str):
    return next(c for c in characteristics() if c.name == name)


def test_connect_answers_as_the_standard_says_and_nothing_before_it(slave, client):
    client.sock.settimeout(0.5)
    with pytest.raises(TimeoutError):
        client(p.GET_STATUS)                               # not connected: not answered, counted
    assert slave.counters.dropped == 1
    client.sock.settimeout(10.0)
    r = client(p.CONNECT, 0)
    assert r[0] == p.RES and r[1] == 0x05 and r[3] == p.MAX_CTO and struct.unpack_from("<H", r, 4)[0] == p.MAX_DTO
    assert client(p.GET_STATUS)[:2] == b"\xff\x00"
    assert client(p.SYNCH) == err(p.ERR_CMD_SYNCH)
    assert client(p.GET_SEED, 0, 0) == err(p.ERR_CMD_UNKNOWN)     # no protection: no seed and key
    assert client(p.GET_COMM_MODE_INFO)[0] == p.RES
    assert client(p.DISCONNECT) == b"\xff"


def test_every_characteristic_reads_as_the_configuration_says(slave, client):
    client(p.CONNECT, 0)
    cfg = DaemonConfig()
    for c in characteristics():
        r = client(p.SHORT_UPLOAD, c.size, 0, 0, struct.pack("<I", c.address))
        assert r[0] == p.RES
        value = struct.unpack("<" + c.fmt, r[1:])[0]
        assert value == pytest.approx(c.get(cfg), rel=1e-6), c.name


def test_a_write_takes_whole_values_within_the_configurations_limits(slave, client):
    client(p.CONNECT, 0)
    sigma = char("ident.sigma_limit_lh_um")
    set_mta(client, sigma.address)
    assert client(p.DOWNLOAD, 4, struct.pack("<f", 0.5)) == b"\xff"
    assert slave.applied[-1].tracker.ident.sigma_limit_lh_um == pytest.approx(0.5)
    assert slave.counters.writes == 1
    r = client(p.SHORT_UPLOAD, 4, 0, 0, struct.pack("<I", sigma.address))
    assert struct.unpack("<f", r[1:])[0] == pytest.approx(0.5)              # read back from the working page
    set_mta(client, sigma.address)
    assert client(p.DOWNLOAD, 4, struct.pack("<f", 500.0)) == err(p.ERR_OUT_OF_RANGE)   # beyond its range
    set_mta(client, sigma.address)
    assert client(p.DOWNLOAD, 2, b"\0\0") == err(p.ERR_OUT_OF_RANGE)        # half a value: never
    lo = char("drive_correction.scale_min")
    set_mta(client, lo.address)
    # both limits in one write, all at once: a pair the configuration refuses (low above high) is refused whole
    assert client(p.DOWNLOAD, 8, struct.pack("<ff", 1.4, 1.2)) == err(p.ERR_OUT_OF_RANGE)
    set_mta(client, lo.address)
    assert client(p.DOWNLOAD, 8, struct.pack("<ff", 0.6, 1.4)) == b"\xff"
    assert slave.applied[-1].drive_correction.scale_limits == pytest.approx((0.6, 1.4))
    assert len(slave.applied) == 2 and slave.counters.writes == 2


def test_the_reference_page_is_the_files_and_read_only(slave, client):
    client(p.CONNECT, 0)
    sigma = char("ident.sigma_limit_lh_um")
    set_mta(client, sigma.address)
    client(p.DOWNLOAD, 4, struct.pack("<f", 0.5))
    assert client(p.SET_CAL_PAGE, 0x02, 0, 1) == b"\xff"                  # XCP looks at the reference page
    r = client(p.SHORT_UPLOAD, 4, 0, 0, struct.pack("<I", sigma.address))
    assert struct.unpack("<f", r[1:])[0] == pytest.approx(0.25)
    set_mta(client, sigma.address)
    assert client(p.DOWNLOAD, 4, struct.pack("<f", 0.3)) == err(p.ERR_WRITE_PROTECTED)
    assert client(p.SET_CAL_PAGE, 0x01, 0, 1) == b"\xff"                  # the estimator uses the file's values
    assert slave.applied[-1].tracker.ident.sigma_limit_lh_um == pytest.approx(0.25)
    assert client(p.GET_CAL_PAGE, 0x01, 0) == b"\xff\x00\x00\x01"
    assert client(p.SET_CAL_PAGE, 0x03, 0, 0) == b"\xff"                  # and the working page again, one step
    assert slave.applied[-1].tracker.ident.sigma_limit_lh_um == pytest.approx(0.5)
    assert client(p.SET_CAL_PAGE, 0x03, 0, 7) == err(p.ERR_PAGE_NOT_VALID)
    assert client(p.COPY_CAL_PAGE, 0, 1, 0, 0) == b"\xff"                 # reference -> working
    assert slave.applied[-1].tracker.ident.sigma_limit_lh_um == pytest.approx(0.25)
    assert client(p.COPY_CAL_PAGE, 0, 0, 0, 1) == err(p.ERR_WRITE_PROTECTED)


def test_writes_off_makes_the_working_page_read_only():
    cfg = DaemonConfig()
    s = XcpSlave(CODEC.db, lambda: cfg, cfg, lambda c: None, b"", port=0, writes=False)
    s.start()
    c = Client(s.address)
    try:
        c(p.CONNECT, 0)
        set_mta(c, CAL_BASE)
        assert c(p.DOWNLOAD, 4, struct.pack("<f", 14.0)) == err(p.ERR_WRITE_PROTECTED)
        assert s.counters.writes == 0
    finally:
        c.close()
        s.close()


def test_memory_outside_the_map_and_daq_out_of_sequence_are_errors(slave, client):
    client(p.CONNECT, 0)
    set_mta(client, 0x0500_0000)
    assert client(p.UPLOAD, 4) == err(p.ERR_ACCESS_DENIED)
    assert client(p.UPLOAD, 0) == err(p.ERR_OUT_OF_RANGE)
    assert client(p.FREE_DAQ) == b"\xff"
    assert client(p.WRITE_DAQ, 0xFF, 4, 0, struct.pack("<I", CAL_BASE)) == err(p.ERR_SEQUENCE)
    assert client(p.ALLOC_DAQ, 0, struct.pack("<H", 1)) == b"\xff"
    own = len(predefined_lists(CODEC.db))                                 # the master's lists come after them
    assert client(p.START_STOP_DAQ_LIST, 1, struct.pack("<H", own)) == err(p.ERR_DAQ_CONFIG)   # nothing in it
    assert client(p.START_STOP_DAQ_LIST, 1, struct.pack("<H", own + 1)) == err(p.ERR_OUT_OF_RANGE)
    assert client(p.SET_DAQ_LIST_MODE, 0x10, struct.pack("<HH", own, len(EVENTS)), 1, 0) == err(p.ERR_OUT_OF_RANGE)
    assert client(p.DOWNLOAD) == err(p.ERR_CMD_SYNTAX)                   # too short to be a command


def frame_of(message: str, injector: int, counter: int) -> tuple[int, bytes]:
    """A frame the daemon would send: ``message`` of ``injector``, its fields filled from ``counter``."""
    msg = CODEC.db.get_message_by_name(message)
    data = bytearray((injector,)) + bytes((counter + k) & 0xFF for k in range(1, msg.length))
    return msg.frame_id, bytes(data)


def test_an_injectors_predefined_list_sends_its_injections_frames_on_its_own_event(slave, client):
    """A ready DAQ list per injector: described as the standard says (predefined, its event fixed, one
    ODT of its frames), read-only, started without configuring anything, and sampled on that
    injector's estimates only: one DTO, its PID, a timestamp and the bytes its CAN frames had."""
    lists = predefined_lists(CODEC.db)
    client(p.CONNECT, 0)
    r = client(p.GET_DAQ_PROCESSOR_INFO)
    max_daq, events, min_daq = struct.unpack_from("<HHB", r, 2)
    assert r[1] & 0x01 and (min_daq, max_daq, events) == (len(lists), len(lists) + 16, len(EVENTS))
    three = lists[3]
    r = client(p.GET_DAQ_LIST_INFO, 0, struct.pack("<H", 3))
    assert r[1] == 0x07 and (r[2], r[3], struct.unpack_from("<H", r, 4)[0]) == (1, len(three.entries), 5)
    assert injector_event(3) == three.event == 5
    assert client(p.SET_DAQ_PTR, 0, struct.pack("<HBB", 3, 0, 0)) == b"\xff"
    read = [struct.unpack_from("<BBI", client(p.READ_DAQ), 2) for _ in three.entries]
    assert [(a, n) for n, _, a in read] == list(three.entries)
    assert client(p.READ_DAQ) == err(p.ERR_DAQ_CONFIG)                       # past its last entry
    assert client(p.SET_DAQ_PTR, 0, struct.pack("<HBB", 3, 0, 0)) == b"\xff"
    assert client(p.WRITE_DAQ, 0xFF, 4, 0, struct.pack("<I", CAL_BASE)) == err(p.ERR_WRITE_PROTECTED)
    assert client(p.CLEAR_DAQ_LIST, 0, struct.pack("<H", 3)) == err(p.ERR_WRITE_PROTECTED)
    assert client(p.SET_DAQ_LIST_MODE, 0x10, struct.pack("<HH", 3, 0), 1, 0) == err(p.ERR_OUT_OF_RANGE)
    assert client(p.FREE_DAQ) == b"\xff"                                      # frees the master's lists only
    assert client(p.START_STOP_DAQ_LIST, 1, struct.pack("<H", 3)) == b"\xff\x03"   # PID 3, timestamped
    frames = {inj: [frame_of(m, inj, 10 * inj) for m in ("EstimateState", "EstimateQuality", "ValvePrediction",
                                                         "ModelCalibration", "DriveCorrection")] for inj in (3, 5)}
    for inj in (5, 3):
        for fid, data in frames[inj]:
            slave.store(fid, data)
        slave.injection(inj)
    dto, _ = client.sock.recvfrom(65535)
    (_, pid), = [(c, x) for c, x in p.packets(dto)]
    assert pid[0] == 3                                                         # injector 5's event sent nothing
    assert pid[5:] == b"".join(data for _, data in frames[3])
    assert client(p.START_STOP_SYNCH, 0) == b"\xff"
    assert slave.counters.dtos == 1


def test_the_a2l_is_served_by_get_id_and_passes_a2ltool(slave, client, tmp_path):
    client(p.CONNECT, 0)
    r = client(p.GET_ID, 4)
    length = struct.unpack_from("<I", r, 4)[0]
    got = b""
    while len(got) < length:
        got += client(p.UPLOAD, min(254, length - len(got)))[1:]
    assert got == a2l_bytes(CODEC.db, "t", slave.address)
    tool = shutil.which("a2ltool", path=str(Path(sys.executable).parent)) or shutil.which("a2ltool")
    assert tool, "a2ltool (the test extra) is not installed"
    f = tmp_path / "x.a2l"
    f.write_bytes(got)
    out = subprocess.run([tool, str(f), "--check", "--strict"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "No problems found" in out.stdout + out.stderr, out.stdout + out.stderr
    # the IF_DATA XCP block parses by the A2L's own A2ML (a2ltool drops every block that does not) ...
    kept = tmp_path / "kept.a2l"
    subprocess.run([tool, str(f), "--ifdata-cleanup", "--output", str(kept)], capture_output=True, timeout=60,
                   check=True)
    text = kept.read_text()
    assert text.count("/begin IF_DATA XCP") == 2                     # the module's, the calibration segment's
    assert "/begin PAGE 0 ECU_ACCESS_DONT_CARE XCP_READ_ACCESS_DONT_CARE XCP_WRITE_ACCESS_DONT_CARE" in text
    assert "/begin PAGE 1 ECU_ACCESS_DONT_CARE XCP_READ_ACCESS_DONT_CARE XCP_WRITE_ACCESS_NOT_ALLOWED" in text
    assert text.count("/begin DAQ_LIST") == len(predefined_lists(CODEC.db))
    assert text.count("/begin EVENT ") == len(EVENTS)
    # ... and a tool that knows the standard's layout reads the address the slave listens on from it
    xcp = subprocess.run([tool, str(f), "--show-xcp"], capture_output=True, text=True, timeout=60).stdout
    assert "UDP" in xcp and "127.0.0.1" in xcp and f"port: {slave.address[1]}" in xcp, xcp


def test_an_a2l_whose_if_data_breaks_its_a2ml_is_caught(tmp_path):
    """The check above can fail: one wrong keyword in the IF_DATA and a2ltool drops the block."""
    tool = shutil.which("a2ltool", path=str(Path(sys.executable).parent)) or shutil.which("a2ltool")
    assert tool, "a2ltool (the test extra) is not installed"
    f, kept = tmp_path / "x.a2l", tmp_path / "kept.a2l"
    f.write_text(render(CODEC.db).replace("BYTE_ORDER_MSB_LAST ADDRESS", "BYTE_ORDER_LAST ADDRESS"))
    subprocess.run([tool, str(f), "--ifdata-cleanup", "--output", str(kept)], capture_output=True, timeout=60,
                   check=True)
    assert "/begin PROTOCOL_LAYER" not in kept.read_text()       # the module's block went; the segment's stays


def test_a2l_dbc_and_configuration_agree():
    """Each A2L measurement is a DBC signal with its conversion and range; each characteristic's limits
    are ones the configuration accepts, and just beyond them it refuses (or the DBC cannot carry)."""
    text = render(CODEC.db)
    for m in measurements(CODEC.db):
        sig = CODEC.db.get_message_by_name(m.message).get_signal_by_name(m.signal)
        assert f"/begin MEASUREMENT {m.name} " in text
        assert (m.factor, m.offset) == (sig.scale, sig.offset)
        shift = (m.bit_mask & -m.bit_mask).bit_length() - 1
        assert 8 * (m.address - min(a for (fid, _), a in slot_layout(CODEC.db).items()
                                    if fid == CODEC.db.get_message_by_name(m.message).frame_id
                                    and _ == m.injector)) + shift == sig.start
    cfg = DaemonConfig()
    chars = characteristics()
    paired = ("drive_correction.scale_", "drive_correction.offset_")   # a low/high pair: checked as a pair
    for c in chars:
        assert f"/begin CHARACTERISTIC {c.name} " in text

        def accepted(value: float, c=c) -> bool:
            page = bytearray(page_bytes(cfg, chars))
            struct.pack_into("<" + c.fmt, page, c.offset, value if c.fmt == "f" else int(value))
            try:
                apply_page(cfg, bytes(page), chars)
                return True
            except (ValueError, PermissionError):
                return False
        if not c.name.startswith(paired):
            assert accepted(c.lo) and accepted(c.hi), c.name
        assert not accepted(c.hi + max(1.0, abs(c.hi))), c.name
        if c.fmt == "f":
            assert not accepted(float("nan")), c.name
    assert apply_page(cfg, page_bytes(replace(cfg, stale_after_ms=1.0), chars), chars).stale_after_ms == 1.0


def test_hostile_datagrams_cost_one_count_each_and_the_slave_serves_on(slave, client):
    """10,000 random datagrams from another peer (some of them well-formed commands): each is counted,
    none ends the slave, and the master is answered after every batch."""
    rng = np.random.default_rng(5)
    hostile = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    hostile.bind(("127.0.0.1", 0))
    sent = 0
    try:
        for _ in range(100):
            for _ in range(100):
                n = int(rng.integers(0, 300))
                raw = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
                if rng.uniform() < 0.5 and n >= 1:   # half of them framed, so the commands behind are tried
                    raw = p.frame(int(rng.integers(0, 65536)), raw[:p.MAX_CTO])
                hostile.sendto(raw, slave.address)
                sent += 1
            assert client(p.CONNECT, 0)[0] == p.RES     # processed in order: the batch is behind us
    finally:
        hostile.close()
    assert slave.counters.datagrams == sent + 100
    assert slave._thread.is_alive()


def test_a_daemon_that_cannot_take_a_write_answers_generic_and_keeps_its_page():
    cfg = DaemonConfig()

    def fails(_new):
        raise RuntimeError("the parameter file went away")
    s = XcpSlave(CODEC.db, lambda: cfg, cfg, fails, b"", port=0)
    s.start()
    c = Client(s.address)
    try:
        c(p.CONNECT, 0)
        sigma = char("ident.sigma_limit_lh_um")
        set_mta(c, sigma.address)
        assert c(p.DOWNLOAD, 4, struct.pack("<f", 0.5)) == err(p.ERR_GENERIC)
        r = c(p.SHORT_UPLOAD, 4, 0, 0, struct.pack("<I", sigma.address))
        assert struct.unpack("<f", r[1:])[0] == pytest.approx(0.25)      # the page is what the daemon uses
        assert s.counters.writes == 0
    finally:
        c.close()
        s.close()


def test_the_a2l_command_writes_the_configured_slaves_address(tmp_path):
    """``estimator a2l --config``: the A2L says where the configured slave listens (what GET_ID serves
    from that daemon); a configuration it cannot read is one error line and a non-zero exit."""
    from estimator import __version__
    from estimator.cli import main

    cfg = tmp_path / "e.toml"
    cfg.write_text('[estimator.xcp]\nmode = "on"\nhost = "127.0.0.1"\nport = 6123\n')
    out = tmp_path / "e.a2l"
    assert main(["a2l", "--config", str(cfg), "--out", str(out)]) == 0
    assert out.read_bytes() == a2l_bytes(CODEC.db, __version__, ("127.0.0.1", 6123))
    assert '0x0100 6123 ADDRESS "127.0.0.1"' in out.read_text()
    assert "/begin PAGE 0 ECU_ACCESS_DONT_CARE XCP_READ_ACCESS_DONT_CARE XCP_WRITE_ACCESS_DONT_CARE" in out.read_text()
    cfg.write_text('[estimator.xcp]\nmode = "on"\nwrites = false\n')          # a read-only working page says so
    assert main(["a2l", "--config", str(cfg), "--out", str(out)]) == 0
    assert "/begin PAGE 0 ECU_ACCESS_DONT_CARE XCP_READ_ACCESS_DONT_CARE XCP_WRITE_ACCESS_NOT_ALLOWED" in out.read_text()
    assert '0x0100 5555 ADDRESS "127.0.0.1"' in out.read_text()
    cfg.write_text('[estimator.xcp]\nmode = "on"\nport = 99999\n')
    assert main(["a2l", "--config", str(cfg), "--out", str(out)]) != 0


def test_pyxcps_own_daq_setup_numbers_the_masters_lists_after_the_predefined_ones(slave, monkeypatch):
    """pyxcp's high-level DAQ (``DaqOnlinePolicy``: FREE_DAQ, ALLOC_DAQ and its lists numbered from the
    slave's MIN_DAQ) measures on the slave as a user's script would: every estimate of injector 0 on
    the injection event, decoded by pyxcp, with its timestamp. The policy builds pyxcp's application
    from the command line, as a user's script run bare would: not from pytest's options."""
    pytest.importorskip("pyxcp", reason="pyxcp is the test extra's XCP master")
    monkeypatch.setattr(sys, "argv", [sys.argv[0]])
    import warnings

    from pyxcp.daq_stim import DaqList, DaqOnlinePolicy

    from estimator.service.xcp.daq_lists import EVENT_INJECTION
    from sim_bench.benches.xcp_bench import pyxcp_master
    from sim_bench.hardware.procs import wait_until

    class Collect(DaqOnlinePolicy):
        def __init__(self, lists) -> None:
            super().__init__(lists)
            self.rows: list[tuple[int, list]] = []

        def initialize(self) -> None:
            pass

        def on_daq_list(self, daq_list: int, timestamp0: int, timestamp1: int, payload: list) -> None:
            self.rows.append((timestamp1, list(payload)))

        def finalize(self) -> None:
            pass

    slot = slot_layout(CODEC.db)[(CODEC.db.get_message_by_name("EstimateState").frame_id, 0)]
    policy = Collect([DaqList(name="state0", event_num=EVENT_INJECTION, stim=False, enable_timestamps=True,
                              measurements=[("low", slot, 0, "U32"), ("high", slot + 4, 0, "U32")])])
    frames = [frame_of("EstimateState", 0, 20 * k) for k in range(5)]
    with warnings.catch_warnings(), pyxcp_master(slave.address[1], policy) as x:
        warnings.simplefilter("ignore")
        x.connect()
        policy.setup()
        policy.start()
        for fid, data in frames:
            slave.store(fid, data)
            slave.injection(0)
        assert wait_until(lambda: len(policy.rows) == 5, 10), policy.rows
        policy.stop()
        x.disconnect()
    assert [struct.pack("<II", *values) for _, values in policy.rows] == [data for _, data in frames]
    stamps = [t for t, _ in policy.rows]
    assert stamps == sorted(stamps)
    assert slave.daq[len(predefined_lists(CODEC.db))].odts     # the master's list, after the predefined ones
