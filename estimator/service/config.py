"""Daemon configuration: one dataclass from a TOML file (table ``[estimator]``) plus CLI flags."""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from estimator.errors import EstimatorError


class ConfigError(EstimatorError):
    """The configuration file or a flag is invalid."""


@dataclass(frozen=True)
class DaemonConfig:
    """Everything the daemon needs (units in the names)."""

    bus: str = "socketcan:vcan0"
    state_dir: Path | None = None
    dbc: Path | None = None
    queue_frames: int = 8192            # bounded input queue, drop-oldest when full
    assembly_timeout_ms: float = 50.0   # header without trailer -> rejected
    status_period_s: float = 0.1        # EstimatorStatus heartbeat (10 Hz)
    persist_period_s: float = 5.0       # state written at least this often (and at shutdown)
    max_injectors: int = 8
    window_us: float = 100.0            # identification window
    robust: str = "auto"
    q_nu_n_per_v: float = 0.003         # N_u random walk per injection (floor; per-second terms on top)
    q_lh_um: float = 0.003              # L_h random walk per injection (floor)
    sigma_limit_lh_um: float = 0.25     # sigma(L_h) above this: status "uncertain", not "ok"
    log_level: str = "INFO"

    def __post_init__(self) -> None:
        for name in ("queue_frames", "max_injectors"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} = {getattr(self, name)} must be >= 1")
        if not 1 <= self.max_injectors <= 8:
            raise ConfigError(f"max_injectors = {self.max_injectors} must be within 1..8 (InjectorId has 3 bits)")
        for name in ("assembly_timeout_ms", "status_period_s", "persist_period_s", "window_us", "q_nu_n_per_v",
                     "q_lh_um", "sigma_limit_lh_um"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"{name} = {v!r} must be a positive number")
        if self.robust not in ("auto", "on", "off"):
            raise ConfigError(f"robust = {self.robust!r} must be auto, on or off")

    @classmethod
    def load(cls, path: Path | None, **overrides: Any) -> "DaemonConfig":
        """Defaults <- TOML file ``[estimator]`` <- non-None overrides (CLI) <- $STATE_DIRECTORY for state_dir."""
        values: dict[str, Any] = {}
        if path is not None:
            try:
                data = tomllib.loads(Path(path).read_text())
            except (OSError, tomllib.TOMLDecodeError) as exc:
                raise ConfigError(f"config {path}: {exc}") from None
            table = data.get("estimator", {})
            known = {f.name for f in fields(cls)}
            unknown = set(table) - known
            if unknown:
                raise ConfigError(f"config {path}: unknown key(s) {', '.join(sorted(unknown))}")
            values.update(table)
        values.update({k: v for k, v in overrides.items() if v is not None})
        if "state_dir" not in values and os.environ.get("STATE_DIRECTORY"):
            values["state_dir"] = os.environ["STATE_DIRECTORY"].split(":")[0]
        for key in ("state_dir", "dbc"):
            if values.get(key) is not None:
                values[key] = Path(values[key])
        try:
            return cls(**values)
        except TypeError as exc:
            raise ConfigError(str(exc)) from None

    def with_bus(self, bus: str) -> "DaemonConfig":
        """A copy on another bus."""
        return replace(self, bus=bus)
