"""Settings of the identification and of the recursive estimator (frozen, validated, units in the names).

The configuration tree is ``daemon <- tracker <- identification``: :class:`TrackerConfig` holds an
:class:`IdentConfig`; the service layer builds both from its TOML file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from estimator.choices import Choice, ColdStart, Norm, Robust
from estimator.ident.fit.adequacy import EXCESS_Z_THRESHOLD, STRUCTURE_THRESHOLD
from estimator.model.parameters import InjectorParameters
from estimator.units import UM_PER_M

# the search's margin beyond the parameters' N_u range: an injector at 20.99 N/V whose noise puts its
# estimate at 21.01 is not "at a bound" (the laws of eqs. 21-22 are smooth there)
NU_SEARCH_MARGIN_N_PER_V = 0.1


def coerce_choice(obj: object, name: str, kind: type[Choice]) -> None:
    """Set ``obj.name`` (a frozen dataclass's field) to its :class:`Choice`; ValueError naming the words."""
    v = getattr(obj, name)
    try:
        object.__setattr__(obj, name, kind(v))
    except ValueError:
        raise ValueError(f"{name} must be one of {', '.join(kind.words())}, not {v!r}") from None


def _positive(obj: object, *names: str, allow_zero: bool = False) -> None:
    for name in names:
        v = getattr(obj, name)
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and (
            v >= 0 if allow_zero else v > 0)
        if not ok:
            raise ValueError(f"{name} = {v!r} must be a {'non-negative' if allow_zero else 'positive'} number")


@dataclass(frozen=True)
class IdentConfig:
    """Settings of the single-injection identification (eq. 28)."""

    window_s: float = 100e-6
    robust_window_s: float = 150e-6        # window in robust mode, if the trace is that long
    norm: Norm = Norm.L2
    robust: Robust = Robust.AUTO
    model_error_threshold: float = 40.0    # chi-square(6) statistic; P(>40 | correct model) < 1e-6
    nu_bounds_n_per_v: tuple[float, float] | None = None   # N/V; None: the parameters' N_u range and NU_SEARCH_MARGIN
    lh_bounds_um: tuple[float, float] | None = None        # µm; None: the parameters' L_h range
    grid: tuple[int, int] = (13, 25)       # N_u x L_h points of the cold-start grid
    zoom_points: int = 9                   # N_u columns per zoom of the cold start's profile search
    zooms: int = 2                         # zooms of the profile search (each 1/4 of the previous span)
    tol: tuple[float, float] = (2e-4, 2e-3)  # convergence: N/V, µm
    max_cycles: int = 10
    sigma_limit_lh_um: float = 0.25        # above this sigma(L_h) the status is "uncertain", not "ok"
    cold_start: ColdStart = ColdStart.LOCAL_FIRST
    start_point: tuple[float, float] = (18.0, 4.0)   # N/V, µm: where a local-first cold start begins (a lot's nominal)
    local_accept_z: float = 6.0            # a local fit is kept if its residual exceeds white noise by <= z standard deviations
    adequacy_structure: float = STRUCTURE_THRESHOLD  # chi-square(24) of the residual's smooth part above which the model is inadequate
                                           # (its lowest 8 columns: 0.6 of it)
    adequacy_excess_z: float = EXCESS_Z_THRESHOLD    # the whole residual's energy above noise (sd) above which it is inadequate
    mismatch_floor: tuple[float, float] = (0.01, 0.6)   # model-error sigma of an inadequate fit: N_u relative, L_h µm
    mismatch_scale: tuple[float, float] = (0.002, 0.18)  # ... plus this per sqrt(structure chi2 / 24): N_u relative, L_h µm
    preload_rel_sigma: float = 0.0         # relative uncertainty (1 sigma) of the header's PreloadForce; enters sigma
    window_disagreement_chi2: float = 20.0  # the robust fit (its longer window) worse than the plain one over the
                                           # plain window by more than this (chi-square units): the later samples
                                           # disagree with the plain fit, a model mismatch (exact model: > -7); 0: off
    preload_check_chi2: float = 15.0       # chi-square(1) of the header's PreloadForce against the samples above which
                                           # it is taken as wrong (P = 1e-4 when right); 0: not tested

    def __post_init__(self) -> None:
        coerce_choice(self, "robust", Robust)
        coerce_choice(self, "cold_start", ColdStart)
        coerce_choice(self, "norm", Norm)
        if isinstance(self.start_point, list):
            object.__setattr__(self, "start_point", tuple(self.start_point))
        if not (isinstance(self.start_point, tuple) and len(self.start_point) == 2
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                        for v in self.start_point)):
            raise ValueError(f"start_point {self.start_point!r} must be two numbers (N/V, µm)")
        _positive(self, "window_s", "robust_window_s", "model_error_threshold", "sigma_limit_lh_um", "local_accept_z",
                  "adequacy_structure", "adequacy_excess_z")
        _positive(self, "preload_rel_sigma", "preload_check_chi2", "window_disagreement_chi2", allow_zero=True)
        if self.preload_rel_sigma > 0.5:
            raise ValueError(f"preload_rel_sigma = {self.preload_rel_sigma!r} must be within 0..0.5")
        for name in ("mismatch_floor", "mismatch_scale"):
            v = getattr(self, name)
            if not (isinstance(v, tuple) and len(v) == 2 and all(
                    isinstance(e, (int, float)) and not isinstance(e, bool) and math.isfinite(e) and e >= 0 for e in v)):
                raise ValueError(f"{name} {v!r} must be two numbers >= 0 (relative N_u, µm)")
        if not (20e-6 <= self.window_s <= 2e-3):
            raise ValueError(f"window_s = {self.window_s!r} must be within 2e-05..0.002 s (20..2000 µs)")
        if self.nu_bounds_n_per_v is not None:
            lo, hi = self.nu_bounds_n_per_v
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
                raise ValueError(f"N_u bounds {self.nu_bounds_n_per_v} N/V are not an interval")
        if self.lh_bounds_um is not None:
            lo, hi = self.lh_bounds_um
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"L_h bounds {self.lh_bounds_um} µm are not an interval")

    def nu_range(self, params: InjectorParameters) -> tuple[float, float]:
        """The N_u search range in N/V: the configured one, else the parameters' range (Table 1's
        15..21 N/V) widened by :data:`NU_SEARCH_MARGIN_N_PER_V`."""
        if self.nu_bounds_n_per_v is not None:
            return self.nu_bounds_n_per_v
        psa = params.psa
        return psa.nu_min_n_per_v - NU_SEARCH_MARGIN_N_PER_V, psa.nu_max_n_per_v + NU_SEARCH_MARGIN_N_PER_V

    def lh_range(self, params: InjectorParameters) -> tuple[float, float]:
        """The L_h search range in µm: the configured one, else the parameters' (Table 2's -2..10 µm)."""
        if self.lh_bounds_um is not None:
            return self.lh_bounds_um
        return params.valve.lh_min_m * UM_PER_M, params.valve.lh_max_m * UM_PER_M
        if min(self.grid) < 3 or self.zoom_points < 3 or self.zooms < 0 or self.max_cycles < 1:
            raise ValueError("grid needs >= 3 points per axis, zoom_points >= 3, zooms >= 0, max_cycles >= 1")


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of the recursive estimator.

    Process noise is time-aware: per injection a floor (model jitter), plus per second of time since
    that injector's last accepted injection a random walk of N_u (temperature) and L_h (wear) and a
    white acceleration of the N_u drift rate. Times come from the bus (or a trace's ``time_s``); where
    unknown, ``default_interval_s`` is assumed.
    """

    ident: IdentConfig = field(default_factory=IdentConfig)
    q_nu_n_per_v: float = 0.003             # N_u random walk per injection, N/V (floor)
    q_lh_um: float = 0.003                  # L_h random walk per injection, µm (floor)
    q_nu_per_sqrt_s: float = 0.01           # N_u random walk, N/V per sqrt(s), temperature not measured
    q_nu_per_sqrt_s_known_t: float = 0.002  # the same where the temperature change is measured (eq. 25 explains the rest)
    q_lh_per_sqrt_s: float = 0.002          # L_h random walk (wear), µm per sqrt(s)
    q_rate_per_sqrt_s: float = 0.01         # N_u drift-rate random walk, N/V/s per sqrt(s)
    q_rate_per_sqrt_s_known_t: float = 0.001  # the same where the temperature change is measured
    q_wear_um: float = 1e-4                 # the wear rate's random walk, µm per injection, per injection
    max_wear_um: float = 0.015              # bound of |dL_h| per injection, µm (its prior sd a third of it)
    max_rate_n_per_v_s: float = 0.3         # physical bound of |dN_u/dt| (5 degC/s at 0.06 N/V/degC)
    rate_tau_s: float = 120.0               # a drift rate decays with this time constant (warm-ups end)
    slope_n_per_v_degc: float = 0.06        # prior of dN_u/dT (eq. 25; Table 1: 15..21 N/V over 0..100 degC)
    slope_sigma: float = 0.03               # its prior standard deviation, N/V/degC
    default_interval_s: float = 0.1         # assumed time between injections when the time is unknown
    max_interval_s: float = 3600.0          # longer gaps count as this long (covariance caps apply anyway)
    gate_chi2: float = 18.4                 # 2 dof, P(false rejection) = 1e-4
    raw_publish_chi2: float = 40.0          # a doubt beyond this (P = 2e-9 for noise) publishes its own estimate
    max_consecutive_outliers: int = 5       # doubts in a row that do not agree with each other: re-acquire
    warm_cycles: int = 3
    robust_on_after: int = 3                # consecutive injections with model error to switch robust on
    robust_off_after: int = 20              # consecutive clean injections to switch it off again
    robust_floor: tuple[float, float] = (0.02, 0.1)  # added raw sigma (N/V, µm) in robust mode: bias
    mismatch_on_after: int = 2              # consecutive mismatched injections that make an adequate injector mismatched
    mismatch_clear_after: int = 10          # consecutive adequate injections before an injector's model mismatch is cleared

    def __post_init__(self) -> None:
        _positive(self, "q_nu_n_per_v", "q_lh_um", "gate_chi2", "raw_publish_chi2", "default_interval_s", "max_interval_s",
                  "max_rate_n_per_v_s", "rate_tau_s", "slope_sigma", "max_wear_um")
        _positive(self, "q_nu_per_sqrt_s", "q_nu_per_sqrt_s_known_t", "q_lh_per_sqrt_s", "q_rate_per_sqrt_s",
                  "q_rate_per_sqrt_s_known_t", "q_wear_um", allow_zero=True)
        if not math.isfinite(self.slope_n_per_v_degc):
            raise ValueError(f"slope_n_per_v_degc = {self.slope_n_per_v_degc!r} must be a number")
        for name in ("max_consecutive_outliers", "warm_cycles", "robust_on_after", "robust_off_after",
                     "mismatch_on_after", "mismatch_clear_after"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise ValueError(f"{name} = {v!r} must be a whole number >= 1")
