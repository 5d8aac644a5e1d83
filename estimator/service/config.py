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
    status_period_s: float = 0.1        # EstimatorStatus heartbeat (10 Hz)
    persist_period_s: float = 5.0       # state written at least this often (and at shutdown)
    log_level: str = "INFO"

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
    def _convert(cls, values: dict[str, Any]) -> None:
        if "state_dir" not in values and os.environ.get("STATE_DIRECTORY"):
            values["state_dir"] = os.environ["STATE_DIRECTORY"].split(":")[0]
        super()._convert(values)
        if isinstance(values.get("log_level"), str):
            values["log_level"] = values["log_level"].upper()

    def with_bus(self, bus: str) -> DaemonConfig:
        """A copy on another bus."""
        return replace(self, bus=bus)


assert set(DaemonConfig.RULES) | {"tracker", "self_calibration", "drive_correction"} == \
    {f.name for f in fields(DaemonConfig)}, "every daemon key needs a rule"
