"""Packing a message's signal values into its payload with integer shifts, the layout read once from
the DBC (cantools): what the daemon does for every frame it publishes, ≈ 8 times cheaper than
cantools' own encoder, and byte for byte the same (a test compares them).

It covers the messages whose signals are all little-endian and sit inside the payload without
overlapping (every message of the contract); :func:`packer_for` returns None for any other, and the
codec then encodes with cantools.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True, slots=True)
class _Field:
    name: str
    start: int        # bit of the payload's least significant bit (little-endian numbering)
    mask: int         # (1 << length) - 1
    scale: float
    offset: float
    lo: int           # raw range (the signal's own, two's complement for signed ones)
    hi: int
    minimum: float    # physical range (the DBC's, else the raw range's)
    maximum: float


class Packer:
    """One message's layout: :meth:`pack_saturated` turns {signal name: physical value} into its
    payload, saturating and rounding as the codec's cantools path does before its strict encoder."""

    def __init__(self, fields: list[_Field], length: int) -> None:
        self.fields = fields
        self.length = length
        self.minimum = {f.name: f.minimum for f in fields}   # physical, by signal name
        self._rows = [(f.name, f.start, f.mask, f.scale, f.offset, f.lo, f.hi, f.minimum, f.maximum) for f in fields]

    def pack_saturated(self, values: dict[str, Any]) -> bytes:
        """The payload of any values: each saturated to its signal's range and rounded to its grid; a
        value that is None or not finite goes out as 0 (saturated), a missing one as its minimum."""
        word = 0
        isfinite = math.isfinite
        for name, start, mask, scale, offset, lo, hi, minimum, maximum in self._rows:
            v = values.get(name, minimum)     # a signal the record does not carry: its minimum
            v = float(v) if v is not None else 0.0
            if not isfinite(v):
                v = 0.0
            v = minimum if v < minimum else maximum if v > maximum else v
            raw = round((v - offset) / scale)
            raw = lo if raw < lo else hi if raw > hi else raw
            word |= (raw & mask) << start
        return word.to_bytes(self.length, "little")


def packer_for(msg: Any) -> Packer | None:
    """The packer of a cantools message, or None when its layout is not one this module packs."""
    fields = []
    used = 0
    for s in msg.signals:
        if s.byte_order != "little_endian" or s.is_float or s.length < 1 or s.start + s.length > 8 * msg.length:
            return None
        mask = (1 << s.length) - 1
        if used & (mask << s.start):
            return None
        used |= mask << s.start
        lo, hi = (-(1 << (s.length - 1)), (1 << (s.length - 1)) - 1) if s.is_signed else (0, mask)
        minimum = float(s.minimum) if s.minimum is not None else lo * s.scale + s.offset
        maximum = float(s.maximum) if s.maximum is not None else hi * s.scale + s.offset
        fields.append(_Field(s.name, s.start, mask, float(s.scale), float(s.offset), lo, hi, minimum, maximum))
    return Packer(fields, msg.length)
