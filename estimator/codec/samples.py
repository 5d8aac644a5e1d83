"""Bulk sample blocks: the layout of ``InjectionSamples`` read from the DBC, decoded with numpy.

The DBC is the only place the layout lives: :class:`SampleLayout` derives byte offsets, strides
and scales from the signals ``Current_k``/``Voltage_k`` and refuses layouts numpy cannot slice
(not byte aligned, not 16-bit little-endian, no constant stride). A test proves that this decoder
and cantools agree on every field.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np
from cantools.database.can import Message

from estimator.codec.errors import ContractError

INVALID_RAW = -32768   # raw int16 reserved for "no valid sample" (ADC overflow, NaN at the source)


def sample_pairs(msg: Message) -> list[Any]:
    """The (Current_k, Voltage_k) signal pairs of the samples message, k = 0, 1, ... in order."""
    by_name = {s.name: s for s in msg.signals}
    pairs = []
    k = 0
    while f"Current_{k}" in by_name and f"Voltage_{k}" in by_name:
        pairs.append((by_name[f"Current_{k}"], by_name[f"Voltage_{k}"]))
        k += 1
    return pairs


@dataclass(frozen=True)
class SampleLayout:
    """Byte layout of the current/voltage pairs in one samples frame."""

    per_block: int
    current_offset: int     # byte offset of Current_0
    voltage_offset: int     # byte offset of Voltage_0
    stride: int             # bytes from pair k to pair k+1
    current_scale: float    # A per LSB
    voltage_scale: float    # V per LSB
    length: int             # frame length in bytes

    @classmethod
    def from_message(cls, msg: Message) -> SampleLayout:
        pairs = sample_pairs(msg)
        if not pairs:
            raise ContractError("InjectionSamples has no Current_k/Voltage_k pairs")

        def off(sig: Any) -> int:
            if sig.byte_order != "little_endian" or sig.length != 16 or not sig.is_signed or sig.start % 8:
                raise ContractError(f"{sig.name}: numpy decoding needs byte-aligned signed 16-bit little-endian")
            if sig.offset != 0:
                raise ContractError(f"{sig.name}: offsets are not supported for samples")
            result: int = sig.start // 8
            return result

        cur = [off(c) for c, _ in pairs]
        vol = [off(v) for _, v in pairs]
        stride = cur[1] - cur[0] if len(pairs) > 1 else 4
        if any(np.diff(cur) != stride) or any(np.diff(vol) != stride):
            raise ContractError("InjectionSamples pairs do not have a constant stride")
        scales_c = {c.scale for c, _ in pairs}
        scales_v = {v.scale for _, v in pairs}
        if len(scales_c) != 1 or len(scales_v) != 1:
            raise ContractError("InjectionSamples pairs do not share one scale")
        return cls(len(pairs), cur[0], vol[0], stride, scales_c.pop(), scales_v.pop(), msg.length)

    def raw_pairs(self, data: bytes) -> tuple[np.ndarray, np.ndarray]:
        """Raw int16 current and voltage of one frame, each (per_block,): read-only views of ``data``.

        An even stride is two strided int16 views (numpy reads the unaligned words of an odd offset
        itself); an odd one gathers the bytes.
        """
        if self.stride % 2 == 0:
            step, count = self.stride // 2, (self.stride // 2) * (self.per_block - 1) + 1
            return (np.frombuffer(data, dtype="<i2", count=count, offset=self.current_offset)[::step],
                    np.frombuffer(data, dtype="<i2", count=count, offset=self.voltage_offset)[::step])
        raw = np.frombuffer(data, dtype=np.uint8)
        idx_c = self.current_offset + self.stride * np.arange(self.per_block)
        idx_v = self.voltage_offset + self.stride * np.arange(self.per_block)
        cur = (raw[idx_c].astype(np.uint16) | (raw[idx_c + 1].astype(np.uint16) << 8)).view(np.int16)
        vol = (raw[idx_v].astype(np.uint16) | (raw[idx_v + 1].astype(np.uint16) << 8)).view(np.int16)
        return cur, vol

    def encode(self, header_bytes: bytes, current_raw: np.ndarray, voltage_raw: np.ndarray) -> bytes:
        """A frame from the encoded identification bytes (InjectorId, counter, block) and raw pairs."""
        buf = np.zeros(self.length, dtype=np.uint8)
        buf[: self.current_offset] = np.frombuffer(header_bytes[: self.current_offset], dtype=np.uint8)
        c = np.zeros(self.per_block, dtype="<i2")
        v = np.zeros(self.per_block, dtype="<i2")
        c[: current_raw.size] = current_raw
        v[: voltage_raw.size] = voltage_raw
        cb, vb = c.view(np.uint8).reshape(-1, 2), v.view(np.uint8).reshape(-1, 2)
        idx_c = self.current_offset + self.stride * np.arange(self.per_block)
        idx_v = self.voltage_offset + self.stride * np.arange(self.per_block)
        buf[idx_c], buf[idx_c + 1] = cb[:, 0], cb[:, 1]
        buf[idx_v], buf[idx_v + 1] = vb[:, 0], vb[:, 1]
        return buf.tobytes()

    def to_raw(self, current_a: np.ndarray, voltage_v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Physical samples -> raw int16 (rounded, saturated; NaN -> INVALID_RAW)."""
        def conv(x: np.ndarray, scale: float) -> np.ndarray:
            r = np.round(np.asarray(x, dtype=float) / scale)
            bad = ~np.isfinite(r)
            r = np.clip(np.where(bad, 0, r), INVALID_RAW + 1, 32767).astype("<i2")
            r[bad] = INVALID_RAW
            return r
        return conv(current_a, self.current_scale), conv(voltage_v, self.voltage_scale)


def samples_crc32(current_raw: np.ndarray, voltage_raw: np.ndarray) -> int:
    """CRC-32 (zlib) over the raw int16 little-endian pairs (Current_k, Voltage_k) in sample order."""
    inter = np.empty(2 * current_raw.size, dtype="<i2")
    inter[0::2] = current_raw
    inter[1::2] = voltage_raw
    return zlib.crc32(inter.tobytes()) & 0xFFFFFFFF
