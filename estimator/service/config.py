"""The daemon's configuration: the estimator's (:class:`~estimator.pipeline.config.EstimatorConfig`,
``[estimator]`` and its sub-tables, the same for every entry point) with the bus, the state
directory and the service's keys added.

Sources, later ones winning: the defaults, the file, CLI flags, ``$STATE_DIRECTORY`` (for
``state_dir`` only, as systemd's ``StateDirectory=`` sets it). A bad value raises :class:`ConfigError`
with one line that names the table and the key, before the daemon touches the bus.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, ClassVar

from estimator.pipeline.config import (
    DEPRECATED,
    ESTIMATOR_RULES,
    SECTIONS,
    Check,
    ConfigError,
    EstimatorConfig,
    choice,
    flag,
    number,
    options,
    path_or_none,
    rate_or_none,
    read_table,
    show,
    text_or_none,
    whole,
)
from estimator.service.bus import BusSetupError, BusSpec

__all__ = ["DEPRECATED", "SECTIONS", "ConfigError", "DaemonConfig", "read_table"]

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


@dataclass(frozen=True)
class XcpConfig:
    """``[estimator.xcp]``: the XCP-on-Ethernet slave (UDP), off unless ``mode = "on"``. It listens on
    ``host``:``port`` (loopback unless configured otherwise: an open port lets anyone who reaches it read
    every measurement and, with ``writes``, change the calibratable keys)."""

    host: str = "127.0.0.1"
    port: int = 5555
    writes: bool = True                 # false: the working page is read-only

    def __post_init__(self) -> None:
        if not (isinstance(self.port, int) and 0 <= self.port <= 65535):
            raise ValueError(f"port = {self.port!r}: must be 0..65535 (0: any free port)")
        if not self.host:
            raise ValueError("host: an address to listen on, e.g. 127.0.0.1")

SERVICE_RULES: dict[str, Check] = {
    "bus": text_or_none,
    "bitrate": rate_or_none,
    "data_bitrate": rate_or_none,
    "fd": flag,
    "bus_options": options,
    "state_dir": path_or_none,
    "queue_frames": whole(16, 1_000_000),
    "silent_bus_s": number(0.05, 3600.0),
    "stale_after_ms": number(1.0, 3_600_000.0),
    "shed_after_ms": number(0.1, 3_600_000.0),
    "status_period_s": number(0.01, 60.0),
    "persist_period_s": number(0.05, 86_400.0),
    "log_level": choice(*LOG_LEVELS),
}


@dataclass(frozen=True)
class DaemonConfig(EstimatorConfig):
    """The estimator's configuration and the daemon's own keys (units in the names); see
    ``systemd/estimator.toml`` for each key."""

    bus: str | None = None              # INTERFACE:CHANNEL; None: python-can's configuration, else socketcan:vcan0
    bitrate: int | None = None          # nominal bit rate, bit/s (interfaces that set it; SocketCAN: ip link)
    data_bitrate: int | None = None     # CAN FD data-phase bit rate, bit/s
    fd: bool = True                     # CAN FD (the sample frames need it)
    bus_options: dict[str, Any] = field(default_factory=dict)   # interface-specific python-can keyword arguments
    state_dir: Path | None = None
    queue_frames: int = 8192            # bounded input queue, drop-oldest when full
    silent_bus_s: float = 1.0           # wall-clock guard: no frame at all for this long -> pending injections time out
    stale_after_ms: float = 100.0       # an estimate published later than this after its last frame is "stale", never ok
    shed_after_ms: float = 4.0          # above capacity: an established injector's injection waiting longer is shed
    status_period_s: float = 0.1        # EstimatorStatus heartbeat (10 Hz)
    persist_period_s: float = 5.0       # state written at least this often (and at shutdown)
    log_level: str = "INFO"
    xcp: XcpConfig | None = None        # [estimator.xcp]; None: mode = "off" (the default)

    RULES: ClassVar[dict[str, Check]] = {**ESTIMATOR_RULES, **SERVICE_RULES}
    PATH_KEYS: ClassVar[tuple[str, ...]] = (*EstimatorConfig.PATH_KEYS, "state_dir")

    def __post_init__(self) -> None:
        super().__post_init__()
        try:
            self.bus_spec()
        except BusSetupError as exc:
            raise ConfigError(f"bus = {show(self.bus)}: {exc}") from None

    def bus_spec(self) -> BusSpec:
        """The bus as python-can opens it (see :mod:`estimator.service.bus`)."""
        base: dict[str, Any] = dict(fd=self.fd, bitrate=self.bitrate, data_bitrate=self.data_bitrate,
                                    options=dict(self.bus_options))
        if self.bus is None:
            return BusSpec(None, None, **base)
        return BusSpec.parse(self.bus, **base)

    @property
    def log_level_number(self) -> int:
        """``log_level`` as a :mod:`logging` level."""
        return int(getattr(logging, self.log_level))

    @classmethod
    def from_mapping(cls, table: dict[str, Any], where: str = "config") -> DaemonConfig:
        """:meth:`EstimatorConfig.from_mapping` with the daemon's own sub-table ``[estimator.xcp]`` (off
        unless its ``mode = "on"``)."""
        from estimator.pipeline.config import build_section

        table = dict(table)
        sub = table.pop("xcp", {})
        if not isinstance(sub, dict):
            raise ConfigError(f"[estimator.xcp]: must be a table, not {show(sub)}")
        sub = dict(sub)
        mode = sub.pop("mode", "off")
        if mode not in ("on", "off"):
            raise ConfigError(f"[estimator.xcp] mode = {show(mode)}: must be one of 'on', 'off'")
        xcp = build_section(XcpConfig, "xcp", sub)
        cfg = super().from_mapping(table, where)
        return replace(cfg, xcp=xcp if mode == "on" else None)

    @classmethod
    def _convert(cls, values: dict[str, Any]) -> None:
        if "state_dir" not in values and os.environ.get("STATE_DIRECTORY"):
            values["state_dir"] = os.environ["STATE_DIRECTORY"].split(":")[0]
        super()._convert(values)
        if isinstance(values.get("log_level"), str):
            values["log_level"] = values["log_level"].upper()

    def with_bus(self, bus: str) -> DaemonConfig:
        """A copy on another bus."""
        return replace(self, bus=bus)


assert set(DaemonConfig.RULES) | {"tracker", "self_calibration", "drive_correction", "xcp"} == \
    {f.name for f in fields(DaemonConfig)}, "every daemon key needs a rule"
