"""Daemon configuration: the one config tree (daemon <- tracker <- identification), validated here.

Sources, later ones winning: the defaults below, the TOML file's ``[estimator]`` table, CLI flags,
``$STATE_DIRECTORY`` (for ``state_dir`` only, as systemd's ``StateDirectory=`` sets it). Every key is
type- and range-checked in :meth:`DaemonConfig.__post_init__`; a bad value raises :class:`ConfigError`
with one line that names the key. The tracker and identification settings are built from the same
values at load time (:meth:`DaemonConfig.tracker_config`), so a value they refuse is also reported
here, naming the key, before the daemon touches the bus.
"""

from __future__ import annotations

import logging
import math
import os
import sys
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any
from collections.abc import Callable

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from estimator.codec.assembler import MAX_SAMPLE_PERIOD_NS
from estimator.errors import EstimatorError
from estimator.ident.config import IdentConfig, TrackerConfig
from estimator.ident.selfcal import SelfCalConfig
from estimator.service.bus import BusSetupError, BusSpec
from estimator.service.processor import COMMAND_POLICIES

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


class ConfigError(EstimatorError):
    """The configuration file or a flag is invalid."""


# ---- one checker per kind of value: each returns what the value must be, or None if it is fine ----
def _number(lo: float, hi: float, lo_open: bool = False) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and (
            (v > lo if lo_open else v >= lo) and v <= hi)
        return None if ok else f"must be a number in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
    return check


def _whole(lo: int, hi: int) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        ok = isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi
        return None if ok else f"must be a whole number in [{lo}, {hi}]"
    return check


def _choice(*options: str) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        return None if v in options else f"must be one of {', '.join(repr(o) for o in options)}"
    return check


def _text_or_none(v: Any) -> str | None:
    return None if v is None or (isinstance(v, str) and v) else "must be a non-empty string"


def _rate_or_none(v: Any) -> str | None:
    ok = v is None or (isinstance(v, int) and not isinstance(v, bool) and 10_000 <= v <= 15_000_000)
    return None if ok else "must be a whole number of bit/s in [10000, 15000000]"


def _flag(v: Any) -> str | None:
    return None if isinstance(v, bool) else "must be true or false"


def _options(v: Any) -> str | None:
    ok = isinstance(v, dict) and all(isinstance(k, str) and k for k in v) and len(v) <= 64
    return None if ok else "must be a table of python-can keyword arguments"


def _path_or_none(v: Any) -> str | None:
    return None if v is None or isinstance(v, Path) else "must be a path (a string)"


def _periods(v: Any) -> str | None:
    ok = isinstance(v, tuple) and len(v) <= 64 and all(
        isinstance(x, int) and not isinstance(x, bool) and 1 <= x <= MAX_SAMPLE_PERIOD_NS for x in v)
    return None if ok else f"must be a list of at most 64 whole numbers in [1, {MAX_SAMPLE_PERIOD_NS}] (ns)"


@dataclass(frozen=True)
class DaemonConfig:
    """Everything the daemon needs (units in the names); see ``systemd/estimator.toml`` for each key."""

    bus: str | None = None              # INTERFACE:CHANNEL; None: python-can's configuration, else socketcan:vcan0
    bitrate: int | None = None          # nominal bit rate, bit/s (interfaces that set it; SocketCAN: ip link)
    data_bitrate: int | None = None     # CAN FD data-phase bit rate, bit/s
    fd: bool = True                     # CAN FD (the sample frames need it)
    bus_options: dict[str, Any] = field(default_factory=dict)   # interface-specific python-can keyword arguments
    state_dir: Path | None = None
    dbc: Path | None = None
    params: Path | None = None          # model parameters (what `estimator calibrate --out` writes); default Tables 1-2
    queue_frames: int = 8192            # bounded input queue, drop-oldest when full
    assembly_timeout_ms: float = 50.0   # header without trailer -> rejected, judged by bus timestamps
    silent_bus_s: float = 1.0           # wall-clock guard: no frame at all for this long -> pending injections time out
    status_period_s: float = 0.1        # EstimatorStatus heartbeat (10 Hz)
    persist_period_s: float = 5.0       # state written at least this often (and at shutdown)
    max_injectors: int = 8
    sample_periods_ns: tuple[int, ...] = ()   # accepted sample periods; empty: any the contract allows
    max_sample_periods: int = 4         # simulators kept (LRU, ~3 MB and ~30 ms to build each)
    commands: str = "reset-only"        # EstimatorCommand policy: off | reset-only | all
    window_us: float = 100.0            # identification window
    robust: str = "auto"
    q_nu_n_per_v: float = 0.003         # N_u random walk per injection (floor; per-second terms on top)
    q_lh_um: float = 0.003              # L_h random walk per injection (floor)
    sigma_limit_lh_um: float = 0.25     # sigma(L_h) above this: status "uncertain", not "ok"
    cold_start: str = IdentConfig.cold_start   # local-first (a checked local fit, the global search where it fails) | global
    start_nu_n_per_v: float = IdentConfig.start_point[0]   # where a local-first cold start begins: the type's nominal N_u
    start_lh_um: float = IdentConfig.start_point[1]        # ... and L_h
    self_calibration: str = "off"       # off | on: a mismatched injector learns its own model in the background
    self_calibration_window: int = SelfCalConfig.window     # injections per calibration (two held out to test it)
    self_calibration_min_preload_spread: float = SelfCalConfig.min_preload_spread   # (max - min) / mean preload force
    log_level: str = "INFO"

    def __post_init__(self) -> None:
        for name, check in _RULES.items():
            value = getattr(self, name)
            problem = check(value)
            if problem:
                raise ConfigError(f"{name} = {_show(value)}: {problem}")
        try:
            self.tracker_config()
            self.self_calibration_config()
        except ValueError as exc:   # a combination the identification refuses
            raise ConfigError(f"tracker/identification settings: {exc}") from None
        try:
            self.bus_spec()
        except BusSetupError as exc:
            raise ConfigError(f"bus = {_show(self.bus)}: {exc}") from None

    def bus_spec(self) -> BusSpec:
        """The bus as python-can opens it (see :mod:`estimator.service.bus`)."""
        base = dict(fd=self.fd, bitrate=self.bitrate, data_bitrate=self.data_bitrate, options=dict(self.bus_options))
        if self.bus is None:
            return BusSpec(None, None, **base)
        return BusSpec.parse(self.bus, **base)

    def self_calibration_config(self) -> SelfCalConfig | None:
        """The self-calibration settings (None when ``self_calibration = "off"``)."""
        if self.self_calibration == "off":
            return None
        return SelfCalConfig(window=self.self_calibration_window,
                             min_preload_spread=self.self_calibration_min_preload_spread)

    def tracker_config(self) -> TrackerConfig:
        """The tracker <- identification part of the tree."""
        ident = IdentConfig(window_s=self.window_us * 1e-6, robust=self.robust, sigma_limit_lh_um=self.sigma_limit_lh_um,
                            cold_start=self.cold_start, start_point=(self.start_nu_n_per_v, self.start_lh_um))
        return TrackerConfig(ident=ident, q_nu_n_per_v=self.q_nu_n_per_v, q_lh_um=self.q_lh_um)

    @property
    def log_level_number(self) -> int:
        """``log_level`` as a :mod:`logging` level."""
        return int(getattr(logging, self.log_level))

    @classmethod
    def load(cls, path: Path | None, **overrides: Any) -> DaemonConfig:
        """Defaults <- TOML file ``[estimator]`` <- non-None overrides (CLI) <- $STATE_DIRECTORY for state_dir."""
        values: dict[str, Any] = {}
        if path is not None:
            values.update(read_table(Path(path)))
        values.update({k: v for k, v in overrides.items() if v is not None})
        if "state_dir" not in values and os.environ.get("STATE_DIRECTORY"):
            values["state_dir"] = os.environ["STATE_DIRECTORY"].split(":")[0]
        for key in ("state_dir", "dbc", "params"):
            v = values.get(key)
            if isinstance(v, str) and v:
                values[key] = Path(v)
            elif v is not None and not isinstance(v, Path):
                raise ConfigError(f"{key} = {_show(v)}: must be a path (a string)")
        if isinstance(values.get("sample_periods_ns"), list):
            values["sample_periods_ns"] = tuple(values["sample_periods_ns"])
        if isinstance(values.get("log_level"), str):
            values["log_level"] = values["log_level"].upper()
        cfg = cls(**values)
        cfg.check_files()
        return cfg

    def check_files(self) -> None:
        """Fail fast on a parameter file that cannot be used (the DBC is checked when it is loaded)."""
        if self.params is not None:
            from estimator.model.parameters import InjectorParameters   # noqa: PLC0415 (only when configured)
            try:
                InjectorParameters.from_toml(self.params)
            except EstimatorError as exc:
                raise ConfigError(f"params = {str(self.params)!r}: {exc}") from None

    def with_bus(self, bus: str) -> DaemonConfig:
        """A copy on another bus."""
        return replace(self, bus=bus)


def read_table(path: Path) -> dict[str, Any]:
    """The ``[estimator]`` table of a TOML file; unknown keys and unreadable files raise ConfigError."""
    try:
        data = tomllib.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"config {path}: not UTF-8 text (byte {exc.start}); TOML files are UTF-8") from None
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"config {path}: {exc}") from None
    table = data.get("estimator", {})
    if not isinstance(table, dict):
        raise ConfigError(f"config {path}: 'estimator' must be a table ([estimator])")
    unknown = set(table) - {f.name for f in fields(DaemonConfig)}
    if unknown:
        raise ConfigError(f"config {path}: unknown key(s) {', '.join(sorted(unknown))} in [estimator]")
    return dict(table)


def _show(v: Any) -> str:
    text = repr(str(v)) if isinstance(v, Path) else repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


_RULES: dict[str, Callable[[Any], str | None]] = {
    "bus": _text_or_none,
    "bitrate": _rate_or_none,
    "data_bitrate": _rate_or_none,
    "fd": _flag,
    "bus_options": _options,
    "state_dir": _path_or_none,
    "dbc": _path_or_none,
    "params": _path_or_none,
    "queue_frames": _whole(16, 1_000_000),
    "assembly_timeout_ms": _number(1.0, 10_000.0),
    "silent_bus_s": _number(0.05, 3600.0),
    "status_period_s": _number(0.01, 60.0),
    "persist_period_s": _number(0.05, 86_400.0),
    "max_injectors": _whole(1, 8),
    "sample_periods_ns": _periods,
    "max_sample_periods": _whole(1, 64),
    "commands": _choice(*COMMAND_POLICIES),
    "window_us": _number(20.0, 2000.0),
    "robust": _choice("auto", "on", "off"),
    "q_nu_n_per_v": _number(0.0, 1.0, lo_open=True),
    "q_lh_um": _number(0.0, 10.0, lo_open=True),
    "sigma_limit_lh_um": _number(0.0, 100.0, lo_open=True),
    "cold_start": _choice("local-first", "global"),
    "start_nu_n_per_v": _number(1.0, 100.0),
    "start_lh_um": _number(-100.0, 100.0),
    "self_calibration": _choice("off", "on"),
    "self_calibration_window": _whole(5, 64),
    "self_calibration_min_preload_spread": _number(0.0, 10.0),
    "log_level": _choice(*LOG_LEVELS),
}
assert set(_RULES) == {f.name for f in fields(DaemonConfig)}, "every config key needs a rule"
