"""The recursive estimator's state per injector (:class:`TrackerState`): what it holds between
injections, its schema as the state file stores it, its validation when restored, and the bounds the
filter is held within (one fact, so that a state the estimator wrote always loads)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from estimator.ident.config import TrackerConfig
from estimator.ident.fit.search import Box
from estimator.ident.tracking import kalman

STATE_VERSION = 2


def process_noise(config: TrackerConfig, box: Box) -> kalman.ProcessNoise:
    """The filter's process noise and variance caps for this configuration and search box."""
    span = box.hi - box.lo
    return kalman.ProcessNoise(
        config.q_nu_n_per_v, config.q_lh_um, config.q_nu_per_sqrt_s, config.q_nu_per_sqrt_s_known_t,
        config.q_lh_per_sqrt_s,
        config.q_rate_per_sqrt_s, config.q_rate_per_sqrt_s_known_t, config.slope_sigma / math.sqrt(3600.0), config.rate_tau_s,
        (float(span[0] / 2) ** 2, float(span[1] / 2) ** 2, config.max_rate_n_per_v_s ** 2, config.slope_sigma ** 2,
         config.max_wear_um ** 2), config.q_wear_um)


@dataclass
class Pending:
    """A raw estimate in doubt (N/V, µm) with its covariance, time (s) and temperature (degC)."""

    z: list[float]
    r: list[list[float]]
    time_s: float | None
    temperature_c: float | None
    counter: int


@dataclass
class TrackerState:
    """Everything the estimator knows about one injector; JSON-serialisable via ``to_dict``.

    ``x`` = filtered [N_u N/V, L_h µm, drift rate N/V/s, temperature slope N/V/degC] at the time and
    temperature of the last accepted injection, ``p`` its covariance; ``directions`` (columns) and
    ``steps`` the line-search state carried to the next injection; ``pending`` an injection in doubt;
    ``mismatch`` whether the model cannot explain this injector (until ``mismatch_clean`` reaches the
    configured count of adequate injections; ``mismatch_run`` counts mismatched ones in a row),
    ``model_error_d`` and ``model_error_structure`` running mean squares of the plain - robust
    differences (N/V, µm) and of the plain residual's structure (chi-square) that size its model error;
    ``excess_z`` a running mean of a mismatched injector's residual excess over white noise (standard
    deviations), which lets a re-acquisition keep a local fit that leaves as much (see :func:`_cold_estimate`);
    ``preload_shift`` the move (N/V, µm) the samples' own preload force implied at the last test of the
    header's (None: the header's agreed, or no test yet) and ``preload_wrong`` that test's verdict, both
    held until the next test; ``current_noise_cov`` the covariance (N/V, µm) the measured current's
    noise added to the last estimate that sized it (with the preload force's test), added to the
    estimates in between.
    """

    initialized: bool = False
    x: list[float] = field(default_factory=lambda: [math.nan] * kalman.N_STATE)
    p: list[list[float]] = field(default_factory=lambda: np.eye(kalman.N_STATE).tolist())
    time_s: float | None = None
    temperature_c: float | None = None
    directions: list[list[float]] = field(default_factory=lambda: [[1.0, 0.0], [0.0, 1.0]])
    steps: list[float] = field(default_factory=lambda: [0.05, 0.2])
    robust: bool = False
    model_error_run: int = 0
    clean_run: int = 0
    doubts: int = 0
    pending: Pending | None = None
    accepted: int = 0
    rejected: int = 0
    updates: int = 0
    mismatch: bool = False
    mismatch_clean: int = 0
    mismatch_run: int = 0
    model_error_d: list[float] = field(default_factory=lambda: [0.0, 0.0])
    model_error_structure: float | None = None
    excess_z: float | None = None
    preload_shift: list[float] | None = None
    preload_wrong: bool = False
    current_noise_cov: list[list[float]] | None = None
    version: int = STATE_VERSION

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for JSON (no NaN: unknown values are None)."""
        d = asdict(self)
        d["x"] = [v if math.isfinite(v) else None for v in self.x]
        return d

    @classmethod
    def from_dict(cls, d: Any) -> TrackerState:
        """Inverse of :meth:`to_dict`, validating every field; ValueError names the first bad one."""
        if not isinstance(d, dict) or d.get("version") != STATE_VERSION:
            raise ValueError(f"not a tracker state of version {STATE_VERSION}")
        st = cls()
        for name in ("initialized", "robust", "mismatch", "preload_wrong"):
            setattr(st, name, _check_bool(d, name, getattr(st, name)))
        for name in ("model_error_run", "clean_run", "doubts", "accepted", "rejected", "updates", "mismatch_clean",
                     "mismatch_run"):
            setattr(st, name, _check_count(d, name))
        st.model_error_d = _check_array(d, "model_error_d", (2,), True).tolist() if "model_error_d" in d else [0.0, 0.0]
        st.model_error_structure = _check_optional_float(d, "model_error_structure")
        st.excess_z = _check_optional_float(d, "excess_z") if "excess_z" in d else None
        if d.get("preload_shift") is not None:
            st.preload_shift = _check_array(d, "preload_shift", (2,), True).tolist()
        if d.get("current_noise_cov") is not None:
            c = _check_array(d, "current_noise_cov", (2, 2), True)
            if not is_covariance(c, -1e-15):
                raise ValueError("current_noise_cov is not a symmetric positive semi-definite covariance")
            st.current_noise_cov = c.tolist()
        x, p = _without_wear(d)
        st.x = (x if x is not None else _check_array(d, "x", (kalman.N_STATE,), st.initialized)).tolist()
        p = p if p is not None else _check_array(d, "p", (kalman.N_STATE, kalman.N_STATE), True)
        if st.initialized and not is_covariance(p):
            raise ValueError("p is not a symmetric positive semi-definite covariance")
        st.p = p.tolist()
        st.directions = _check_array(d, "directions", (2, 2), True).tolist()
        steps = _check_array(d, "steps", (2,), True)
        if np.any(steps <= 0):
            raise ValueError("steps must be positive")
        st.steps = steps.tolist()
        st.time_s = _check_optional_float(d, "time_s")
        st.temperature_c = _check_optional_float(d, "temperature_c")
        if st.initialized:
            nu, lh = st.x[0], st.x[1]
            if not (5.0 <= nu <= 40.0 and -20.0 <= lh <= 50.0):
                raise ValueError(f"x = N_u {nu} N/V, L_h {lh} µm is far outside any physical range")
        pend = d.get("pending")
        if pend is not None:
            if not isinstance(pend, dict):
                raise ValueError("pending must be an object or null")
            st.pending = Pending(_check_array(pend, "z", (2,), True).tolist(),
                                 _check_array(pend, "r", (2, 2), True).tolist(),
                                 _check_optional_float(pend, "time_s"), _check_optional_float(pend, "temperature_c"),
                                 _check_count(pend, "counter"))
        return st

    def with_prior(self, nu_n_per_v: float, lh_um: float, sigma: tuple[float, float] = (0.3, 1.0),
                   slope: float = 0.06, slope_sigma: float = 0.03) -> TrackerState:
        """A state that starts from a given prior (used by EstimatorCommand 'set prior')."""
        x, p = kalman.initial(np.array([nu_n_per_v, lh_um], dtype=float), np.diag(np.square(sigma)), 0.01 ** 2,
                              slope, slope_sigma ** 2, wear_variance(TrackerConfig()))
        return replace(TrackerState(), initialized=True, x=x.tolist(), p=p.tolist())


CARRIED = (kalman.SLOPE, kalman.WEAR)   # what the filter learns of the part itself, whatever its model


def carried_over(st: TrackerState | None) -> TrackerState:
    """A state for the same part re-acquired under a refinement of its model: N_u and L_h start cold
    (under another model they are biased differently), the temperature slope and the wear rate
    learned so far are kept with their variances (:data:`CARRIED`; the restart takes them). Learned
    afresh after every refinement, the wear rate's prior (sd 0.005 µm per injection) let L_h wander
    and widened its σ for the 20-odd injections it took to learn it again."""
    new = TrackerState()
    if st is None or not st.initialized or not all(map(math.isfinite, st.x)):
        return new
    for k in CARRIED:
        new.x[k], new.p[k][k] = st.x[k], st.p[k][k]
    return new


def wear_variance(config: TrackerConfig) -> float:
    """The wear rate's prior variance, (µm per injection)^2: a third of its bound, squared."""
    return (config.max_wear_um / 3.0) ** 2


def _without_wear(d: dict[str, Any]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """A state written before the filter had a wear rate (four states): its ``x`` and ``p`` with no
    wear and the wear rate's prior variance; (None, None) for any other state."""
    old = kalman.N_STATE - 1
    x, p = d.get("x"), d.get("p")
    if not (isinstance(x, list) and len(x) == old and isinstance(p, list) and len(p) == old):
        return None, None
    xs = _check_array(d, "x", (old,), bool(d.get("initialized", False)))
    ps = _check_array(d, "p", (old, old), True)
    pn = np.zeros((kalman.N_STATE, kalman.N_STATE))
    pn[:old, :old] = ps
    pn[kalman.WEAR, kalman.WEAR] = wear_variance(TrackerConfig())
    return np.append(xs, 0.0), pn


def _check_bool(d: dict[str, Any], name: str, default: bool) -> bool:
    v = d.get(name, default)
    if not isinstance(v, bool):
        raise ValueError(f"{name} = {v!r} must be true or false")
    return v


def _check_count(d: dict[str, Any], name: str) -> int:
    v = d.get(name, 0)
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise ValueError(f"{name} = {v!r} must be a non-negative whole number")
    return v


def _check_optional_float(d: dict[str, Any], name: str) -> float | None:
    v = d.get(name)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"{name} = {v!r} must be a finite number or null")
    return float(v)


def is_covariance(m: np.ndarray, floor: float = 0.0) -> bool:
    """``m`` symmetric (to rounding) with no eigenvalue below ``floor``."""
    return bool(np.allclose(m, m.T, rtol=1e-9, atol=1e-15) and not np.any(np.linalg.eigvalsh(m) < floor))


def _check_array(d: dict[str, Any], name: str, shape: tuple[int, ...], finite: bool) -> np.ndarray:
    v = d.get(name)
    try:
        a = np.array(v, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers of shape {shape}") from None
    if a.shape != shape:
        raise ValueError(f"{name} has shape {a.shape}, expected {shape}")
    if finite and not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has non-finite values")
    return a


def physical_problem(st: TrackerState, config: TrackerConfig, box: Box,
                     temperature_range_c: tuple[float, float] | None = None) -> str | None:
    """Why a (restored) state is outside what this estimator can hold, or None.

    ``box`` is the search box in (N/V, µm): Table 1's N_u range (with the simulator's margin) and the
    model's L_h range. The drift rate and the temperature slope must be within their configured
    bounds (a little slack for rounding), the variances within the caps the filter applies itself,
    the counters below 2**53.
    """
    noise = process_noise(config, box)
    lo, hi = box.lo, box.hi
    for name in ("model_error_run", "clean_run", "doubts", "accepted", "rejected", "updates"):
        if getattr(st, name) >= 2 ** 53:
            return f"{name} = {getattr(st, name)} is not a plausible count"
    t_lo, t_hi = temperature_range_c if temperature_range_c is not None else (-math.inf, math.inf)
    if st.temperature_c is not None and not t_lo <= st.temperature_c <= t_hi:
        return f"temperature_c = {st.temperature_c} degC is outside {t_lo:g}..{t_hi:g} degC"
    points = []
    x, p = np.asarray(st.x, dtype=float), np.asarray(st.p, dtype=float)
    # an initialized state holds every component; one not yet acquired at most those carried over
    held = list(range(kalman.N_STATE)) if st.initialized else [k for k in CARRIED if math.isfinite(x[k])]
    rate_max, slope_lo, slope_hi, wear_max = state_bounds(config)
    if st.initialized:
        points.append(("x", x[:2]))
        if abs(x[kalman.RATE]) > rate_max * (1 + 1e-9):
            return f"drift rate {x[kalman.RATE]:.4g} N/V/s is beyond the bound {rate_max} N/V/s"
    if kalman.SLOPE in held and not slope_lo - 1e-12 <= x[kalman.SLOPE] <= slope_hi + 1e-12:
        return f"temperature slope {x[kalman.SLOPE]:.4g} N/V/degC is beyond {SLOPE_SDS:g} prior sigma"
    if kalman.WEAR in held and abs(x[kalman.WEAR]) > wear_max * (1 + 1e-9):
        return f"wear rate {x[kalman.WEAR]:.4g} µm per injection is beyond the bound {wear_max} µm"
    var = np.diag(p)[held]
    if np.any(var > 1.01 * np.asarray(noise.max_var)[held]) or np.any(var < 0.0):
        return "p has variances beyond the filter's caps"
    if st.pending is not None:
        points.append(("pending z", np.asarray(st.pending.z, dtype=float)))
        r = np.asarray(st.pending.r, dtype=float)
        if not is_covariance(r):
            return "pending r is not a covariance"
    for what, (nu, lh) in points:
        if not (lo[0] <= nu <= hi[0]):
            return f"{what}: N_u = {nu:.4g} N/V is outside [{lo[0]:g}, {hi[0]:g}] N/V"
        if not (lo[1] <= lh <= hi[1]):
            return f"{what}: L_h = {lh:.4g} µm is outside [{lo[1]:g}, {hi[1]:g}] µm"
    return None


SLOPE_SDS = 10.0   # the temperature slope is held within this many prior sigmas of the prior slope


def state_bounds(config: TrackerConfig) -> tuple[float, float, float, float]:
    """The bounds of the filter's drift rate (|rate| at most, N/V/s), temperature slope (low, high,
    N/V/degC) and wear rate (|w| at most, µm per injection): what :func:`_store` holds the filter to
    and what a restored state is checked against (one fact, so that a state the estimator wrote
    always loads)."""
    return (config.max_rate_n_per_v_s, config.slope_n_per_v_degc - SLOPE_SDS * config.slope_sigma,
            config.slope_n_per_v_degc + SLOPE_SDS * config.slope_sigma, config.max_wear_um)
