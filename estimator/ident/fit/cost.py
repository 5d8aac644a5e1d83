"""Cost functions of eqs. 26 and 28, evaluated in batches with the fast simulator.

``J = ∫_0^t1 |U_m − U_sim| dt`` (the paper's L1 cost, reported as ``cost_uvs``) and its least
squares sibling ``∫ (U_m − U_sim)^2 dt`` which the searches minimise by default: under Gaussian
measurement noise it is the maximum-likelihood criterion (it attains the Cramér–Rao bound where the
L1 cost loses about a third of the information), and it is smooth, so parabolic line searches work.

Robust mode (model error): the model's largest error is the hysteresis H[Q] that it replaces by
R(N_u)·I (paper, section 3.3, Fig. 7: about ±2 V), plus resistances in series. On the rising branch
(charging, Q increasing) a Prandtl–Ishlinskii operator is exactly ``sum_i w_i max(Q − r_i, 0)``.
With ``robust=True`` the residual is projected onto the orthogonal complement of
span{I, Q, max(Q − r_i, 0)} with four thresholds r_i at 4, 10, 25 and 50 % of the window's final
charge, i.e. any PI operator with those thresholds and any series resistance is absorbed, whatever
its weights. What remains is the dynamic contact signature, which determines L_h. Four thresholds
are the compromise measured in the accuracy bench: with two the hysteresis leaks into the
estimate, with seven the basis starts to absorb the contact itself. :func:`model_error_statistic`
tests whether a residual has significant structure in that span, which is how the estimator
decides to use it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from estimator._compiled import njit
from estimator._compiled.direct_call import DirectCall, c_float
from estimator.choices import Norm
from estimator.ident.measurement import Injection
from estimator.model.automaton import Automaton
from estimator.model.drive import sample_count
from estimator.model.fast_sim import BatchResult, FastSimulator
from estimator.model.kernel import KernelModel

NUISANCE_THRESHOLDS = (0.04, 0.10, 0.25, 0.50)   # fractions of the window's final charge
MAD_PER_SIGMA = 0.6744897501960817   # median absolute deviation of a unit normal
NOISE_FLOOR_V = 1e-3   # 1 mV: far below any amplifier ADC step; keeps noise-free (simulated) traces sane
NUISANCE_NAMES = ("I", "Q", *tuple(f"max(Q-{r:.2f}Qend,0)" for r in NUISANCE_THRESHOLDS))


def charge_c(current_a: np.ndarray, dt_s: float) -> np.ndarray:
    """Cumulative charge (C) of a current that is linear between samples (trapezoidal rule)."""
    return _charge(np.ascontiguousarray(current_a, dtype=float), float(dt_s))


@njit(cache=True, nogil=True)
def _charge(current_a: np.ndarray, dt_s: float) -> np.ndarray:
    q = np.empty(current_a.size)
    q[0] = 0.0
    acc = 0.0
    for k in range(1, current_a.size):
        acc += (current_a[k] + current_a[k - 1]) * (0.5 * dt_s)
        q[k] = acc
    return q


def nuisance_columns(current_a: np.ndarray, dt_s: float) -> np.ndarray:
    """The nuisance span's columns I, Q, max(Q - r_i, 0), each normalised to max 1, shape (N, 6)."""
    return _nuisance_columns(np.ascontiguousarray(current_a, dtype=float), float(dt_s), _THRESHOLDS)


_THRESHOLDS = np.array(NUISANCE_THRESHOLDS, dtype=float)


@njit(cache=True, nogil=True)
def _nuisance_columns(current_a: np.ndarray, dt_s: float, thresholds: np.ndarray) -> np.ndarray:
    q = _charge(current_a, dt_s)
    n = q.size
    q_end = max(q[-1], 1e-12)
    i_max = max(np.abs(current_a).max(), 1e-300)
    b = np.empty((n, 2 + thresholds.size))
    for k in range(n):
        b[k, 0] = current_a[k] / i_max
        b[k, 1] = q[k] / q_end
        for m in range(thresholds.size):
            b[k, 2 + m] = max(b[k, 1] - thresholds[m], 0.0)
    return b


def nuisance_basis(current_a: np.ndarray, dt_s: float) -> np.ndarray:
    """Orthonormal basis (N, 6) of the nuisance span (QR of :func:`nuisance_columns`). numpy's QR:
    numba's (the same LAPACK routines, from another build) took 11 instead of 24 µs but differed in the
    last bits for some windows (35 of the accuracy bench's 400 estimates moved by 1e-10)."""
    qb, _ = np.linalg.qr(nuisance_columns(current_a, dt_s))
    return qb


def noise_sigma_v(residual_v: np.ndarray) -> float:
    """White-noise level (V, 1 sigma) of a residual from its first differences, robust (MAD).

    Differencing removes smooth model errors; the median ignores isolated spikes.
    """
    return float(noise_sigma(np.ascontiguousarray(residual_v, dtype=float)))


@njit(cache=True, nogil=True)
def noise_sigma(r: np.ndarray) -> float:
    """:func:`noise_sigma_v` of a contiguous float array, callable from compiled code."""
    n = r.shape[0]
    d = np.empty(n - 1)
    for k in range(n - 1):
        d[k] = abs(r[k + 1] - r[k])
    mad = np.partition(d, (n - 1) // 2)[(n - 1) // 2]
    result: float = max(mad / MAD_PER_SIGMA / np.sqrt(2.0), NOISE_FLOOR_V)
    return result


def model_error_statistic(residual_v: np.ndarray, basis: np.ndarray, sigma_v: float | None = None) -> float:
    """Residual energy in the nuisance span, in units of the noise variance.

    ``basis`` is orthonormal (:func:`nuisance_basis`) or the raw columns (:func:`nuisance_columns`).

    Under a correct model with white noise it is chi-square distributed with ``basis.shape[1]``
    degrees of freedom (mean 6); a model error of the I/Q form makes it large.
    """
    sigma = noise_sigma_v(residual_v) if sigma_v is None else sigma_v
    return _span_energy(np.ascontiguousarray(residual_v, dtype=float), np.ascontiguousarray(basis, dtype=float)) / sigma ** 2


def plain_model_error(residual_v: np.ndarray, current_a: np.ndarray, dt_s: float, sigma_v: float) -> float:
    """:func:`model_error_statistic` of a residual (V) against the raw :func:`nuisance_columns` of its
    window's current (A, sampled every ``dt_s`` s), with the noise level ``sigma_v`` (V): one compiled
    call (the warm update's test of the plain model)."""
    return float(_PLAIN_MODEL_ERROR(c_float(residual_v), c_float(current_a), float(dt_s), _THRESHOLDS,
                                    float(sigma_v)))


@njit(cache=True, nogil=True)
def _plain_model_error(r: np.ndarray, current_a: np.ndarray, dt_s: float, thresholds: np.ndarray, sigma_v: float) -> float:
    """``_span_energy(r, _nuisance_columns(...)) / sigma_v**2``; for the four thresholds of
    :data:`NUISANCE_THRESHOLDS` (six columns) with each column formed per sample and the 6 + 21 sums
    of ``b'r`` and ``b'b`` kept in registers, in the same order (the same to the bit, 6.1 -> 3.1 µs)."""
    if thresholds.size != 4:
        return _span_energy(r, _nuisance_columns(current_a, dt_s, thresholds)) / sigma_v ** 2
    q = _charge(current_a, dt_s)
    q_end = max(q[-1], 1e-12)
    i_max = max(np.abs(current_a).max(), 1e-300)
    t0, t1, t2, t3 = thresholds[0], thresholds[1], thresholds[2], thresholds[3]
    b0 = b1 = b2 = b3 = b4 = b5 = 0.0
    g00 = g01 = g02 = g03 = g04 = g05 = g11 = g12 = g13 = g14 = g15 = 0.0
    g22 = g23 = g24 = g25 = g33 = g34 = g35 = g44 = g45 = g55 = 0.0
    for k in range(q.size):
        c0 = current_a[k] / i_max
        c1 = q[k] / q_end
        c2 = max(c1 - t0, 0.0)
        c3 = max(c1 - t1, 0.0)
        c4 = max(c1 - t2, 0.0)
        c5 = max(c1 - t3, 0.0)
        rk = r[k]
        b0 += c0 * rk
        b1 += c1 * rk
        b2 += c2 * rk
        b3 += c3 * rk
        b4 += c4 * rk
        b5 += c5 * rk
        g00 += c0 * c0
        g01 += c0 * c1
        g02 += c0 * c2
        g03 += c0 * c3
        g04 += c0 * c4
        g05 += c0 * c5
        g11 += c1 * c1
        g12 += c1 * c2
        g13 += c1 * c3
        g14 += c1 * c4
        g15 += c1 * c5
        g22 += c2 * c2
        g23 += c2 * c3
        g24 += c2 * c4
        g25 += c2 * c5
        g33 += c3 * c3
        g34 += c3 * c4
        g35 += c3 * c5
        g44 += c4 * c4
        g45 += c4 * c5
        g55 += c5 * c5
    br = np.array([b0, b1, b2, b3, b4, b5])
    if abs(g00 - 1.0) <= 1e-9:     # _span_energy's orthonormal test (column 0 of unit norm)
        return float(br @ br) / sigma_v ** 2
    g = np.array([[g00, g01, g02, g03, g04, g05], [g01, g11, g12, g13, g14, g15], [g02, g12, g22, g23, g24, g25],
                  [g03, g13, g23, g33, g34, g35], [g04, g14, g24, g34, g44, g45], [g05, g15, g25, g35, g45, g55]])
    return float(br @ np.linalg.solve(g, br)) / sigma_v ** 2


@njit(cache=True, nogil=True)
def _span_energy(r: np.ndarray, b: np.ndarray) -> float:
    """``|P r|^2`` for the projection P onto the span of the columns of ``b`` (N, K): ``|b' r|^2`` if they
    are orthonormal, else through the normal equations ``(b'r)' (b'b)^-1 (b'r)``."""
    n, m = b.shape
    if m == 0:
        return 0.0
    br = np.zeros(m)
    for k in range(n):
        for q in range(m):
            br[q] += b[k, q] * r[k]
    norm0 = 0.0
    for k in range(n):
        norm0 += b[k, 0] * b[k, 0]
    if abs(norm0 - 1.0) <= 1e-9:
        return float(br @ br)
    g = np.zeros((m, m))
    for k in range(n):
        for p in range(m):
            for q in range(p, m):
                g[p, q] += b[k, p] * b[k, q]
    for p in range(m):          # symmetric: the lower triangle is the upper one (a * b == b * a exactly)
        for q in range(p):
            g[p, q] = g[q, p]
    return float(br @ np.linalg.solve(g, br))


@njit(cache=True, nogil=True)
def residuals_into(measured: np.ndarray, u: np.ndarray, basis: np.ndarray, project: bool, out: np.ndarray) -> None:
    """``out`` (B, N) = ``measured`` (N,) - ``u`` (B, >= N) in V, each row projected off ``basis``
    (N, K, orthonormal) if ``project``."""
    nb, n = out.shape
    for b in range(nb):
        for k in range(n):
            out[b, k] = measured[k] - u[b, k]
    if project:
        nk = basis.shape[1]
        c = np.empty(nk)
        for b in range(nb):
            for q in range(nk):
                s = 0.0
                for k in range(n):
                    s += out[b, k] * basis[k, q]
                c[q] = s
            for k in range(n):
                s = 0.0
                for q in range(nk):
                    s += c[q] * basis[k, q]
                out[b, k] -= s


@njit(cache=True, nogil=True)
def costs_of(r: np.ndarray, weights: np.ndarray, l1: bool, success: np.ndarray) -> np.ndarray:
    """The cost of each row of residuals ``r`` (B, N) in V with quadrature ``weights`` (s): V^2 s, or
    V s if ``l1``; +inf where not ``success`` or not finite."""
    nb, n = r.shape
    j = np.empty(nb)
    for b in range(nb):
        s = 0.0
        for k in range(n):
            v = r[b, k]
            s += (abs(v) if l1 else v * v) * weights[k]
        j[b] = s if (success[b] and np.isfinite(s)) else np.inf
    return j


@njit(cache=True, nogil=True)
def residual_costs(measured: np.ndarray, u: np.ndarray, basis: np.ndarray, project: bool, weights: np.ndarray, l1: bool,
                   success: np.ndarray) -> np.ndarray:
    """:func:`costs_of` the residuals :func:`residuals_into` gives."""
    r = np.empty((u.shape[0], measured.shape[0]))
    residuals_into(measured, u, basis, project, r)
    return costs_of(r, weights, l1, success)


@functools.lru_cache(maxsize=32)
def trapezoid_weights(n: int, dt_s: float) -> np.ndarray:
    """Trapezoidal-rule weights (s) of ``n`` samples ``dt_s`` apart, kept per (n, dt_s): shared by every
    cost model of that window, so nothing may write to them (left writeable: compiled callers would
    otherwise be compiled a second time for read-only arrays)."""
    w = np.full(n, dt_s)
    w[[0, -1]] *= 0.5
    return w


class Problem(NamedTuple):
    """One cost window as compiled code reads it (:mod:`estimator.ident.fit.fit_kernel`): the simulator's
    kernel, the window's samples and the cost's settings. Its types never change (float64 C arrays,
    floats, bools), so compiled calls on it can skip numba's dispatch (:class:`DirectCall`)."""

    model: KernelModel
    automaton: Automaton
    table: np.ndarray       # the simulator's transition-matrix table (scaled units)
    h_us: float             # sample period in the kernel's time unit (µs)
    nu_lo: float            # the simulator's N_u range (N/V)
    nu_hi: float
    current: np.ndarray     # (N,) A
    f_open_n: float         # N
    measured: np.ndarray    # (N,) V
    weights: np.ndarray     # (N,) s, trapezoidal
    basis: np.ndarray       # (N, K) orthonormal nuisance basis if robust, else (0, 0)
    robust: bool
    l1: bool


_NO_BASIS = np.empty((0, 0))


@dataclass
class CostModel:
    """The cost of one injection over a window, as a function of (N_u, L_h) candidates.

    Parameters
    ----------
    sim : the fast simulator (its sample period must equal the injection's).
    injection : the measured injection.
    window_s : end of the cost window t1 in s (the window starts at 0).
    norm : "l2" (least squares, default) or "l1" (the paper's absolute error).
    robust : project out the nuisance span (see module docstring).
    """

    sim: FastSimulator
    injection: Injection
    window_s: float = 100e-6
    norm: Norm | str = Norm.L2
    robust: bool = False

    def __post_init__(self) -> None:
        try:
            self.norm = Norm(self.norm)
        except ValueError:
            raise ValueError(f"norm must be one of {', '.join(Norm.words())}, not {self.norm!r}") from None
        inj = self.injection
        self.n = min(inj.n, sample_count(self.window_s, inj.dt_s))
        self.current = np.ascontiguousarray(inj.current_a[: self.n], dtype=float)
        self.measured = np.ascontiguousarray(inj.voltage_v[: self.n], dtype=float)
        self.dt = inj.dt_s
        self.weights = trapezoid_weights(self.n, self.dt)
        self._basis: np.ndarray | None = None
        self._basis_of: CostModel | None = None   # another model of the same samples: its basis is this one's
        self._problem: Problem | None = None
        self.evaluations = 0

    @property
    def problem(self) -> Problem:
        """This window as compiled code reads it (built on first use)."""
        if self._problem is None:
            h = self.sim.kernel_handle()
            self._problem = Problem(h.model, h.automaton, h.table, h.h_us, h.nu_lo, h.nu_hi, self.current,
                                    float(self.injection.f_open_n), self.measured, self.weights,
                                    c_float(self.basis) if self.robust else _NO_BASIS, bool(self.robust),
                                    self.norm == "l1")
        return self._problem

    @property
    def basis(self) -> np.ndarray:
        """Orthonormal nuisance basis of this injection's window (computed on first use, or
        ``share_basis``'s model's)."""
        if self._basis is None:
            self._basis = self._basis_of.basis if self._basis_of is not None else nuisance_basis(self.current, self.dt)
        return self._basis

    def share_basis(self, other: CostModel) -> None:
        """Take ``other``'s nuisance basis (whichever of the two asks first computes it) where both
        models cover the same samples of the same injection: the plain and the robust cost of one
        cold start over one window (a QR, ≈ 29 µs, once instead of twice)."""
        if other is not self and other.injection is self.injection and other.n == self.n and self._basis is None:
            self._basis_of = other

    def simulate(self, nu: np.ndarray | float, lh: np.ndarray | float) -> BatchResult:
        """Simulate candidates over the window (counts evaluations)."""
        nu = np.atleast_1d(nu)
        self.evaluations += int(np.broadcast(nu, np.atleast_1d(lh)).size)
        return self.sim.simulate(self.current, nu, lh, self.injection.f_open_n)

    def without_nuisance(self, r: np.ndarray) -> np.ndarray:
        """One residual (N,) in V with this window's nuisance span projected out."""
        result: np.ndarray = r - self.basis @ (self.basis.T @ r)
        return result

    def from_result(self, res: BatchResult) -> np.ndarray:
        """The cost of simulated candidates: V^2*s (l2) or V*s (l1); +inf where infeasible."""
        return self.cost_of(res.voltage_v, res.success)

    def cost_of(self, voltage_v: np.ndarray, success: np.ndarray | None = None) -> np.ndarray:
        """The cost of simulated voltages (B, >= N) in V; +inf where not ``success`` or not finite
        (the compiled fits' own cost, :func:`residual_costs`)."""
        p = self.problem
        u = np.ascontiguousarray(voltage_v[:, : self.n], dtype=float)
        ok = np.ones(u.shape[0], dtype=bool) if success is None else np.ascontiguousarray(success, dtype=bool)
        return residual_costs(p.measured, u, p.basis, p.robust, p.weights, p.l1, ok)

    def __call__(self, nu: np.ndarray | float, lh: np.ndarray | float) -> np.ndarray:
        """The cost of candidates (N_u in N/V, L_h in m; arrays broadcast)."""
        return self.from_result(self.simulate(nu, lh))

    def paper_cost_vs(self, res: BatchResult) -> np.ndarray:
        """The paper's J = ∫|U_m − U_sim| dt in V*s, unprojected (eq. 28); +inf where not finite."""
        u = np.ascontiguousarray(res.voltage_v[:, : self.n], dtype=float)
        return residual_costs(self.measured, u, _NO_BASIS, False, self.weights, True, np.ones(u.shape[0], dtype=bool))


_PLAIN_MODEL_ERROR = DirectCall(_plain_model_error)   # its argument types are fixed in plain_model_error
