"""A bus-neutral CAN frame, so the codec never imports python-can (the service converts)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Frame:
    """One CAN or CAN FD frame: identifier, payload, FD flag and a timestamp in s (monotonic or bus time)."""

    arbitration_id: int
    data: bytes
    is_fd: bool = False
    timestamp: float = 0.0
    is_extended_id: bool = False
