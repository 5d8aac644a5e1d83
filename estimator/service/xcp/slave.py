"""The XCP slave: a UDP server thread answering one master's commands, and DAQ on its events.

Events and predefined DAQ lists: :mod:`estimator.service.xcp.daq_lists` (an event per injection, one
per injector's injections, and a 10 Hz one; a ready list per injector and one for the daemon). A
master may add lists of its own dynamically (FREE_DAQ, ALLOC_DAQ, ALLOC_ODT, ALLOC_ODT_ENTRY), numbered
after the predefined ones; every DTO carries an absolute ODT number, and the first ODT of a list a
4-byte timestamp in µs when its mode asks for one (the predefined lists' does at start). Calibration: DOWNLOAD writes whole characteristics on the working page; the values
are checked as a configuration and handed to the daemon (``apply``), which takes them between two
injections, all at once. A malformed datagram is counted and dropped; an unknown or refused command
is answered with its error code. Nothing here runs on the worker but :meth:`XcpSlave.store` and
:meth:`XcpSlave.event` (a copy into the image; a few DTOs while DAQ runs).
"""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from estimator.service.xcp import protocol as p
from estimator.service.xcp.a2l import NAME as A2L_NAME
from estimator.service.xcp.daq_lists import (
    EVENT_INJECTION,
    EVENTS,
    MAX_DYNAMIC_LISTS,
    MAX_ENTRIES,
    MAX_ENTRY_BYTES,
    MAX_ODTS,
    injector_event,
    predefined_lists,
)
from estimator.service.xcp.memory import (
    A2L_BASE,
    CAL_BASE,
    CAL_BYTES,
    MEAS_BASE,
    SLAVE_COUNTERS,
    STATS_BASE,
    MeasurementImage,
    apply_page,
    characteristics,
    page_bytes,
)
from estimator.units import US_PER_S

log = logging.getLogger(__name__)

ID_BASE = 0x1100_0000           # GET_ID's text identifications, uploaded from here
WORKING, REFERENCE = 0, 1
SESSION_DAQ_RUNNING = 0x40
TIMESTAMP_MODE = 0x04 | 0x08 | (3 << 4)   # 4 bytes, fixed, unit 1 µs
DAQ_MODE_TIMESTAMP = 0x10


@dataclass
class _Odt:
    entries: list[tuple[int, int]] = field(default_factory=list)   # (address, size)


@dataclass
class _DaqList:
    odts: list[_Odt] = field(default_factory=list)
    mode: int = 0
    event: int = 0
    prescaler: int = 1
    selected: bool = False
    running: bool = False
    first_pid: int = 0
    count: int = 0                     # events seen (the prescaler's)
    predefined: bool = False           # read-only ODTs on a fixed event


@dataclass
class SlaveCounters:
    """What the slave counted: datagrams received, packets answered, dropped (a malformed datagram, a
    packet before CONNECT or from another peer than the master), errors sent,
    calibration writes applied, DTOs sent and DAQ overruns (a DTO the socket would not take)."""

    datagrams: int = 0
    packets: int = 0
    dropped: int = 0
    errors: int = 0
    writes: int = 0
    dtos: int = 0
    overruns: int = 0


class XcpSlave:
    """An XCP-on-Ethernet (UDP) slave for the daemon.

    ``db``: the DBC (the measurement image's layout); ``config``: returns the running configuration;
    ``reference``: the configuration file's (the reference page); ``apply``: hands a calibrated
    configuration to the daemon (raises ValueError/PermissionError to refuse it); ``a2l``: the A2L's
    bytes, or a function of the address the slave listens on that writes them; ``ident``: GET_ID type
    0's text.
    """

    def __init__(self, db: Any, config: Callable[[], Any], reference: Any, apply: Callable[[Any], None],
                 a2l: bytes | Callable[[tuple[str, int]], bytes], host: str = "127.0.0.1", port: int = 5555,
                 writes: bool = True,
                 ident: str = A2L_NAME, name: str = A2L_NAME) -> None:
        self.image = MeasurementImage(db)
        self.config = config
        self.apply = apply
        self.writes = writes
        self.chars = characteristics()
        self.lock = threading.Lock()    # the DAQ lists and the counter (commands vs events), the pages
        self.reload(reference)
        self.xcp_page = WORKING
        self.counters = SlaveCounters()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, port))
        self.sock.settimeout(0.2)
        self.address = self.sock.getsockname()
        self.a2l = a2l(self.address) if callable(a2l) else a2l
        self.ids = {0: ident.encode(), 1: name.encode(), 4: self.a2l}
        self.master: tuple[str, int] | None = None
        self.mta = 0
        self.daq: list[_DaqList] = [
            _DaqList([_Odt(list(pl.entries))], DAQ_MODE_TIMESTAMP, pl.event, first_pid=i, predefined=True)
            for i, pl in enumerate(predefined_lists(db))]
        self.min_daq = len(self.daq)
        self.daq_ptr: tuple[int, int, int] | None = None
        self.ctr = 0
        self.t0 = time.monotonic()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def reload(self, cfg: Any) -> None:
        """Both pages hold ``cfg``'s values, the configuration file's (at start, and after a SIGHUP read
        it again); the estimator uses the working page."""
        with self.lock:
            self.pages = [bytearray(page_bytes(cfg, self.chars)), page_bytes(cfg, self.chars)]
            self.ecu_page = WORKING

    # ---- lifecycle ----------------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._serve, name="xcp", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.sock.close()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                datagram, peer = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                if self._stop.is_set():
                    return
                continue
            try:
                self.receive(datagram, peer)
            except Exception:   # a bug must not end the slave: count, log, serve on
                self.counters.dropped += 1
                log.exception("XCP: a packet could not be handled (dropped)")

    # ---- the worker's side --------------------------------------------------------------------------
    def store(self, frame_id: int, payload: bytes) -> None:
        """A frame the daemon sent: its payload becomes the measurements of its slot."""
        self.image.store(frame_id, payload)

    def injection(self, injector: int) -> None:
        """An estimate of ``injector`` was published (all its frames stored): its events happened."""
        own = injector_event(injector)
        if own is None:
            self.event(EVENT_INJECTION)
        else:
            self.event(EVENT_INJECTION, own)

    def event(self, *channels: int) -> None:
        """Events ``channels`` happened together: sample and send every running DAQ list on one of
        them (one timestamp)."""
        if self.master is None:
            return
        with self.lock:
            lists = [d for d in self.daq if d.running and d.event in channels]
            if not lists:
                return
            stamp = struct.pack("<I", int((time.monotonic() - self.t0) * US_PER_S) & 0xFFFFFFFF)
            out = []
            for d in lists:
                d.count += 1
                if d.count % max(d.prescaler, 1):
                    continue
                for k, odt in enumerate(d.odts):
                    body = bytearray((d.first_pid + k,))
                    if k == 0 and d.mode & DAQ_MODE_TIMESTAMP:
                        body += stamp
                    for address, size in odt.entries:
                        body += self._read(address, size) or bytes(size)
                    out.append(self._framed(bytes(body)))
        for datagram in out:
            try:
                self.sock.sendto(datagram, self.master)
                self.counters.dtos += 1
            except (BlockingIOError, OSError):
                self.counters.overruns += 1

    # ---- the command thread -------------------------------------------------------------------------
    def receive(self, datagram: bytes, peer: tuple[str, int]) -> None:
        """One datagram from ``peer``: each packet answered, or the datagram counted as dropped."""
        self.counters.datagrams += 1
        packets = p.packets(datagram)
        if packets is None:
            self.counters.dropped += 1
            return
        for _ctr, packet in packets:
            if self.master is None and packet[0] != p.CONNECT:
                self.counters.dropped += 1     # not connected: only CONNECT is answered
                continue
            if self.master is not None and peer != self.master and packet[0] != p.CONNECT:
                self.counters.dropped += 1     # one master at a time
                continue
            try:
                reply = self.command(packet, peer)
            except p.XcpError as exc:
                self.counters.errors += 1
                reply = p.error(exc.code)
            except (IndexError, struct.error):
                self.counters.errors += 1
                reply = p.error(p.ERR_CMD_SYNTAX)
            self.counters.packets += 1
            if reply:
                with self.lock:
                    out = self._framed(reply)
                self.sock.sendto(out, peer)

    def _framed(self, packet: bytes) -> bytes:
        out = p.frame(self.ctr, packet)
        self.ctr = (self.ctr + 1) & 0xFFFF
        return out

    def command(self, c: bytes, peer: tuple[str, int]) -> bytes:
        """The response to one command packet ``c`` (XcpError: the error response)."""
        code = c[0]
        handler = self._handlers().get(code)
        if handler is None:
            raise p.XcpError(p.ERR_CMD_UNKNOWN)
        if code == p.CONNECT:
            return self._connect(c, peer)
        return handler(c)

    def _handlers(self) -> dict[int, Callable[[bytes], bytes]]:
        return {
            p.CONNECT: lambda c: b"", p.DISCONNECT: self._disconnect, p.GET_STATUS: self._get_status,
            p.SYNCH: self._synch, p.GET_COMM_MODE_INFO: self._comm_mode_info, p.GET_ID: self._get_id,
            p.SET_MTA: self._set_mta, p.UPLOAD: self._upload, p.SHORT_UPLOAD: self._short_upload,
            p.DOWNLOAD: self._download, p.SET_CAL_PAGE: self._set_cal_page, p.GET_CAL_PAGE: self._get_cal_page,
            p.GET_PAG_PROCESSOR_INFO: lambda c: bytes((p.RES, 1, 0)), p.GET_SEGMENT_INFO: self._segment_info,
            p.GET_PAGE_INFO: self._page_info, p.COPY_CAL_PAGE: self._copy_cal_page,
            p.FREE_DAQ: self._free_daq, p.ALLOC_DAQ: self._alloc_daq, p.ALLOC_ODT: self._alloc_odt,
            p.ALLOC_ODT_ENTRY: self._alloc_odt_entry, p.SET_DAQ_PTR: self._set_daq_ptr, p.WRITE_DAQ: self._write_daq,
            p.SET_DAQ_LIST_MODE: self._set_daq_list_mode, p.GET_DAQ_LIST_MODE: self._get_daq_list_mode,
            p.START_STOP_DAQ_LIST: self._start_stop_daq_list, p.START_STOP_SYNCH: self._start_stop_synch,
            p.GET_DAQ_CLOCK: self._daq_clock, p.GET_DAQ_PROCESSOR_INFO: self._daq_processor_info,
            p.GET_DAQ_RESOLUTION_INFO: lambda c: bytes((p.RES, 1, MAX_ENTRY_BYTES, 1, MAX_ENTRY_BYTES, TIMESTAMP_MODE)) + struct.pack("<H", 1),
            p.GET_DAQ_EVENT_INFO: self._daq_event_info, p.CLEAR_DAQ_LIST: self._clear_daq_list,
            p.READ_DAQ: self._read_daq, p.GET_DAQ_LIST_INFO: self._get_daq_list_info,
            p.LEVEL_1_COMMAND: self._level1,
        }

    # connection
    def _connect(self, c: bytes, peer: tuple[str, int]) -> bytes:
        if len(c) < 2 or c[1] not in (0, 1):
            raise p.XcpError(p.ERR_CMD_SYNTAX)
        if self.master is not None and peer != self.master:
            self._stop_daq()            # a new master takes the connection over
        self.master = peer
        comm_mode_basic = 0x80          # optional GET_COMM_MODE_INFO; Intel byte order, byte granularity
        return struct.pack("<BBBBHBB", p.RES, 0x01 | 0x04, comm_mode_basic, p.MAX_CTO, p.MAX_DTO,
                           p.PROTOCOL_LAYER_VERSION, p.TRANSPORT_LAYER_VERSION)

    def _disconnect(self, c: bytes) -> bytes:
        self._stop_daq()
        self.master = None
        return bytes((p.RES,))

    def _get_status(self, c: bytes) -> bytes:
        running = any(d.running for d in self.daq)
        return struct.pack("<BBBBH", p.RES, SESSION_DAQ_RUNNING if running else 0, 0, 0, 0)

    def _synch(self, c: bytes) -> bytes:
        raise p.XcpError(p.ERR_CMD_SYNCH)

    def _comm_mode_info(self, c: bytes) -> bytes:
        return bytes((p.RES, 0, 0, 0, 0, 0, 0, 0x10))

    def _level1(self, c: bytes) -> bytes:
        if c[1] != p.GET_VERSION:
            raise p.XcpError(p.ERR_CMD_UNKNOWN)
        return bytes((p.RES, 0, 1, 0, 1, 0))       # protocol 1.0, transport 1.0

    def _get_id(self, c: bytes) -> bytes:
        kind = c[1]
        data = self.ids.get(kind, b"")
        self.mta = A2L_BASE if kind == 4 else ID_BASE + (kind << 16)
        return struct.pack("<BBHI", p.RES, 0, 0, len(data))

    # memory
    def _set_mta(self, c: bytes) -> bytes:
        ext, address = struct.unpack_from("<BI", c, 3)
        if ext != 0:
            raise p.XcpError(p.ERR_OUT_OF_RANGE)
        self.mta = address
        return bytes((p.RES,))

    def _read(self, address: int, size: int) -> bytes | None:
        """``size`` bytes at ``address`` (None: not readable)."""
        if address >= STATS_BASE and address + size <= STATS_BASE + 4 * len(SLAVE_COUNTERS):
            stats = struct.pack(f"<{len(SLAVE_COUNTERS)}I", *(getattr(self.counters, n) & 0xFFFFFFFF
                                                              for n, _ in SLAVE_COUNTERS))
            return stats[address - STATS_BASE:address - STATS_BASE + size]
        if MEAS_BASE <= address < CAL_BASE:
            return self.image.read(address, size)
        if address >= CAL_BASE and address + size <= CAL_BASE + CAL_BYTES:
            at = address - CAL_BASE
            return bytes(self.pages[self.xcp_page][at:at + size])
        if address >= A2L_BASE and address + size <= A2L_BASE + len(self.a2l):
            return self.a2l[address - A2L_BASE:address - A2L_BASE + size]
        for kind, data in self.ids.items():
            base = ID_BASE + (kind << 16)
            if kind != 4 and base <= address and address + size <= base + len(data):
                return data[address - base:address - base + size]
        return None

    def _upload(self, c: bytes) -> bytes:
        n = c[1]
        if not 1 <= n <= p.MAX_CTO - 1:
            raise p.XcpError(p.ERR_OUT_OF_RANGE)
        data = self._read(self.mta, n)
        if data is None:
            raise p.XcpError(p.ERR_ACCESS_DENIED)
        self.mta += n
        return bytes((p.RES,)) + data

    def _short_upload(self, c: bytes) -> bytes:
        n = c[1]
        ext, address = struct.unpack_from("<BI", c, 3)
        if ext != 0 or not 1 <= n <= p.MAX_CTO - 1:
            raise p.XcpError(p.ERR_OUT_OF_RANGE)
        data = self._read(address, n)
        if data is None:
            raise p.XcpError(p.ERR_ACCESS_DENIED)
        self.mta = address + n
        return bytes((p.RES,)) + data

    def _download(self, c: bytes) -> bytes:
        n = c[1]
        data = c[2:2 + n]
        if not 1 <= n <= p.MAX_CTO - 2 or len(data) != n:
            raise p.XcpError(p.ERR_OUT_OF_RANGE)
        at = self.mta - CAL_BASE
        if not (at >= 0 and at + n <= CAL_BYTES):
            raise p.XcpError(p.ERR_ACCESS_DENIED if self._read(self.mta, n) is not None else p.ERR_OUT_OF_RANGE)
        if self.xcp_page == REFERENCE or not self.writes:
            raise p.XcpError(p.ERR_WRITE_PROTECTED)
        whole = [ch for ch in self.chars if at < ch.offset + ch.size and ch.offset < at + n]
        if any(ch.offset < at or ch.offset + ch.size > at + n for ch in whole):
            raise p.XcpError(p.ERR_OUT_OF_RANGE, "a write must hold whole characteristics")
        page = bytearray(self.pages[WORKING])
        page[at:at + n] = data
        if self.ecu_page == WORKING:
            self._use(bytes(page), p.ERR_OUT_OF_RANGE)
        self.pages[WORKING] = page
        self.mta += n
        self.counters.writes += 1
        log.info("XCP: calibration written: %s", ", ".join(ch.name for ch in whole) or "padding")
        return bytes((p.RES,))

    def _use(self, page: bytes, refused: int) -> None:
        """Hand the configuration ``page`` holds to the daemon; XcpError ``refused`` for a value out of
        its range or refused by the configuration, ERR_ACCESS_DENIED for a key whose section is off,
        ERR_GENERIC (logged) when the daemon could not prepare it."""
        try:
            self.apply(apply_page(self.config(), page, self.chars))
        except PermissionError as exc:
            log.warning("XCP: calibration refused: %s", exc)
            raise p.XcpError(p.ERR_ACCESS_DENIED) from None
        except ValueError as exc:
            log.warning("XCP: calibration refused: %s", exc)
            raise p.XcpError(refused) from None
        except Exception:   # e.g. a parameter file that went away while the daemon prepares the change
            log.exception("XCP: calibration not applied")
            raise p.XcpError(p.ERR_GENERIC) from None

    # pages
    def _set_cal_page(self, c: bytes) -> bytes:
        mode, segment, page = c[1], c[2], c[3]
        if page not in (WORKING, REFERENCE):
            raise p.XcpError(p.ERR_PAGE_NOT_VALID)
        if segment != 0 and not mode & 0x80:
            raise p.XcpError(p.ERR_SEGMENT_NOT_VALID)
        if not mode & 0x03:
            raise p.XcpError(p.ERR_MODE_NOT_VALID)
        if mode & 0x01 and page != self.ecu_page:
            self._use(bytes(self.pages[page]), p.ERR_PAGE_NOT_VALID)
            self.ecu_page = page
            log.info("XCP: the estimator now uses the %s page", "working" if page == WORKING else "reference")
        if mode & 0x02:
            self.xcp_page = page
        return bytes((p.RES,))

    def _get_cal_page(self, c: bytes) -> bytes:
        mode, segment = c[1], c[2]
        if segment != 0:
            raise p.XcpError(p.ERR_SEGMENT_NOT_VALID)
        if mode not in (0x01, 0x02):
            raise p.XcpError(p.ERR_MODE_NOT_VALID)
        return bytes((p.RES, 0, 0, self.ecu_page if mode == 0x01 else self.xcp_page))

    def _segment_info(self, c: bytes) -> bytes:
        mode, segment, info = c[1], c[2], c[3]
        if segment != 0:
            raise p.XcpError(p.ERR_SEGMENT_NOT_VALID)
        if mode == 0:
            return struct.pack("<BBBBI", p.RES, 0, 0, 0, CAL_BASE if info == 0 else CAL_BYTES)
        if mode == 1:
            return bytes((p.RES, 2, 0, 0, 0, 0))    # two pages, extension 0, no mapping, no compression/encryption
        raise p.XcpError(p.ERR_MODE_NOT_VALID)

    def _page_info(self, c: bytes) -> bytes:
        segment, page = c[2], c[3]
        if segment != 0:
            raise p.XcpError(p.ERR_SEGMENT_NOT_VALID)
        if page not in (WORKING, REFERENCE):
            raise p.XcpError(p.ERR_PAGE_NOT_VALID)
        # the estimator and XCP read both pages at any time; XCP writes the working page (when allowed)
        props = 0x01 | 0x02 | 0x04 | 0x08 | (0x10 | 0x20 if page == WORKING and self.writes else 0)
        return bytes((p.RES, props, 0))

    def _copy_cal_page(self, c: bytes) -> bytes:
        src_seg, src_page, dst_seg, dst_page = c[1], c[2], c[3], c[4]
        if src_seg != 0 or dst_seg != 0:
            raise p.XcpError(p.ERR_SEGMENT_NOT_VALID)
        if src_page not in (WORKING, REFERENCE) or dst_page not in (WORKING, REFERENCE):
            raise p.XcpError(p.ERR_PAGE_NOT_VALID)
        if dst_page == REFERENCE or not self.writes:
            raise p.XcpError(p.ERR_WRITE_PROTECTED)
        if src_page != dst_page:
            if self.ecu_page == WORKING:
                self._use(bytes(self.pages[src_page]), p.ERR_PAGE_NOT_VALID)
            self.pages[WORKING] = bytearray(self.pages[src_page])
            self.counters.writes += 1
        return bytes((p.RES,))

    # DAQ
    def _stop_daq(self) -> None:
        with self.lock:
            for d in self.daq:
                d.running = d.selected = False

    def _free_daq(self, c: bytes) -> bytes:
        """The master's own lists go; the predefined ones stay as they are."""
        with self.lock:
            self.daq, self.daq_ptr = self.daq[:self.min_daq], None
        return bytes((p.RES,))

    def _alloc_daq(self, c: bytes) -> bytes:
        (count,) = struct.unpack_from("<H", c, 2)
        if any(d.odts for d in self.daq[self.min_daq:]):
            raise p.XcpError(p.ERR_SEQUENCE)
        if count > MAX_DYNAMIC_LISTS:
            raise p.XcpError(p.ERR_MEMORY_OVERFLOW)
        with self.lock:
            self.daq = self.daq[:self.min_daq] + [_DaqList() for _ in range(count)]
        return bytes((p.RES,))

    def _list(self, number: int) -> _DaqList:
        if number >= len(self.daq):
            raise p.XcpError(p.ERR_OUT_OF_RANGE)
        return self.daq[number]

    def _own_list(self, number: int) -> _DaqList:
        """List ``number`` for a change of its ODTs: ERR_WRITE_PROTECTED for a predefined one."""
        d = self._list(number)
        if d.predefined:
            raise p.XcpError(p.ERR_WRITE_PROTECTED)
        return d

    def _alloc_odt(self, c: bytes) -> bytes:
        (number,) = struct.unpack_from("<H", c, 2)
        count = c[4]
        d = self._own_list(number)
        if (sum(len(x.odts) for x in self.daq[self.min_daq:]) + count > MAX_ODTS
                or any(o.entries for o in d.odts)):
            raise p.XcpError(p.ERR_MEMORY_OVERFLOW)
        with self.lock:
            d.odts.extend(_Odt() for _ in range(count))
            first = 0
            for x in self.daq:
                x.first_pid = first
                first += len(x.odts)
        return bytes((p.RES,))

    def _alloc_odt_entry(self, c: bytes) -> bytes:
        (number,) = struct.unpack_from("<H", c, 2)
        odt, count = c[4], c[5]
        d = self._own_list(number)
        if odt >= len(d.odts):
            raise p.XcpError(p.ERR_OUT_OF_RANGE)
        if count > MAX_ENTRIES or d.odts[odt].entries:
            raise p.XcpError(p.ERR_MEMORY_OVERFLOW)
        with self.lock:
            d.odts[odt].entries = [(0, 0)] * count
        return bytes((p.RES,))

    def _set_daq_ptr(self, c: bytes) -> bytes:
        (number,) = struct.unpack_from("<H", c, 2)
        odt, entry = c[4], c[5]
        d = self._list(number)
        if odt >= len(d.odts) or entry >= len(d.odts[odt].entries):
            raise p.XcpError(p.ERR_OUT_OF_RANGE)
        if d.running:
            raise p.XcpError(p.ERR_DAQ_ACTIVE)
        self.daq_ptr = (number, odt, entry)
        return bytes((p.RES,))

    def _write_daq(self, c: bytes) -> bytes:
        bit, size, ext = c[1], c[2], c[3]
        (address,) = struct.unpack_from("<I", c, 4)
        if self.daq_ptr is None:
            raise p.XcpError(p.ERR_SEQUENCE)
        number, odt, entry = self.daq_ptr
        d = self._own_list(number)
        if entry >= len(d.odts[odt].entries):
            raise p.XcpError(p.ERR_DAQ_CONFIG)
        if bit != 0xFF or ext != 0 or not 1 <= size <= MAX_ENTRY_BYTES or self._read(address, size) is None:
            raise p.XcpError(p.ERR_OUT_OF_RANGE)
        odt_bytes = sum(s for _, s in d.odts[odt].entries) - d.odts[odt].entries[entry][1] + size
        if 1 + 4 + odt_bytes > p.MAX_DTO:
            raise p.XcpError(p.ERR_DAQ_CONFIG)
        with self.lock:
            d.odts[odt].entries[entry] = (address, size)
        self.daq_ptr = (number, odt, entry + 1)
        return bytes((p.RES,))

    def _read_daq(self, c: bytes) -> bytes:
        """The ODT entry at the DAQ pointer (a predefined list's, or one the master wrote); the pointer
        moves on."""
        if self.daq_ptr is None:
            raise p.XcpError(p.ERR_SEQUENCE)
        number, odt, entry = self.daq_ptr
        entries = self._list(number).odts[odt].entries
        if entry >= len(entries):
            raise p.XcpError(p.ERR_DAQ_CONFIG)
        address, size = entries[entry]
        self.daq_ptr = (number, odt, entry + 1)
        return struct.pack("<BBBBI", p.RES, 0xFF, size, 0, address)

    def _get_daq_list_info(self, c: bytes) -> bytes:
        (number,) = struct.unpack_from("<H", c, 2)
        d = self._list(number)
        if d.predefined:      # predefined, its event fixed, DAQ
            props, odts, entries = 0x01 | 0x02 | 0x04, len(d.odts), max(len(o.entries) for o in d.odts)
        else:
            props, odts, entries = 0x04, MAX_ODTS, MAX_ENTRIES
        return struct.pack("<BBBBH", p.RES, props, odts, entries, d.event if d.predefined else 0xFFFF)

    def _set_daq_list_mode(self, c: bytes) -> bytes:
        mode = c[1]
        number, event = struct.unpack_from("<HH", c, 2)
        prescaler = c[6]
        d = self._list(number)
        if event >= len(EVENTS) or prescaler == 0 or mode & 0x02 or (d.predefined and event != d.event):
            raise p.XcpError(p.ERR_OUT_OF_RANGE)     # no STIM; a predefined list's event is fixed
        with self.lock:
            d.mode, d.event, d.prescaler = mode, event, prescaler
        return bytes((p.RES,))

    def _get_daq_list_mode(self, c: bytes) -> bytes:
        (number,) = struct.unpack_from("<H", c, 2)
        d = self._list(number)
        mode = d.mode | (0x40 if d.running else 0) | (0x01 if d.selected else 0)
        return struct.pack("<BBHHBB", p.RES, mode, 0, d.event, d.prescaler, 0)

    def _start_stop_daq_list(self, c: bytes) -> bytes:
        mode = c[1]
        (number,) = struct.unpack_from("<H", c, 2)
        d = self._list(number)
        if mode > 2:
            raise p.XcpError(p.ERR_MODE_NOT_VALID)
        if not d.odts or any(not o.entries or any(s == 0 for _, s in o.entries) for o in d.odts):
            raise p.XcpError(p.ERR_DAQ_CONFIG)
        with self.lock:
            if mode == 0:
                d.running = False
            elif mode == 1:
                d.running, d.count = True, 0
            else:
                d.selected = True
        return bytes((p.RES, d.first_pid))

    def _start_stop_synch(self, c: bytes) -> bytes:
        mode = c[1]
        if mode > 2:
            raise p.XcpError(p.ERR_MODE_NOT_VALID)
        with self.lock:
            for d in self.daq:
                if mode == 0:
                    d.running = d.selected = False
                elif d.selected:
                    d.running, d.count = mode == 1, 0
                    d.selected = False
        return bytes((p.RES,))

    def _clear_daq_list(self, c: bytes) -> bytes:
        (number,) = struct.unpack_from("<H", c, 2)
        d = self._own_list(number)
        with self.lock:
            d.running = d.selected = False
            for o in d.odts:
                o.entries = [(0, 0)] * len(o.entries)
        return bytes((p.RES,))

    def _daq_clock(self, c: bytes) -> bytes:
        return struct.pack("<BBBBI", p.RES, 0, 0, 0, int((time.monotonic() - self.t0) * US_PER_S) & 0xFFFFFFFF)

    def _daq_processor_info(self, c: bytes) -> bytes:
        properties = 0x01 | 0x02 | 0x10             # dynamic configuration, prescaler, timestamps
        return struct.pack("<BBHHBB", p.RES, properties, self.min_daq + MAX_DYNAMIC_LISTS, len(EVENTS), self.min_daq, 0)

    def _daq_event_info(self, c: bytes) -> bytes:
        (event,) = struct.unpack_from("<H", c, 2)
        if event >= len(EVENTS):
            raise p.XcpError(p.ERR_OUT_OF_RANGE)
        e = EVENTS[event]
        self.ids[0x100 + event] = e.name.encode()
        self.mta = ID_BASE + ((0x100 + event) << 16)
        return bytes((p.RES, 0x04, 0xFF, len(e.name), e.cycle, e.unit, 0))
