"""The A2L (ASAM MCD-2 MC 1.7) the XCP slave serves and ``python -m estimator a2l`` writes: its
measurements from the DBC (:func:`~estimator.service.xcp.memory.measurements`), its characteristics
from the configuration (:func:`~estimator.service.xcp.memory.characteristics`), one text for both."""

from __future__ import annotations

import re

from cantools.database import Database

from estimator.service.config import XcpConfig
from estimator.service.xcp.if_data import a2ml, if_data, segment
from estimator.service.xcp.memory import (
    A2L_BASE,
    CAL_BASE,
    CAL_BYTES,
    MEAS_BASE,
    SLAVE_COUNTERS,
    SLOT_BYTES,
    STATS_BASE,
    Characteristic,
    Measurement,
    characteristics,
    counter_measurements,
    measurements,
    slot_layout,
)

NAME = "injector_estimator"     # the A2L's name: GET_ID type 1, and the file name the command suggests
ADDRESS = (XcpConfig.host, XcpConfig.port)   # [estimator.xcp]'s default host and port


def _text(s: str) -> str:
    """An A2L string: quotes doubled away, one line."""
    return '"' + s.replace("\\", "/").replace('"', "'").replace("\n", " ") + '"'


def _ident(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.]", "_", s)


def _number(x: float) -> str:
    return repr(float(x)) if x != int(x) or abs(x) >= 1e15 else str(int(x))


def _format(factor: float) -> str:
    """A display format with the decimals a factor's resolution needs."""
    decimals = 0
    while decimals < 6 and abs(factor * 10 ** decimals - round(factor * 10 ** decimals)) > 1e-9:
        decimals += 1
    return f"%10.{decimals}"


def _vtab(name: str, values: tuple[tuple[int, str], ...] | tuple[str, ...]) -> list[str]:
    pairs = list(enumerate(values)) if values and isinstance(values[0], str) else list(values)
    body = " ".join(f"{int(k)} {_text(str(v))}" for k, v in pairs)
    return [f"    /begin COMPU_VTAB VT_{name} \"\" TAB_VERB {len(pairs)} {body}", "    /end COMPU_VTAB"]


def render(db: Database, version: str = "", address: tuple[str, int] = ADDRESS, writes: bool = True) -> str:
    """The A2L text for the DBC ``db`` (the daemon's own), the calibratable configuration keys and the
    slave listening on ``address`` (host, UDP port), its working page writable when ``writes``."""
    meas = measurements(db) + counter_measurements()
    chars = characteristics()
    slots = len(slot_layout(db))
    out = ["ASAP2_VERSION 1 71",
           f"/begin PROJECT {NAME} {_text('Piezo injector estimator: per-injection N_u, L_h, valve prediction and drive correction')}",
           f"  /begin HEADER {_text('Written by the daemon from its DBC and its configuration')}",
           f"    VERSION {_text(version or 'unversioned')}",
           "  /end HEADER",
           f"  /begin MODULE estimator {_text('The estimator daemon (XCP on Ethernet, UDP)')}",
           a2ml(),
           "    /begin MOD_COMMON \"\"",
           "      BYTE_ORDER MSB_LAST",
           "      ALIGNMENT_BYTE 1",
           "    /end MOD_COMMON",
           "    /begin MOD_PAR \"\"",
           f"      /begin MEMORY_SEGMENT measurements {_text('The last frame of each output message, per injector')}"
           f" DATA RAM INTERN 0x{MEAS_BASE:X} 0x{slots * SLOT_BYTES:X} -1 -1 -1 -1 -1",
           "      /end MEMORY_SEGMENT",
           f"      /begin MEMORY_SEGMENT slave {_text('The XCP slave counters')}"
           f" DATA RAM INTERN 0x{STATS_BASE:X} 0x{4 * len(SLAVE_COUNTERS):X} -1 -1 -1 -1 -1",
           "      /end MEMORY_SEGMENT",
           f"      /begin MEMORY_SEGMENT calibration {_text('Calibratable configuration: page 0 working, page 1 reference')}"
           f" DATA FLASH INTERN 0x{CAL_BASE:X} 0x{CAL_BYTES:X} -1 -1 -1 -1 -1",
           *segment(writes),
           "      /end MEMORY_SEGMENT",
           "    /end MOD_PAR",
           *if_data(db, address),
           "    /begin COMPU_METHOD CM_IDENTICAL \"\" IDENTICAL \"%10.3\" \"\"",
           "    /end COMPU_METHOD"]
    methods: dict[str, str] = {}
    for m in meas:
        key = f"{m.message}_{m.signal}"
        if key in methods:
            continue
        methods[key] = f"CM_{_ident(key)}"
        if m.values:
            out += [f"    /begin COMPU_METHOD {methods[key]} \"\" TAB_VERB \"%4.0\" {_text(m.unit)}",
                    f"      COMPU_TAB_REF VT_{_ident(key)}", "    /end COMPU_METHOD"]
            out += _vtab(_ident(key), m.values)
        else:
            out += [f"    /begin COMPU_METHOD {methods[key]} \"\" LINEAR {_text(_format(m.factor))} {_text(m.unit)}",
                    f"      COEFFS_LINEAR {_number(m.factor)} {_number(m.offset)}", "    /end COMPU_METHOD"]
    for c in chars:
        if c.words:
            out += [f"    /begin COMPU_METHOD CM_{_ident(c.name)} \"\" TAB_VERB \"%4.0\" \"\"",
                    f"      COMPU_TAB_REF VT_{_ident(c.name)}", "    /end COMPU_METHOD"]
            out += _vtab(_ident(c.name), c.words)
        else:
            out += [f"    /begin COMPU_METHOD CM_{_ident(c.name)} \"\" IDENTICAL \"%10.4\" {_text(c.unit)}",
                    "    /end COMPU_METHOD"]
    for kind in sorted({c.datatype for c in chars}):
        out += [f"    /begin RECORD_LAYOUT RL_{kind} FNC_VALUES 1 {kind} COLUMN_DIR DIRECT", "    /end RECORD_LAYOUT"]
    out += [_measurement(m, methods[f"{m.message}_{m.signal}"]) for m in meas]
    out += [_characteristic(c) for c in chars]
    out += _groups(meas, chars)
    out += ["  /end MODULE", "/end PROJECT", ""]
    return "\n".join(out)


def _measurement(m: Measurement, method: str) -> str:
    lo, hi = sorted((m.lo, m.hi))
    lines = [f"    /begin MEASUREMENT {_ident(m.name)} {_text(m.comment)}",
             f"      {m.datatype} {method} 0 0 {_number(lo)} {_number(hi)}",
             f"      ECU_ADDRESS 0x{m.address:X}"]
    full = (1 << (8 * m.size)) - 1
    if m.bit_mask != full:
        lines.append(f"      BIT_MASK 0x{m.bit_mask:X}")
    if m.unit and not m.values:
        lines.append(f"      PHYS_UNIT {_text(m.unit)}")
    lines.append("    /end MEASUREMENT")
    return "\n".join(lines)


def _characteristic(c: Characteristic) -> str:
    return "\n".join([f"    /begin CHARACTERISTIC {_ident(c.name)} {_text(c.comment)}",
                      f"      VALUE 0x{c.address:X} RL_{c.datatype} 0 CM_{_ident(c.name)} {_number(c.lo)} {_number(c.hi)}",
                      "    /end CHARACTERISTIC"])


def _groups(meas: list[Measurement], chars: list[Characteristic]) -> list[str]:
    """One group per injector (its measurements), one for the daemon's health, one for the characteristics."""
    out: list[str] = []
    by: dict[str, list[str]] = {}
    for m in meas:
        by.setdefault(f"injector_{m.injector}" if m.injector is not None else "daemon", []).append(_ident(m.name))
    for name, members in sorted(by.items()):
        out += [f"    /begin GROUP {name} {_text('Measurements of ' + name.replace('_', ' '))} ROOT",
                "      /begin REF_MEASUREMENT", *(f"        {x}" for x in members), "      /end REF_MEASUREMENT",
                "    /end GROUP"]
    out += [f"    /begin GROUP calibration {_text('Calibratable configuration keys')} ROOT",
            "      /begin REF_CHARACTERISTIC", *(f"        {_ident(c.name)}" for c in chars),
            "      /end REF_CHARACTERISTIC", "    /end GROUP"]
    return out


def a2l_bytes(db: Database, version: str = "", address: tuple[str, int] = ADDRESS, writes: bool = True) -> bytes:
    """:func:`render` as the bytes GET_ID serves and the command writes (UTF-8)."""
    return render(db, version, address, writes).encode("utf-8")


__all__ = ["A2L_BASE", "ADDRESS", "NAME", "a2l_bytes", "render"]
