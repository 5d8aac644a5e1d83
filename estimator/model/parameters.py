"""Frozen, validated parameter objects for the PSA (Table 1) and the valve (Table 2).

All values are SI. The nominal values live in ``parameters.toml`` beside this file, each traced
to the paper's table; :func:`load_nominal` reads them.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

import numpy as np

from estimator._compiled import njit
from estimator.errors import ParameterError
from estimator.model.chain import NO_CHAIN, MeasurementChain
from estimator.model.hysteresis import NO_HYSTERESIS, Hysteresis
from estimator.units import UM_PER_M

NOMINAL_FILE = Path(__file__).with_name("parameters.toml")

# The simulators and the estimator accept N_u a little past the configured range: an injector at
# 20.99 N/V must not read as "at a bound" because noise put its estimate at 21.01. The laws of
# eqs. 21-22 are smooth there; 0.1 N/V is 0.5 % of N_u.
NU_EXTRAPOLATION_N_PER_V = 0.1


def check_nu_in(nu_n_per_v: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """``nu_n_per_v`` (N/V, 1-D) if every value is finite and within [lo, hi], else ParameterError
    naming the first offending value. The one N_u range check of the package."""
    if nu_n_per_v.size == 0 or (np.isfinite(nu_n_per_v.sum()) and nu_n_per_v.min() >= lo and nu_n_per_v.max() <= hi):
        return nu_n_per_v
    bad = ~np.isfinite(nu_n_per_v) | (nu_n_per_v < lo) | (nu_n_per_v > hi)
    raise ParameterError(f"N_u = {float(nu_n_per_v[bad][0])!r} N/V is outside [{lo}, {hi}] N/V")


# Units of every field, used in error messages (name -> unit).
_UNITS = {
    "m1_kg": "kg", "m2_kg": "kg", "m3_kg": "kg", "m4_kg": "kg",
    "kp_n_per_m": "N/m", "kg1_n_per_m": "N/m", "kg2_n_per_m": "N/m", "ks_n_per_m": "N/m",
    "bg1_ns_per_m": "N*s/m", "bg2_ns_per_m": "N*s/m", "rb_v2s_per_mn": "V^2*s/(m*N)",
    "r0a_ohm": "Ohm", "r0b_v_per_n": "V/N", "nu_min_n_per_v": "N/V", "nu_max_n_per_v": "N/V",
    "kf_n_per_m": "N/m", "kv1_n_per_m": "N/m", "kv2_n_per_m": "N/m", "sp_m": "m",
    "bf_ns_per_m": "N*s/m", "bv_ns_per_m": "N*s/m", "f_open_n": "N", "lh_min_m": "m", "lh_max_m": "m",
}
# Fields that may be zero (dampers, which the paper sets to 0) or negative (L_h bound).
_NON_NEGATIVE = {"bg1_ns_per_m", "bg2_ns_per_m", "bf_ns_per_m", "bv_ns_per_m", "rb_v2s_per_mn"}
_SIGNED = {"lh_min_m", "lh_max_m"}


def _check_fields(obj: Any) -> None:
    for f in fields(obj):
        value = getattr(obj, f.name)
        unit = _UNITS.get(f.name, "")
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
            raise ParameterError(f"{f.name} = {value!r} {unit}: must be a finite number")
        if f.name in _SIGNED:
            continue
        if f.name in _NON_NEGATIVE:
            if value < 0:
                raise ParameterError(f"{f.name} = {value!r} {unit}: must be >= 0")
        elif value <= 0:
            raise ParameterError(f"{f.name} = {value!r} {unit}: must be > 0")


if TYPE_CHECKING:
    from _typeshed import DataclassInstance

_T = TypeVar("_T", bound="DataclassInstance")


def _from_mapping(cls: type[_T], values: Mapping[str, Any], label: str) -> _T:
    """A parameter dataclass from {field: SI value}; unknown or missing fields raise ParameterError."""
    unknown = set(values) - {f.name for f in fields(cls)}
    if unknown:
        raise ParameterError(f"unknown {label} parameter(s): {', '.join(sorted(unknown))}")
    try:
        return cls(**{k: float(v) for k, v in values.items()})
    except TypeError as exc:
        raise ParameterError(f"{label} parameters incomplete: {exc}") from None


@dataclass(frozen=True)
class PsaParameters:
    """Piezo stack actuator with mounting, Table 1 (SI units).

    The coupling factor N_u is *not* a field: it is the temperature dependent quantity that is
    identified, and is passed separately. ``nu_min_n_per_v``/``nu_max_n_per_v`` bound it.
    """

    m1_kg: float
    m2_kg: float
    m3_kg: float
    kp_n_per_m: float
    kg1_n_per_m: float
    kg2_n_per_m: float
    ks_n_per_m: float
    bg1_ns_per_m: float
    bg2_ns_per_m: float
    rb_v2s_per_mn: float
    r0a_ohm: float
    r0b_v_per_n: float
    nu_min_n_per_v: float
    nu_max_n_per_v: float

    def __post_init__(self) -> None:
        _check_fields(self)
        if self.nu_min_n_per_v >= self.nu_max_n_per_v:
            raise ParameterError(
                f"nu_min_n_per_v = {self.nu_min_n_per_v} N/V must be below "
                f"nu_max_n_per_v = {self.nu_max_n_per_v} N/V")

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> PsaParameters:
        """Build from a mapping of field name to SI value (e.g. the TOML table ``[psa]``)."""
        return _from_mapping(cls, values, "PSA")

    def check_nu(self, nu_n_per_v: float) -> float:
        """Return ``nu_n_per_v`` if it is finite and inside the configured range, else raise."""
        return float(check_nu_in(np.array([nu_n_per_v], dtype=float), self.nu_min_n_per_v,
                                 self.nu_max_n_per_v)[0])

    @property
    def simulation_nu_range(self) -> tuple[float, float]:
        """N_u values (N/V) the simulators accept: the range widened by ``NU_EXTRAPOLATION_N_PER_V``."""
        return self.nu_min_n_per_v - NU_EXTRAPOLATION_N_PER_V, self.nu_max_n_per_v + NU_EXTRAPOLATION_N_PER_V

    def capacitance_f(self, nu_n_per_v: float) -> float:
        """Blocked capacitance C = N_u^2 / k_s (eq. 21), in F."""
        return nu_n_per_v ** 2 / self.ks_n_per_m

    def resistance_ohm(self, nu_n_per_v: float) -> float:
        """Hysteresis substitute R(N_u) = R_0a exp(-R_0b N_u) (eq. 22), in Ohm."""
        return self.r0a_ohm * math.exp(-self.r0b_v_per_n * nu_n_per_v)

    def damping_ns_per_m(self, nu_n_per_v: float) -> float:
        """Material damping b_p = R_b N_u^2, in N*s/m."""
        return self.rb_v2s_per_mn * nu_n_per_v ** 2

    def with_nu_range(self, nu_min: float, nu_max: float) -> PsaParameters:
        """A copy with another admissible N_u range (N/V)."""
        return replace(self, nu_min_n_per_v=nu_min, nu_max_n_per_v=nu_max)


@njit(cache=True, nogil=True)
def contact_force(kv1_n_per_m: float, kv2_n_per_m: float, sp_m: float, s: float) -> float:
    """The contact spring F_v(s) of Fig. 11 in N at compression ``s`` (m): 0 for s <= 0, stiffness
    k_v1 up to s_p and k_v2 beyond (compiled, for the compiled pre-compressed starts too)."""
    if s <= 0.0:
        return 0.0
    if s <= sp_m:
        return kv1_n_per_m * s
    return kv1_n_per_m * sp_m + kv2_n_per_m * (s - sp_m)


@dataclass(frozen=True)
class ValveParameters:
    """Control valve mechanics, Table 2 (SI units)."""

    m4_kg: float
    kf_n_per_m: float
    kv1_n_per_m: float
    kv2_n_per_m: float
    sp_m: float
    bf_ns_per_m: float
    bv_ns_per_m: float
    f_open_n: float
    lh_min_m: float
    lh_max_m: float

    def __post_init__(self) -> None:
        _check_fields(self)
        if self.lh_min_m >= self.lh_max_m:
            raise ParameterError(
                f"lh_min_m = {self.lh_min_m} m must be below lh_max_m = {self.lh_max_m} m")

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> ValveParameters:
        """Build from a mapping of field name to SI value (e.g. the TOML table ``[valve]``)."""
        return _from_mapping(cls, values, "valve")

    def contact_force_n(self, compression_m: float) -> float:
        """Piecewise linear contact spring F_v(s) of Fig. 11 (0 for s <= 0), in N."""
        return float(contact_force(self.kv1_n_per_m, self.kv2_n_per_m, self.sp_m, float(compression_m)))


@dataclass(frozen=True)
class CalibrationUncertainty:
    """How uncertain a calibrated parameter set leaves the estimates made with it (1 sigma, the same
    for every injection of the injector, so averaging does not shrink it): ``nu_rel_sigma`` of N_u
    (relative), ``lh_sigma_m`` of L_h (m); and of what the valve does, ``stroke_rel_sigma`` of the
    plateau stroke (relative) and ``opening_sigma_s`` of the opening instant (s) predicted from an
    estimate made with these parameters. A structural error moves N_u and L_h so that the voltage
    still fits, and the valve's predicted motion keeps less of it than either (zero: not known, the
    prediction's σ then comes from N_u's and L_h's). ``preload_lo_n``..``preload_hi_n``: the preload
    forces (N) of the injections it was calibrated on, the span its valve motion was checked over (0:
    not stated). Zero for the tables' values, taken as exact."""

    nu_rel_sigma: float = 0.0
    lh_sigma_m: float = 0.0
    stroke_rel_sigma: float = 0.0
    opening_sigma_s: float = 0.0
    preload_lo_n: float = 0.0
    preload_hi_n: float = 0.0

    def __post_init__(self) -> None:
        for name, limit in (("nu_rel_sigma", 0.1), ("lh_sigma_m", 10e-6), ("stroke_rel_sigma", 1.0),
                            ("opening_sigma_s", 100e-6), ("preload_lo_n", 1e5), ("preload_hi_n", 1e5)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and 0 <= v <= limit):
                raise ParameterError(f"[calibration] {name} = {v!r} must be a number within 0..{limit:g}")
        if self.preload_lo_n > self.preload_hi_n:
            raise ParameterError(f"[calibration] preload_lo_n = {self.preload_lo_n!r} is above preload_hi_n = "
                                 f"{self.preload_hi_n!r}")

    @property
    def zero(self) -> bool:
        """True for exact parameters (the default)."""
        return self.nu_rel_sigma == 0.0 and self.lh_sigma_m == 0.0

    @property
    def has_response(self) -> bool:
        """True when the calibration states the uncertainty of the valve's predicted motion."""
        return self.stroke_rel_sigma > 0.0 or self.opening_sigma_s > 0.0

    def cov(self, nu_n_per_v: float) -> np.ndarray:
        """The covariance it adds to an estimate at ``nu_n_per_v``, in (N/V, µm)."""
        return np.diag([(nu_n_per_v * self.nu_rel_sigma) ** 2, (self.lh_sigma_m * UM_PER_M) ** 2])


@dataclass(frozen=True)
class InjectorParameters:
    """The PSA and the valve together: everything the hybrid model needs except N_u, L_h, F_open;
    the amplifier's measurement chain between the actuator and the samples (default: none); and,
    for a calibrated set, the uncertainty the calibration leaves in every estimate."""

    psa: PsaParameters
    valve: ValveParameters
    chain: MeasurementChain = NO_CHAIN
    calibration: CalibrationUncertainty = field(default_factory=CalibrationUncertainty)
    hysteresis: Hysteresis = NO_HYSTERESIS

    def feedthrough_ohm(self, nu_n_per_v: float) -> float:
        """The resistance (Ω) through which the current reaches the terminal voltage directly: R(N_u)
        (eq. 22), or the hysteresis element's series resistance where the set has the element."""
        return self.hysteresis.series_ohm if self.hysteresis.present else self.psa.resistance_ohm(nu_n_per_v)

    def to_toml(self, header: str = "") -> str:
        """This parameter set as a TOML file in the layout of ``parameters.toml`` (every key of
        ``[psa]`` and ``[valve]``; ``[chain]`` when there is one), ``header`` as comment lines first."""
        lines = [f"# {line}" for line in header.splitlines()] + ([""] if header else []) + ["[psa]"]
        lines += [f"{k} = {float(v)!r}" for k, v in self.psa.__dict__.items()]
        lines += ["", "[valve]"] + [f"{k} = {float(v)!r}" for k, v in self.valve.__dict__.items()]
        if not self.chain.identity:
            lines += ["", "[chain]"] + [f"{k} = {float(v)!r}" for k, v in self.chain.__dict__.items()]
        if not self.calibration.zero:
            lines += ["", "[calibration]"] + [f"{k} = {float(v)!r}" for k, v in self.calibration.__dict__.items()]
        if self.hysteresis.present:
            lines += ["", *self.hysteresis.to_toml_lines()]
        return "\n".join(lines) + "\n"

    def to_mapping(self) -> dict[str, dict[str, Any]]:
        """{"psa": {...}, "valve": {...}, "chain": {...}, "calibration": {...}} of SI values, and
        "hysteresis" where the set has the element (JSON-ready; :meth:`from_mapping`)."""
        out: dict[str, dict[str, Any]] = {
            "psa": {k: float(v) for k, v in self.psa.__dict__.items()},
            "valve": {k: float(v) for k, v in self.valve.__dict__.items()},
            "chain": {k: float(v) for k, v in self.chain.__dict__.items()},
            "calibration": {k: float(v) for k, v in self.calibration.__dict__.items()}}
        if self.hysteresis.present:
            out["hysteresis"] = self.hysteresis.to_mapping()
        return out

    @classmethod
    def from_mapping(cls, data: Any) -> InjectorParameters:
        """The inverse of :meth:`to_mapping`, validated like a parameter file; raises ParameterError."""
        if not isinstance(data, Mapping) or not isinstance(data.get("psa"), Mapping) \
                or not isinstance(data.get("valve"), Mapping):
            raise ParameterError("a parameter set needs the tables psa and valve")
        cal = data.get("calibration", {})
        if not isinstance(cal, Mapping) or set(cal) - {f.name for f in fields(CalibrationUncertainty)}:
            raise ParameterError("[calibration] must be a table of nu_rel_sigma, lh_sigma_m, stroke_rel_sigma, "
                                 "opening_sigma_s, preload_lo_n and preload_hi_n")
        return cls(PsaParameters.from_mapping(data["psa"]), ValveParameters.from_mapping(data["valve"]),
                   chain_from_mapping(data.get("chain", {})), CalibrationUncertainty(**cal),
                   Hysteresis.from_mapping(data.get("hysteresis", {})))

    @classmethod
    def from_toml(cls, path: str | Path) -> InjectorParameters:
        """Read ``[psa]`` and ``[valve]`` tables (SI values) and an optional ``[chain]`` table
        (``u_filter_tau_s``, ``i_filter_tau_s``, ``i_skew_s``: :class:`MeasurementChain`), an optional
        ``[calibration]`` table (:class:`CalibrationUncertainty`) and an optional ``[hysteresis]`` table
        (:class:`~estimator.model.hysteresis.Hysteresis`) from a TOML file."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ParameterError(f"cannot read parameter file {path}: {exc}") from None
        if "psa" not in data or "valve" not in data:
            raise ParameterError(f"parameter file {path} needs the tables [psa] and [valve]")
        return cls.from_mapping(data)


def chain_from_mapping(values: Any) -> MeasurementChain:
    """A :class:`MeasurementChain` from the TOML table ``[chain]`` (s; missing keys are 0)."""
    if not isinstance(values, Mapping):
        raise ParameterError("[chain] must be a table")
    known = {f.name for f in fields(MeasurementChain)}
    unknown = set(values) - known
    if unknown:
        raise ParameterError(f"unknown chain parameter(s): {', '.join(sorted(unknown))} (known: {', '.join(sorted(known))})")
    try:
        return MeasurementChain(**{k: v for k, v in values.items()})
    except (TypeError, ValueError) as exc:
        raise ParameterError(str(exc)) from None


_NOMINAL: InjectorParameters | None = None


def load_parameters(path: str | Path | None = None) -> InjectorParameters:
    """The parameters of ``path`` (what ``estimator calibrate --out`` writes), or the nominal ones if None."""
    return InjectorParameters.from_toml(path) if path is not None else load_nominal()


def load_nominal() -> InjectorParameters:
    """The paper's nominal parameters (Tables 1 and 2), read once from ``parameters.toml``."""
    global _NOMINAL
    if _NOMINAL is None:
        _NOMINAL = InjectorParameters.from_toml(NOMINAL_FILE)
    return _NOMINAL


#: the structural parameters of an injector that series parts vary and an electrical calibration fits:
#: (table, field) of :class:`InjectorParameters`
STRUCTURAL = (("psa", "m1_kg"), ("psa", "m2_kg"), ("psa", "m3_kg"), ("psa", "kp_n_per_m"), ("psa", "kg1_n_per_m"),
              ("psa", "kg2_n_per_m"), ("psa", "ks_n_per_m"), ("psa", "rb_v2s_per_mn"), ("psa", "r0a_ohm"),
              ("valve", "kv1_n_per_m"), ("valve", "sp_m"), ("valve", "m4_kg"), ("valve", "bv_ns_per_m"))


def scaled(params: InjectorParameters, factors: dict[str, float]) -> InjectorParameters:
    """``params`` with the named fields (``"psa.m1_kg"``, ``"valve.sp_m"``) multiplied by the factors."""
    psa: dict[str, float] = {}
    valve: dict[str, float] = {}
    for key, f in factors.items():
        table, name = key.split(".")
        target, src = (psa, params.psa) if table == "psa" else (valve, params.valve)
        target[name] = getattr(src, name) * f
    return replace(params, psa=replace(params.psa, **psa), valve=replace(params.valve, **valve))   # the chain kept


#: The valve's nominal preload F_open in N (Table 2, from ``parameters.toml``): what an injection
#: without a preload force of its own (a trace without ``preload_force_n``) is assumed to have.
NOMINAL_PRELOAD_N: float = load_nominal().valve.f_open_n
