"""Opening the CAN bus the python-can way, and converting between python-can and codec frames.

Any interface python-can supports (``can.VALID_INTERFACES``: socketcan, pcan, kvaser, vector,
slcan, gs_usb, socketcand, ... and the loopback hub's ``remote``). A bus is given as

* the shorthand ``INTERFACE:CHANNEL`` (``socketcan:vcan0``, ``pcan:PCAN_USBBUS1``,
  ``remote:ws://127.0.0.1:PORT/``, ``virtual:NAME``), or
* python-can's own options (``-i/--interface``, ``-c/--channel``, ``-b/--bitrate``, ``--fd``,
  ``--data-bitrate``, ``--bus-kwargs``; :func:`can.cli.add_bus_arguments`), or
* nothing: then python-can's configuration decides (``~/.canrc``, ``can.conf``, ``CAN_INTERFACE``,
  ``CAN_CHANNEL``, ``CAN_BITRATE``), and without any, ``socketcan:vcan0``.

The estimator needs CAN FD (64-byte sample frames), so ``fd`` defaults to True. A SocketCAN
interface must exist and carry CAN FD (MTU 72); the error says how to set up a virtual (``vcanN``)
or a real (``canN``) interface.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from estimator.errors import EstimatorError

log = logging.getLogger(__name__)
CANFD_MTU = 72
DEFAULT_BUS = "socketcan:vcan0"
INTERFACES = tuple(sorted(can.VALID_INTERFACES))


class BusSetupError(EstimatorError):
    """The bus cannot be opened as configured (one readable line says how to fix it)."""


@dataclass(frozen=True)
class BusSpec:
    """What python-can needs to open one bus. ``interface`` None: python-can's configuration decides."""

    interface: str | None
    channel: str | None
    fd: bool = True
    bitrate: int | None = None
    data_bitrate: int | None = None
    options: dict[str, Any] = field(default_factory=dict)   # interface-specific keyword arguments

    @classmethod
    def parse(cls, spec: str, **kw: Any) -> BusSpec:
        """``INTERFACE:CHANNEL`` (the interface one of python-can's); ``kw`` as the dataclass fields."""
        kind, sep, channel = spec.partition(":")
        if not sep or not channel:
            raise BusSetupError(f"bus {spec!r}: use INTERFACE:CHANNEL, e.g. socketcan:vcan0, pcan:PCAN_USBBUS1, "
                                f"remote:ws://127.0.0.1:PORT/")
        check_interface(kind)
        return cls(kind, channel, **kw)

    def __str__(self) -> str:
        if self.interface is None:
            return "python-can configuration"
        return f"{self.interface}:{self.channel}"


def add_arguments(parser: Any) -> None:
    """``--bus INTERFACE:CHANNEL`` plus python-can's own bus options (:func:`can.cli.add_bus_arguments`)."""
    import can.cli

    parser.add_argument("--bus", default=None, help="shorthand INTERFACE:CHANNEL (socketcan:vcan0, pcan:PCAN_USBBUS1, "
                        "remote:ws://127.0.0.1:PORT/); or python-can's -i/-c options below; neither: python-can's "
                        "configuration (~/.canrc, CAN_INTERFACE/CAN_CHANNEL), else socketcan:vcan0")
    can.cli.add_bus_arguments(parser, group_title="python-can bus options")


def overrides_from_args(args: Any) -> dict[str, Any]:
    """Config overrides (``bus``, ``bitrate``, ``data_bitrate``, ``fd``, ``bus_options``) from parsed
    :func:`add_arguments` options; only what was given."""
    out: dict[str, Any] = {}
    interface, channel = getattr(args, "interface", None), getattr(args, "channel", None)
    if getattr(args, "bus", None) is not None:
        if interface or channel:
            raise BusSetupError("give either --bus INTERFACE:CHANNEL or -i/--interface with -c/--channel, not both")
        out["bus"] = args.bus
    elif interface or channel:
        if not (interface and channel):
            raise BusSetupError("-i/--interface and -c/--channel go together (or use --bus INTERFACE:CHANNEL)")
        out["bus"] = f"{interface}:{channel}"
    for key in ("bitrate", "data_bitrate"):
        if getattr(args, key, None) is not None:
            out[key] = getattr(args, key)
    if getattr(args, "fd", None):
        out["fd"] = True
    options = dict(getattr(args, "bus_kwargs", None) or {})
    if getattr(args, "timing", None) is not None:
        options["timing"] = args.timing
    if options:
        out["bus_options"] = options
    return out


def spec_from_args(args: Any) -> BusSpec:
    """The bus of parsed :func:`add_arguments` options (for commands without a config file)."""
    ov = overrides_from_args(args)
    kw = dict(fd=ov.get("fd", True), bitrate=ov.get("bitrate"), data_bitrate=ov.get("data_bitrate"),
              options=ov.get("bus_options", {}))
    return BusSpec.parse(ov["bus"], **kw) if "bus" in ov else BusSpec(None, None, **kw)


def check_interface(name: str) -> None:
    """Refuse an interface name python-can does not know, listing the ones it does."""
    if name not in can.VALID_INTERFACES:
        raise BusSetupError(f"unknown CAN interface {name!r}; python-can supports: {', '.join(INTERFACES)}")


def check_socketcan(channel: str, sysfs: Path = Path("/sys/class/net")) -> None:
    """Refuse a missing interface or one that cannot carry CAN FD frames; advice fits vcan and real CAN."""
    dev = sysfs / channel
    virtual = channel.startswith("vcan")
    if not dev.exists():
        if virtual:
            raise BusSetupError(f"CAN interface {channel} does not exist (create it: ip link add dev {channel} type "
                                f"vcan && ip link set {channel} mtu {CANFD_MTU} up)")
        raise BusSetupError(f"CAN interface {channel} does not exist (is the adapter plugged in and its driver "
                            f"loaded? then: ip link set {channel} type can bitrate 500000 dbitrate 2000000 fd on "
                            f"&& ip link set {channel} up)")
    try:
        mtu = int((dev / "mtu").read_text().strip())
    except (OSError, ValueError):
        return
    if mtu < CANFD_MTU:
        fix = (f"ip link set {channel} mtu {CANFD_MTU}" if virtual else
               f"ip link set {channel} down && ip link set {channel} type can bitrate 500000 dbitrate 2000000 fd on "
               f"&& ip link set {channel} up")
        raise BusSetupError(f"CAN interface {channel} has MTU {mtu} and cannot carry CAN FD frames (fix: {fix})")


def resolve(spec: str | BusSpec | None) -> BusSpec:
    """A BusSpec from a shorthand, a BusSpec, or None (python-can's configuration, else vcan0)."""
    if isinstance(spec, BusSpec) and spec.interface is not None:
        return spec
    if isinstance(spec, str):
        return BusSpec.parse(spec)
    base = spec or BusSpec(None, None)
    try:
        cfg = can.util.load_config(config={k: v for k, v in (("channel", base.channel),) if v is not None})
    except (can.CanInterfaceNotImplementedError, ValueError):
        default = BusSpec.parse(DEFAULT_BUS)
        log.info("no bus given and no python-can configuration (~/.canrc, CAN_INTERFACE): using %s", default)
        return BusSpec(default.interface, base.channel or default.channel, base.fd, base.bitrate, base.data_bitrate,
                       base.options)
    check_interface(str(cfg["interface"]))
    return BusSpec(str(cfg["interface"]), base.channel or cfg.get("channel"), bool(cfg.get("fd", base.fd)),
                   base.bitrate or cfg.get("bitrate"), base.data_bitrate or cfg.get("data_bitrate"), base.options)


def open_bus(spec: str | BusSpec | None, receive_own_messages: bool = False) -> can.BusABC:
    """Open the bus (CAN FD unless ``fd=False``). Raises :class:`BusSetupError` with one readable line."""
    s = resolve(spec)
    kw: dict[str, Any] = dict(s.options)
    if s.bitrate is not None:
        kw["bitrate"] = s.bitrate
    if s.data_bitrate is not None:
        kw["data_bitrate"] = s.data_bitrate
    try:
        if s.interface == "socketcan":
            check_socketcan(str(s.channel))
        if s.interface == "virtual":
            return can.Bus(interface="virtual", channel=s.channel, receive_own_messages=receive_own_messages, **kw)
        if s.interface == "remote":
            return can.Bus(interface="remote", channel=s.channel, fd=s.fd, **kw)
        return can.Bus(interface=s.interface, channel=s.channel, fd=s.fd, receive_own_messages=receive_own_messages,
                       **kw)
    except BusSetupError:
        raise
    except (can.CanError, OSError, ValueError, TypeError, ImportError) as exc:
        raise BusSetupError(f"cannot open bus {s}: {exc}") from None
