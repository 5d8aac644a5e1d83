"""Opening the CAN bus from a spec string, and converting between python-can and codec frames.

Specs: ``socketcan:vcan0``, ``remote:ws://127.0.0.1:PORT/`` (python-can-remote), ``virtual:NAME``.
A SocketCAN interface must carry CAN FD (MTU 72); one with MTU 16 is refused with the command
that fixes it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import can

from estimator.codec.frame import Frame
from estimator.errors import EstimatorError

CANFD_MTU = 72


class BusSetupError(EstimatorError):
    """The bus cannot be opened as configured (one readable line says how to fix it)."""


@dataclass(frozen=True)
class BusSpec:
    """interface and channel of a bus spec string."""

    interface: str
    channel: str

    @classmethod
    def parse(cls, spec: str) -> "BusSpec":
        kind, sep, channel = spec.partition(":")
        if not sep or not channel or kind not in ("socketcan", "remote", "virtual"):
            raise BusSetupError(f"bus spec {spec!r}: use socketcan:IFACE, remote:ws://HOST:PORT/ or virtual:NAME")
        return cls(kind, channel)

    def __str__(self) -> str:
        return f"{self.interface}:{self.channel}"


def check_socketcan(channel: str, sysfs: Path = Path("/sys/class/net")) -> None:
    """Refuse a missing interface or one that cannot carry CAN FD frames."""
    dev = sysfs / channel
    if not dev.exists():
        raise BusSetupError(f"CAN interface {channel} does not exist (create it: ip link add dev {channel} type vcan "
                            f"&& ip link set {channel} mtu {CANFD_MTU} up)")
    try:
        mtu = int((dev / "mtu").read_text().strip())
    except (OSError, ValueError):
        return
    if mtu < CANFD_MTU:
        raise BusSetupError(f"CAN interface {channel} has MTU {mtu} and cannot carry CAN FD frames "
                            f"(fix: ip link set {channel} mtu {CANFD_MTU})")


def open_bus(spec: str | BusSpec, receive_own_messages: bool = False) -> can.BusABC:
    """Open the bus for CAN FD. Raises :class:`BusSetupError` with one readable line."""
    s = spec if isinstance(spec, BusSpec) else BusSpec.parse(spec)
    try:
        if s.interface == "socketcan":
            check_socketcan(s.channel)
            return can.Bus(interface="socketcan", channel=s.channel, fd=True,
                           receive_own_messages=receive_own_messages, ignore_config=True)
        if s.interface == "virtual":
            return can.Bus(interface="virtual", channel=s.channel, receive_own_messages=receive_own_messages,
                           ignore_config=True)
        return can.Bus(interface="remote", channel=s.channel, fd=True, ignore_config=True)
    except BusSetupError:
        raise
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        raise BusSetupError(f"cannot open bus {s}: {exc}") from None


def to_frame(msg: can.Message) -> Frame:
    """python-can message -> codec frame (timestamp: the bus's receive time in s)."""
    return Frame(msg.arbitration_id, bytes(msg.data), bool(msg.is_fd), float(msg.timestamp), bool(msg.is_extended_id))


def to_message(frame: Frame, timestamp: float = 0.0) -> can.Message:
    """Codec frame -> python-can message (CAN FD frames with bit-rate switch)."""
    return can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_fd=frame.is_fd,
                       bitrate_switch=frame.is_fd, is_extended_id=frame.is_extended_id, timestamp=timestamp)
