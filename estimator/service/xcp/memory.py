"""The XCP slave's address space: what each address holds, described once for the slave and the A2L.

* **Measurements** (``MEAS_BASE``): the last frame the daemon sent of each of its output messages, per
  injector for the multiplexed ones: a measurement is a DBC signal at its bits in that frame's
  payload, with the DBC's factor, offset, unit, range and value table. The A2L is written from the
  DBC, so the two cannot disagree, and DAQ of an injector's slot gives the bytes its CAN frame had.
* **Characteristics** (``CAL_BASE``): the configuration's calibratable keys, each a little-endian
  number at its own address, on two pages: the working page (RAM, page 0, written by DOWNLOAD) and the
  reference page (FLASH, page 1: the configuration file's values, read-only).
* **The slave's counters** (``STATS_BASE``): datagrams, packets answered, dropped, errors, writes, DAQ
  packets sent and lost, uint32 each.
* **The A2L itself** (``A2L_BASE``): uploaded after GET_ID type 4.

Addresses carry address extension 0; byte order is Intel (little-endian), the granularity a byte.
"""

from __future__ import annotations

import math
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from cantools.database import Database

from estimator.pipeline.config import ConfigError

MEAS_BASE = 0x0001_0000
SLOT_BYTES = 64                 # one frame payload (CAN FD: 64 bytes at most)
STATS_BASE = 0x0004_0000        # the slave's own counters, uint32 each (SLAVE_COUNTERS)
SLAVE_COUNTERS = (("datagrams", "UDP datagrams received"),
                  ("packets", "Command packets answered (a response or an error)"),
                  ("dropped", "Datagrams or packets dropped: malformed, before CONNECT, or from another peer"),
                  ("errors", "Error responses sent"),
                  ("writes", "Calibration writes applied"),
                  ("dtos", "DAQ packets sent"),
                  ("overruns", "DAQ packets the socket did not take (lost)"))
CAL_BASE = 0x0008_0000
A2L_BASE = 0x1000_0000
EXTENSION = 0
INJECTOR_SLOTS = 8              # InjectorId 0..7 (the DBC's multiplexer)
TRANSMITTER = "Estimator"      # the DBC node whose messages the daemon sends


@dataclass(frozen=True)
class Measurement:
    """One DBC signal of one slot: ``address`` of the byte its first bit is in, ``size`` bytes read,
    ``bit_mask`` and sign as the A2L gives them, physical = factor × raw + offset."""

    name: str
    message: str
    signal: str
    injector: int | None
    address: int
    size: int
    bit_mask: int
    signed: bool
    factor: float
    offset: float
    unit: str
    lo: float
    hi: float
    comment: str
    values: tuple[tuple[int, str], ...]

    @property
    def datatype(self) -> str:
        """The A2L data type of the ``size`` bytes read."""
        kinds = {1: "BYTE", 2: "WORD", 4: "LONG"}
        if self.size == 8:
            return "A_INT64" if self.signed else "A_UINT64"
        return ("S" if self.signed else "U") + kinds[self.size]


def output_messages(db: Database) -> list[Any]:
    """The messages the daemon sends that carry no samples, by frame id (the A2L's and the slots' order)."""
    return sorted((m for m in db.messages if TRANSMITTER in m.senders and m.length <= SLOT_BYTES),
                  key=lambda m: m.frame_id)


def slot_layout(db: Database) -> dict[tuple[int, int | None], int]:
    """(frame id, injector or None) -> the slot's address: eight slots for a message multiplexed by
    InjectorId, one for the others."""
    out: dict[tuple[int, int | None], int] = {}
    address = MEAS_BASE
    for msg in output_messages(db):
        for inj in (range(INJECTOR_SLOTS) if msg.is_multiplexed() else (None,)):
            out[(msg.frame_id, inj)] = address
            address += SLOT_BYTES
    return out


def measurements(db: Database) -> list[Measurement]:
    """Every output signal of every slot (the multiplexer itself included: it names the slot's injector)."""
    layout = slot_layout(db)
    out = []
    for msg in output_messages(db):
        for (fid, inj), base in layout.items():
            if fid != msg.frame_id:
                continue
            for sig in msg.signals:
                if sig.byte_order != "little_endian":
                    raise ValueError(f"{msg.name}.{sig.name}: only Intel byte order has an XCP address")
                first = sig.start // 8
                shift = sig.start - 8 * first
                size = next(n for n in (1, 2, 4, 8) if shift + sig.length <= 8 * n)
                name = f"{msg.name}.{sig.name}" + (f"_{inj}" if inj is not None else "")
                choices = tuple(sorted((int(k), str(v)) for k, v in (sig.choices or {}).items()))
                comment = (sig.comment or msg.comment or "").replace('"', "'")
                lo = sig.minimum if sig.minimum is not None else _raw_bound(sig, low=True)
                hi = sig.maximum if sig.maximum is not None else _raw_bound(sig, low=False)
                if lo == hi == 0:
                    lo, hi = _raw_bound(sig, low=True), _raw_bound(sig, low=False)
                out.append(Measurement(name, msg.name, sig.name, inj, base + first, size,
                                       ((1 << sig.length) - 1) << shift, sig.is_signed, float(sig.scale),
                                       float(sig.offset), sig.unit or "", float(lo), float(hi), comment, choices))
    return out


def counter_measurements() -> list[Measurement]:
    """The slave's own counters as measurements (``XcpSlave.<name>``)."""
    return [Measurement(f"XcpSlave.{name}", "XcpSlave", name, None, STATS_BASE + 4 * i, 4, 0xFFFFFFFF, False,
                        1.0, 0.0, "", 0.0, float(0xFFFFFFFF), comment, ())
            for i, (name, comment) in enumerate(SLAVE_COUNTERS)]


def _raw_bound(sig: Any, low: bool) -> float:
    """The physical value of the signal's smallest or largest raw value."""
    raw = -(1 << (sig.length - 1)) if sig.is_signed and low else (
        (1 << (sig.length - 1)) - 1 if sig.is_signed else (0 if low else (1 << sig.length) - 1))
    return float(sig.scale * raw + sig.offset)


@dataclass(frozen=True)
class Characteristic:
    """One calibratable configuration key at ``CAL_BASE + offset``: a ``fmt`` number (struct code) in
    ``unit`` within [``lo``, ``hi``] (the configuration's own limits, a test keeps them so), read from a
    configuration by ``get`` and written into one by ``put``; ``words``: the words of its codes."""

    name: str
    offset: int
    fmt: str
    unit: str
    lo: float
    hi: float
    comment: str
    get: Callable[[Any], float]
    put: Callable[[Any, float], Any]
    words: tuple[str, ...] = ()

    @property
    def size(self) -> int:
        return struct.calcsize("<" + self.fmt)

    @property
    def address(self) -> int:
        return CAL_BASE + self.offset

    @property
    def datatype(self) -> str:
        return {"f": "FLOAT32_IEEE", "H": "UWORD", "B": "UBYTE"}[self.fmt]


def _drive(cfg: Any) -> Any:
    if cfg.drive_correction is None:
        raise PermissionError("drive correction is off (mode = \"off\")")
    return cfg.drive_correction


def _target(key: str) -> tuple[Callable[[Any], float], Callable[[Any, float], Any]]:
    def get(cfg: Any) -> float:
        v = getattr(cfg.drive_correction, key) if cfg.drive_correction is not None else None
        return 0.0 if v is None else float(v)

    def put(cfg: Any, value: float) -> Any:
        return replace(cfg, drive_correction=replace(_drive(cfg), **{key: None if value == 0 else value}))
    return get, put


def _limit(key: str, end: int) -> tuple[Callable[[Any], float], Callable[[Any, float], Any]]:
    def get(cfg: Any) -> float:
        return float(getattr(cfg.drive_correction, key)[end]) if cfg.drive_correction is not None else 0.0

    def put(cfg: Any, value: float) -> Any:
        pair = list(getattr(_drive(cfg), key))
        pair[end] = value
        return replace(cfg, drive_correction=replace(_drive(cfg), **{key: tuple(pair)}))
    return get, put


def _learning_mode() -> tuple[Callable[[Any], float], Callable[[Any, float], Any]]:
    def put(cfg: Any, value: float) -> Any:
        from estimator.ident.learning.selfcal import SelfCalConfig
        if value == 0:
            return replace(cfg, self_calibration=None)
        return cfg if cfg.self_calibration is not None else replace(cfg, self_calibration=SelfCalConfig())
    return (lambda cfg: 0.0 if cfg.self_calibration is None else 1.0), put


def _retry_after() -> tuple[Callable[[Any], float], Callable[[Any, float], Any]]:
    def put(cfg: Any, value: float) -> Any:
        if cfg.self_calibration is None:
            raise PermissionError("learning is off (mode = \"off\")")
        return replace(cfg, self_calibration=replace(cfg.self_calibration, retry_after=int(value)))
    return (lambda cfg: float(cfg.self_calibration.retry_after) if cfg.self_calibration is not None else 0.0), put


def characteristics() -> list[Characteristic]:
    """The calibratable keys, in address order (each on a 4-byte boundary)."""
    rows: list[tuple[str, str, str, float, float, str, tuple[Callable[[Any], float], Callable[[Any, float], Any]],
                     tuple[str, ...]]] = [
        ("drive_correction.stroke_um", "f", "um", 0.0, 65.5,
         "Target plateau stroke; 0: the default rule's", _target("stroke_um"), ()),
        ("drive_correction.opening_us", "f", "us", 0.0, 327.0,
         "Target opening instant after the standard drive's start of charging; 0: the default rule's",
         _target("opening_us"), ()),
        ("drive_correction.scale_min", "f", "", 0.01, 13.1, "Smallest plateau current scale a correction asks for",
         _limit("scale_limits", 0), ()),
        ("drive_correction.scale_max", "f", "", 0.01, 13.1, "Largest plateau current scale a correction asks for",
         _limit("scale_limits", 1), ()),
        ("drive_correction.offset_min_us", "f", "us", -327.0, 327.0, "Earliest start-of-charge offset",
         _limit("offset_limits_us", 0), ()),
        ("drive_correction.offset_max_us", "f", "us", -327.0, 327.0, "Latest start-of-charge offset",
         _limit("offset_limits_us", 1), ()),
        ("ident.sigma_limit_lh_um", "f", "um", 0.001, 50.0,
         "Above this sigma(L_h) an estimate is uncertain, not ok", (
             lambda cfg: float(cfg.tracker.ident.sigma_limit_lh_um),
             lambda cfg, v: replace(cfg, tracker=replace(cfg.tracker, ident=replace(cfg.tracker.ident,
                                                                                    sigma_limit_lh_um=v)))), ()),
        ("stale_after_ms", "f", "ms", 1.0, 3_600_000.0,
         "An estimate published later than this after its last frame is stale, never ok", (
             lambda cfg: float(cfg.stale_after_ms), lambda cfg, v: replace(cfg, stale_after_ms=v)), ()),
        ("self_calibration.mode", "B", "", 0, 1, "Learning: 0 off, 1 on", _learning_mode(), ("off", "on")),
        ("self_calibration.retry_after", "H", "injections", 1, 10_000,
         "Injections after a refused calibration before the next window (doubling, 8x at most)", _retry_after(), ()),
    ]
    return [Characteristic(name, 4 * i, fmt, unit, lo, hi, comment, get, put, words)
            for i, (name, fmt, unit, lo, hi, comment, (get, put), words) in enumerate(rows)]


CAL_BYTES = 4 * len(characteristics())


def page_bytes(cfg: Any, chars: list[Characteristic]) -> bytes:
    """A calibration page holding ``cfg``'s values."""
    out = bytearray(CAL_BYTES)
    for c in chars:
        value = c.get(cfg)
        struct.pack_into("<" + c.fmt, out, c.offset, value if c.fmt == "f" else int(value))
    return bytes(out)


def apply_page(cfg: Any, page: bytes, chars: list[Characteristic]) -> Any:
    """``cfg`` with every characteristic's value from ``page``; ValueError naming the first value out of
    its range or refused by the configuration's own checks, PermissionError for a key whose section is off."""
    held = page_bytes(cfg, chars)
    new = cfg
    for c in chars:
        if page[c.offset:c.offset + c.size] == held[c.offset:c.offset + c.size]:
            continue   # unchanged (as a page holds it: float32)
        value = struct.unpack_from("<" + c.fmt, page, c.offset)[0]
        if not (math.isfinite(value) and c.lo <= value <= c.hi):
            raise ValueError(f"{c.name} = {value}: outside {c.lo}..{c.hi}")
        try:
            new = c.put(new, value)
        except ConfigError as exc:   # the configuration's own checks, run as it is built
            raise ValueError(str(exc)) from None
    return new


class MeasurementImage:
    """The measurement slots: the worker stores each output frame it sends, the XCP thread reads."""

    def __init__(self, db: Database) -> None:
        self.layout = slot_layout(db)
        self.multiplexed = {fid for fid, inj in self.layout if inj is not None}
        self.size = len(self.layout) * SLOT_BYTES
        self.data = bytearray(self.size)
        self.lock = threading.Lock()

    def store(self, frame_id: int, payload: bytes) -> bool:
        """Keep one sent frame's payload in its slot (True when the message has one)."""
        inj = (payload[0] & 0x07) if frame_id in self.multiplexed and payload else None
        address = self.layout.get((frame_id, inj))
        if address is None:
            return False
        at = address - MEAS_BASE
        n = min(len(payload), SLOT_BYTES)
        with self.lock:
            self.data[at:at + n] = payload[:n]
        return True

    def read(self, address: int, size: int) -> bytes | None:
        """``size`` bytes from ``address``, None outside the slots."""
        at = address - MEAS_BASE
        if at < 0 or at + size > self.size:
            return None
        with self.lock:
            return bytes(self.data[at:at + size])
