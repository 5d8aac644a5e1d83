"""The estimator's configuration: one tree of frozen dataclasses, each validating its own keys, that
every entry point builds from — the daemon, ``replay``, ``track``, the library's
:func:`~estimator.pipeline.estimates.iter_estimates`, the fleet and the benches.

The TOML file's tables are the tree: ``[estimator]`` holds the estimator's keys (checked in
:meth:`EstimatorConfig.__post_init__`), ``[estimator.ident]`` builds :class:`IdentConfig`,
``[estimator.tracker]`` :class:`TrackerConfig` (around that IdentConfig),
``[estimator.self_calibration]`` :class:`SelfCalConfig` (with ``mode = "off" | "on"``) and
``[estimator.drive_correction]`` :class:`~estimator.drive.target.DriveTarget` (the same
``mode``). The daemon's configuration (:class:`estimator.service.config.DaemonConfig`) is this one
with the bus, state and service keys added. Sources, later ones winning: the defaults, the file, CLI
flags. A bad value raises :class:`ConfigError` with one line that names the table and the key. The
flat keys of earlier versions (``window_us``, ``robust``, ``self_calibration = "on"``, ... in
``[estimator]``) are still read, with a deprecation warning naming their new place; they go in the
next version.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
from collections.abc import Callable
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar, TypeVar

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from estimator.choices import Switch
from estimator.codec.assembler import MAX_SAMPLE_PERIOD_NS
from estimator.drive.standard import AmplifierDrive
from estimator.drive.target import DriveTarget
from estimator.errors import EstimatorError
from estimator.ident.config import IdentConfig, TrackerConfig
from estimator.ident.learning.selfcal import SelfCalConfig
from estimator.pipeline.processor import COMMAND_POLICIES
from estimator.units import US_PER_S

Check = Callable[[Any], "str | None"]
C = TypeVar("C", bound="EstimatorConfig")


class ConfigError(EstimatorError):
    """The configuration file or a flag is invalid."""


# ---- one checker per kind of value: each returns what the value must be, or None if it is fine ----
def number(lo: float, hi: float, lo_open: bool = False) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and (
            (v > lo if lo_open else v >= lo) and v <= hi)
        return None if ok else f"must be a number in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
    return check


def whole(lo: int, hi: int) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        ok = isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi
        return None if ok else f"must be a whole number in [{lo}, {hi}]"
    return check


def choice(*options: str) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        return None if v in options else f"must be one of {', '.join(repr(o) for o in options)}"
    return check


def text_or_none(v: Any) -> str | None:
    return None if v is None or (isinstance(v, str) and v) else "must be a non-empty string"


def rate_or_none(v: Any) -> str | None:
    ok = v is None or (isinstance(v, int) and not isinstance(v, bool) and 10_000 <= v <= 15_000_000)
    return None if ok else "must be a whole number of bit/s in [10000, 15000000]"


def flag(v: Any) -> str | None:
    return None if isinstance(v, bool) else "must be true or false"


def options(v: Any) -> str | None:
    ok = isinstance(v, dict) and all(isinstance(k, str) and k for k in v) and len(v) <= 64
    return None if ok else "must be a table of python-can keyword arguments"


def path_or_none(v: Any) -> str | None:
    return None if v is None or isinstance(v, Path) else "must be a path (a string)"


def seeds(v: Any) -> str | None:
    ok = isinstance(v, dict) and all(isinstance(k, int) and 0 <= k <= 7 and isinstance(p, Path) for k, p in v.items())
    return None if ok else 'must be a table of injector ids 0..7 and parameter files ("3" = "eol/3.toml")'


def periods(v: Any) -> str | None:
    ok = isinstance(v, tuple) and len(v) <= 64 and all(
        isinstance(x, int) and not isinstance(x, bool) and 1 <= x <= MAX_SAMPLE_PERIOD_NS for x in v)
    return None if ok else f"must be a list of at most 64 whole numbers in [1, {MAX_SAMPLE_PERIOD_NS}] (ns)"


ESTIMATOR_RULES: dict[str, Check] = {
    "dbc": path_or_none,
    "params": path_or_none,
    "injector_params": seeds,
    "assembly_timeout_ms": number(1.0, 10_000.0),
    "max_injectors": whole(1, 8),
    "sample_periods_ns": periods,
    "max_sample_periods": whole(1, 64),
    "commands": choice(*COMMAND_POLICIES),
}
SECTIONS = ("ident", "tracker", "self_calibration", "drive_correction")   # the sub-tables, each a dataclass validating its keys


@dataclass(frozen=True)
class EstimatorConfig:
    """Everything the estimator needs, live or offline (units in the names); see
    ``systemd/estimator.toml`` for each key."""

    dbc: Path | None = None
    params: Path | None = None          # model parameters (what `estimator calibrate --out` writes); default Tables 1-2
    injector_params: dict[int, Path] = field(default_factory=dict)   # [estimator.injector_params]: an injector's own
                                        # (end-of-line) parameter file by id, its starting model (still monitored)
    assembly_timeout_ms: float = 50.0   # header without trailer -> rejected, judged by bus timestamps
    max_injectors: int = 8
    sample_periods_ns: tuple[int, ...] = ()   # accepted sample periods; empty: any the contract allows
    max_sample_periods: int = 4         # simulators kept (LRU, ~3 MB and ~30 ms to build each)
    commands: str = "reset-only"        # EstimatorCommand policy: off | reset-only | all
    tracker: TrackerConfig = field(default_factory=TrackerConfig)   # [estimator.tracker], its ident [estimator.ident]
    self_calibration: SelfCalConfig | None = field(default_factory=SelfCalConfig)   # [estimator.self_calibration]; None: mode = "off"
    drive_correction: DriveTarget | None = field(default_factory=DriveTarget)   # [estimator.drive_correction]; None: mode = "off"

    #: the checks of the plain keys (a subclass adds its own)
    RULES: ClassVar[dict[str, Check]] = ESTIMATOR_RULES
    #: the keys that hold a path (TOML gives a string)
    PATH_KEYS: ClassVar[tuple[str, ...]] = ("dbc", "params")

    def __post_init__(self) -> None:
        for name, check in self.RULES.items():
            value = getattr(self, name)
            problem = check(value)
            if problem:
                raise ConfigError(f"{name} = {show(value)}: {problem}")
        if not isinstance(self.tracker, TrackerConfig):
            raise ConfigError(f"tracker = {show(self.tracker)}: must be a TrackerConfig")
        if self.self_calibration is not None and not isinstance(self.self_calibration, SelfCalConfig):
            raise ConfigError(f"self_calibration = {show(self.self_calibration)}: must be a SelfCalConfig or None")
        if self.drive_correction is not None and not isinstance(self.drive_correction, DriveTarget):
            raise ConfigError(f"drive_correction = {show(self.drive_correction)}: must be a DriveTarget or None")

    def estimator_config(self) -> EstimatorConfig:
        """The estimator's part alone (of a subclass: without its own keys)."""
        return EstimatorConfig(**{f.name: getattr(self, f.name) for f in fields(EstimatorConfig)})

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

    @classmethod
    def load(cls: type[C], path: Path | None, **overrides: Any) -> C:
        """Defaults <- TOML file ``[estimator]`` and its sub-tables <- non-None overrides (CLI)."""
        values: dict[str, Any] = {}
        if path is not None:
            values.update(read_table(Path(path)))
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls.from_mapping(values, str(path) if path is not None else "config")

    @classmethod
    def from_mapping(cls: type[C], table: dict[str, Any], where: str = "config") -> C:
        """The configuration of an ``[estimator]`` table as TOML reads it (sub-tables ``ident``,
        ``tracker``, ``self_calibration``, ``drive_correction``; the deprecated flat keys mapped to
        them); ConfigError naming the key otherwise."""
        values = _sections(dict(table), where)
        unknown = set(values) - {f.name for f in fields(cls)}
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} in [estimator]")
        cls._convert(values)
        cfg = cls(**values)
        cfg.check_files()
        return cfg

    @classmethod
    def _convert(cls, values: dict[str, Any]) -> None:
        """TOML's strings and lists made the fields' paths and tuples, in place (the rules then check them)."""
        for key in cls.PATH_KEYS:
            v = values.get(key)
            if isinstance(v, str) and v:
                values[key] = Path(v)
            elif v is not None and not isinstance(v, Path):
                raise ConfigError(f"{key} = {show(v)}: must be a path (a string)")
        seeds = values.get("injector_params")
        if isinstance(seeds, dict):
            with contextlib.suppress(ValueError):   # the rule names what the table must be
                values["injector_params"] = {int(k): Path(p) if isinstance(p, str) else p for k, p in seeds.items()}
        if isinstance(values.get("sample_periods_ns"), list):
            values["sample_periods_ns"] = tuple(values["sample_periods_ns"])

    def check_files(self) -> None:
        """Fail fast on a parameter file that cannot be used (the DBC is checked when it is loaded)."""
        from estimator.model.parameters import InjectorParameters
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
        if self.drive_correction is not None and self.drive_correction.drive_file is not None:
            load_amplifier_drive(self.drive_correction.drive_file)


def load_amplifier_drive(path: str | Path) -> AmplifierDrive:
    """The amplifier's standard drive from a current table (CSV with columns t_s, current_A from the
    start of charging, as ``python -m estimator drive-table`` writes it); ConfigError naming the key
    and the file otherwise."""
    from estimator.io.traces import read_trace

    try:
        tr = read_trace(path)
        return AmplifierDrive.from_table(tr.column("t_s"), tr.column("current_A"), Path(path).name)
    except (EstimatorError, ValueError, OSError) as exc:
        raise ConfigError(f"[estimator.drive_correction] amplifier_drive = {str(path)!r}: {exc}") from None


def _sections(values: dict[str, Any], where: str) -> dict[str, Any]:
    """``values`` (an ``[estimator]`` table) with its sub-tables built into their settings objects
    (``tracker`` around ``ident``, ``self_calibration`` and ``drive_correction`` None when off) and the
    deprecated flat keys moved to their tables."""
    # a sub-table by its name; a word there is a deprecated flat key (self_calibration = "on")
    sections = {name: values.pop(name, {}) for name in SECTIONS
                if not (name in DEPRECATED and isinstance(values.get(name), str))}
    for name in SECTIONS:
        sections.setdefault(name, {})
    for name, sub in sections.items():
        if not isinstance(sub, dict):
            raise ConfigError(f"[estimator.{name}]: must be a table, not {show(sub)}")
        sections[name] = dict(sub)
    for key in [k for k in values if k in DEPRECATED]:
        section, new_key, convert = DEPRECATED[key]
        value = values.pop(key)
        logging.getLogger("estimator.config").warning(
            "%s: %s in [estimator] is deprecated: use %s in [estimator.%s]", where, key, new_key, section)
        sections[section].setdefault(new_key, convert(value, sections[section]))
    if "ident" in sections["tracker"]:
        raise ConfigError("[estimator.tracker]: the identification settings go in [estimator.ident]")
    ident = build_section(IdentConfig, "ident", sections["ident"])
    values["tracker"] = build_section(TrackerConfig, "tracker", {**sections["tracker"], "ident": ident})
    values["self_calibration"] = _switched(SelfCalConfig, "self_calibration", sections["self_calibration"])
    values["drive_correction"] = _switched(DriveTarget, "drive_correction", sections["drive_correction"])
    return values


def _switched(cls: Any, section: str, table: dict[str, Any]) -> Any:
    """A sub-table with ``mode = "on" | "off"`` (on unless turned off): its settings, None when off
    (checked even then)."""
    table = dict(table)
    mode = table.pop("mode", Switch.ON.value)
    if mode not in Switch.words():
        raise ConfigError(f"[estimator.{section}] mode = {show(mode)}: must be one of "
                          f"{', '.join(repr(w) for w in Switch.words())}")
    settings = build_section(cls, section, table)
    return settings if mode == Switch.ON else None


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
            raise ConfigError(f"[estimator.{section}] {key} = {show(value)}: {problem}")
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


def show(v: Any) -> str:
    text = repr(str(v)) if isinstance(v, Path) else repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


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
    return value / US_PER_S if ok else value


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
