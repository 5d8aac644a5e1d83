"""Daemon configuration: one tree of frozen dataclasses, each validating its own keys.

The TOML file's tables are the tree: ``[estimator]`` holds the daemon's keys (checked in
:meth:`DaemonConfig.__post_init__`), ``[estimator.ident]`` builds :class:`IdentConfig`,
``[estimator.tracker]`` :class:`TrackerConfig` (around that IdentConfig) and
``[estimator.self_calibration]`` :class:`SelfCalConfig` (with ``mode = "off" | "on"``) and
``[estimator.drive_correction]`` :class:`~estimator.ident.drive_correction.DriveTarget` (the same
``mode``). Sources, later
ones winning: the defaults, the file, CLI flags, ``$STATE_DIRECTORY`` (for ``state_dir`` only, as
systemd's ``StateDirectory=`` sets it). A bad value raises :class:`ConfigError` with one line that
names the table and the key, before the daemon touches the bus. The flat keys of earlier versions
(``window_us``, ``robust``, ``self_calibration = "on"``, ... in ``[estimator]``) are still read, with a
deprecation warning naming their new place; they go in the next version.
"""

from __future__ import annotations

import logging
import math
import os
import sys
from collections.abc import Callable
from dataclasses import MISSING, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from estimator.choices import Switch
from estimator.codec.assembler import MAX_SAMPLE_PERIOD_NS
from estimator.errors import EstimatorError
from estimator.ident.config import IdentConfig, TrackerConfig
from estimator.ident.drive_correction import DriveTarget
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


def _seeds(v: Any) -> str | None:
    ok = isinstance(v, dict) and all(isinstance(k, int) and 0 <= k <= 7 and isinstance(p, Path) for k, p in v.items())
    return None if ok else 'must be a table of injector ids 0..7 and parameter files ("3" = "eol/3.toml")'


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
    injector_params: dict[int, Path] = field(default_factory=dict)   # [estimator.injector_params]: an injector's own
                                        # (end-of-line) parameter file by id, its starting model (still monitored)
    queue_frames: int = 8192            # bounded input queue, drop-oldest when full
    assembly_timeout_ms: float = 50.0   # header without trailer -> rejected, judged by bus timestamps
    silent_bus_s: float = 1.0           # wall-clock guard: no frame at all for this long -> pending injections time out
    stale_after_ms: float = 100.0       # an estimate published later than this after its last frame is "stale", never ok
    status_period_s: float = 0.1        # EstimatorStatus heartbeat (10 Hz)
    persist_period_s: float = 5.0       # state written at least this often (and at shutdown)
    max_injectors: int = 8
    sample_periods_ns: tuple[int, ...] = ()   # accepted sample periods; empty: any the contract allows
    max_sample_periods: int = 4         # simulators kept (LRU, ~3 MB and ~30 ms to build each)
    commands: str = "reset-only"        # EstimatorCommand policy: off | reset-only | all
    log_level: str = "INFO"
    tracker: TrackerConfig = field(default_factory=TrackerConfig)   # [estimator.tracker], its ident [estimator.ident]
    self_calibration: SelfCalConfig | None = field(default_factory=SelfCalConfig)   # [estimator.self_calibration]; None: mode = "off"
    drive_correction: DriveTarget | None = field(default_factory=DriveTarget)   # [estimator.drive_correction]; None: mode = "off"

    def __post_init__(self) -> None:
        for name, check in _RULES.items():
            value = getattr(self, name)
            problem = check(value)
            if problem:
                raise ConfigError(f"{name} = {_show(value)}: {problem}")
        if not isinstance(self.tracker, TrackerConfig):
            raise ConfigError(f"tracker = {_show(self.tracker)}: must be a TrackerConfig")
        if self.self_calibration is not None and not isinstance(self.self_calibration, SelfCalConfig):
            raise ConfigError(f"self_calibration = {_show(self.self_calibration)}: must be a SelfCalConfig or None")
        if self.drive_correction is not None and not isinstance(self.drive_correction, DriveTarget):
            raise ConfigError(f"drive_correction = {_show(self.drive_correction)}: must be a DriveTarget or None")
        try:
            self.bus_spec()
        except BusSetupError as exc:
            raise ConfigError(f"bus = {_show(self.bus)}: {exc}") from None

    def bus_spec(self) -> BusSpec:
        """The bus as python-can opens it (see :mod:`estimator.service.bus`)."""
        base: dict[str, Any] = dict(fd=self.fd, bitrate=self.bitrate, data_bitrate=self.data_bitrate,
                                    options=dict(self.bus_options))
        if self.bus is None:
            return BusSpec(None, None, **base)
        return BusSpec.parse(self.bus, **base)

    def self_calibration_config(self) -> SelfCalConfig | None:
        """The self-calibration settings (None: off)."""
        return self.self_calibration

    def tracker_config(self) -> TrackerConfig:
        """The tracker <- identification part of the tree."""
        return self.tracker

    @property
    def ident(self) -> IdentConfig:
        """The identification settings (``[estimator.ident]``)."""
        return self.tracker.ident

    @property
    def log_level_number(self) -> int:
        """``log_level`` as a :mod:`logging` level."""
        return int(getattr(logging, self.log_level))

    @classmethod
    def load(cls, path: Path | None, **overrides: Any) -> DaemonConfig:
        """Defaults <- TOML file ``[estimator]`` and its sub-tables <- non-None overrides (CLI) <-
        $STATE_DIRECTORY for state_dir."""
        values: dict[str, Any] = {}
        if path is not None:
            values.update(read_table(Path(path)))
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls.from_mapping(values, str(path) if path is not None else "config")

    @classmethod
    def from_mapping(cls, table: dict[str, Any], where: str = "config") -> DaemonConfig:
        """The configuration of an ``[estimator]`` table as TOML reads it (sub-tables ``ident``,
        ``tracker``, ``self_calibration``; the deprecated flat keys mapped to them); ConfigError naming
        the key otherwise."""
        values = dict(table)
        # a sub-table by its name; a word there is a deprecated flat key (self_calibration = "on")
        sections = {name: values.pop(name, {}) for name in SECTIONS
                    if not (name in DEPRECATED and isinstance(values.get(name), str))}
        for name in SECTIONS:
            sections.setdefault(name, {})
        for name, sub in sections.items():
            if not isinstance(sub, dict):
                raise ConfigError(f"[estimator.{name}]: must be a table, not {_show(sub)}")
            sections[name] = dict(sub)
        for key in [k for k in values if k in DEPRECATED]:
            section, new_key, convert = DEPRECATED[key]
            value = values.pop(key)
            logging.getLogger("estimator.config").warning(
                "%s: %s in [estimator] is deprecated: use %s in [estimator.%s]", where, key, new_key, section)
            sections[section].setdefault(new_key, convert(value, sections[section]))
        unknown = set(values) - {f.name for f in fields(cls)} - set(SECTIONS)
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} in [estimator]")
        if "ident" in sections["tracker"]:
            raise ConfigError("[estimator.tracker]: the identification settings go in [estimator.ident]")
        ident = build_section(IdentConfig, "ident", sections["ident"])
        values["tracker"] = build_section(TrackerConfig, "tracker", {**sections["tracker"], "ident": ident})
        calibration = dict(sections["self_calibration"])
        mode = calibration.pop("mode", Switch.ON.value)   # learning is on unless turned off
        if mode not in Switch.words():
            raise ConfigError(f"[estimator.self_calibration] mode = {_show(mode)}: must be one of "
                              f"{', '.join(repr(w) for w in Switch.words())}")
        settings = build_section(SelfCalConfig, "self_calibration", calibration)   # checked even when off
        values["self_calibration"] = settings if mode == Switch.ON else None
        correction = dict(sections["drive_correction"])
        mode = correction.pop("mode", Switch.ON.value)
        if mode not in Switch.words():
            raise ConfigError(f"[estimator.drive_correction] mode = {_show(mode)}: must be one of "
                              f"{', '.join(repr(w) for w in Switch.words())}")
        target = build_section(DriveTarget, "drive_correction", correction)
        values["drive_correction"] = target if mode == Switch.ON else None
        if "state_dir" not in values and os.environ.get("STATE_DIRECTORY"):
            values["state_dir"] = os.environ["STATE_DIRECTORY"].split(":")[0]
        for key in ("state_dir", "dbc", "params"):
            v = values.get(key)
            if isinstance(v, str) and v:
                values[key] = Path(v)
            elif v is not None and not isinstance(v, Path):
                raise ConfigError(f"{key} = {_show(v)}: must be a path (a string)")
        seeds = values.get("injector_params")
        if isinstance(seeds, dict):
            try:
                values["injector_params"] = {int(k): Path(p) if isinstance(p, str) else p for k, p in seeds.items()}
            except ValueError:
                pass   # the rule names what the table must be
        if isinstance(values.get("sample_periods_ns"), list):
            values["sample_periods_ns"] = tuple(values["sample_periods_ns"])
        if isinstance(values.get("log_level"), str):
            values["log_level"] = values["log_level"].upper()
        cfg = cls(**values)
        cfg.check_files()
        return cfg

    def check_files(self) -> None:
        """Fail fast on a parameter file that cannot be used (the DBC is checked when it is loaded)."""
        from estimator.model.parameters import InjectorParameters  # noqa: PLC0415 (only when configured)
        if self.params is not None:
            try:
                InjectorParameters.from_toml(self.params)
            except EstimatorError as exc:
                raise ConfigError(f"params = {str(self.params)!r}: {exc}") from None
        for iid, path in self.injector_params.items():
            try:
                InjectorParameters.from_toml(path)
            except EstimatorError as exc:
                raise ConfigError(f"[estimator.injector_params] {iid} = {str(path)!r}: {exc}") from None

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
    return dict(table)


def build_section(cls: Any, section: str, table: dict[str, Any]) -> Any:
    """The frozen dataclass of a sub-table: unknown keys and values of the wrong kind refused naming
    them, TOML lists where the field holds a tuple made tuples, then the class's own checks."""
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(table) - set(known))
    if unknown:
        raise ConfigError(f"[estimator.{section}]: unknown key(s) {', '.join(unknown)}")
    values = {}
    for key, value in table.items():
        f = known[key]
        default = f.default if f.default is not MISSING else (
            f.default_factory() if f.default_factory is not MISSING else None)
        if default is None and str(f.type).startswith("float"):   # an optional number (unset: a default rule)
            default = 0.0
        problem = _kind_problem(value, default)
        if problem:
            raise ConfigError(f"[estimator.{section}] {key} = {_show(value)}: {problem}")
        values[key] = tuple(value) if isinstance(value, list) else value
    try:
        return cls(**values)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"[estimator.{section}]: {exc}") from None


def _kind_problem(value: Any, default: Any) -> str | None:
    """What ``value`` must be to stand where ``default`` stands (None: it may)."""
    if isinstance(default, str):   # the Choice enums too; their words are checked by the class
        return None if isinstance(value, str) else "must be a string"
    if isinstance(default, bool):
        return None if isinstance(value, bool) else "must be true or false"
    if isinstance(default, int):
        return None if isinstance(value, int) and not isinstance(value, bool) else "must be a whole number"
    if isinstance(default, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        return None if ok else "must be a number"
    if isinstance(default, tuple) or default is None:
        if default is None and value is None:
            return None
        ok = isinstance(value, (list, tuple)) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)
        size = len(default) if isinstance(default, tuple) else 2
        return None if ok and len(value) == size else f"must be a list of {size} numbers"
    return None   # a nested dataclass: built by the caller


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
    "injector_params": _seeds,
    "queue_frames": _whole(16, 1_000_000),
    "assembly_timeout_ms": _number(1.0, 10_000.0),
    "silent_bus_s": _number(0.05, 3600.0),
    "stale_after_ms": _number(1.0, 3_600_000.0),
    "status_period_s": _number(0.01, 60.0),
    "persist_period_s": _number(0.05, 86_400.0),
    "max_injectors": _whole(1, 8),
    "sample_periods_ns": _periods,
    "max_sample_periods": _whole(1, 64),
    "commands": _choice(*COMMAND_POLICIES),
    "log_level": _choice(*LOG_LEVELS),
}
SECTIONS = ("ident", "tracker", "self_calibration", "drive_correction")   # the sub-tables, each a dataclass validating its keys
assert set(_RULES) | {"tracker", "self_calibration", "drive_correction"} == {f.name for f in fields(DaemonConfig)}, \
    "every daemon key needs a rule"


def _start_point(index: int) -> Callable[[Any, dict[str, Any]], Any]:
    """A deprecated start_nu_n_per_v / start_lh_um as its element of [estimator.ident] start_point."""
    def convert(value: Any, section: dict[str, Any]) -> Any:
        point = list(section.get("start_point", IdentConfig.start_point))
        point[index] = value
        section.pop("start_point", None)
        return point
    return convert


def _same(value: Any, section: dict[str, Any]) -> Any:
    return value


def _us_to_s(value: Any, section: dict[str, Any]) -> Any:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    return value / 1e6 if ok else value


#: flat [estimator] keys of earlier versions -> (table, key there, conversion)
DEPRECATED: dict[str, tuple[str, str, Callable[[Any, dict[str, Any]], Any]]] = {
    "window_us": ("ident", "window_s", _us_to_s),
    "robust": ("ident", "robust", _same),
    "sigma_limit_lh_um": ("ident", "sigma_limit_lh_um", _same),
    "cold_start": ("ident", "cold_start", _same),
    "start_nu_n_per_v": ("ident", "start_point", _start_point(0)),
    "start_lh_um": ("ident", "start_point", _start_point(1)),
    "q_nu_n_per_v": ("tracker", "q_nu_n_per_v", _same),
    "q_lh_um": ("tracker", "q_lh_um", _same),
    "self_calibration": ("self_calibration", "mode", _same),
    "self_calibration_window": ("self_calibration", "window", _same),
    "self_calibration_min_preload_spread": ("self_calibration", "min_preload_spread", _same),
}
