"""Fast hybrid simulator: exact discretisation per affine region, batched over (N_u, L_h) candidates.

The transition matrices ``exp(A_r(N_u) h)`` of the six regions are tabulated once on a uniform
N_u grid (step 0.02 N/V) and interpolated with 4-point Lagrange polynomials; the interpolation
error is below 1e-13 relative (``tests/model/test_simulators.py`` checks it against the direct exponential).
``exact=True`` computes the matrix exponential for each distinct N_u instead (cached). Both use
:func:`~estimator.model.matrix_exponential.expm_batch`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple, TypeVar

import numpy as np

from estimator._compiled.direct_call import DirectCall
from estimator.errors import ParameterError
from estimator.model import dynamics as dyn
from estimator.model import kernel
from estimator.model.automaton import Automaton, build_automaton
from estimator.model.drive import SAMPLE_PERIOD_S
from estimator.model.dynamics import STATUS_TEXT
from estimator.model.matrix_exponential import expm_batch
from estimator.model.parameters import NU_EXTRAPOLATION_N_PER_V, InjectorParameters, check_nu_in, load_nominal
from estimator.units import PER_MICRO

PLATEAU_WINDOW_S = (215e-6, 490e-6)  # Table 3: mean plunger stroke s_4,s over 215-490 µs
FREE_RUN_LH_M = 1.0   # L_h of a grid column's free run (m): a gap no actuator closes


BAD_CURRENT_TEXT = "current must be a 1-D array of at least 2 finite samples (A)"


_VALVE_PREDICTION = DirectCall(kernel.valve_prediction)


def _current(current_a: np.ndarray) -> np.ndarray:
    """The sampled current (A) as a contiguous 1-D float array of at least 2 samples, else
    ParameterError (its finiteness is checked with the candidates, in :func:`kernel.check_inputs`)."""
    cur = np.ascontiguousarray(current_a, dtype=float)
    if cur.ndim != 1 or cur.size < 2:
        raise ParameterError(BAD_CURRENT_TEXT)
    return cur


class KernelHandle(NamedTuple):
    """What a compiled caller needs to run :func:`kernel.run_batch` for this simulator."""

    model: kernel.KernelModel
    automaton: Automaton
    table: np.ndarray      # interpolation table of the transition matrices (scaled units)
    h_us: float            # sample period in the kernel's time unit (µs)
    nu_lo: float           # the simulator's N_u range (N/V), :attr:`FastSimulator.nu_range`
    nu_hi: float


@dataclass(frozen=True)
class BatchResult:
    """Simulated trajectories of B candidates over N samples (SI units).

    Attributes
    ----------
    t_s : (N,) sample times in s.
    current_a : (N,) the current input in A.
    voltage_v : (B, N) actuator voltage U in V (NaN rows where ``success`` is False).
    s3_m, s4_m : (B, N) PSA bottom plate and valve plunger displacement in m.
    mode : (B, N) automaton mode per sample: 1 no contact, 2 contact, 3 valve open, 4 plunger in flight.
    t_contact_s, t_open_s : (B,) first contact and first valve opening in s (NaN if none).
    success : (B,) bool; status : (B,) int code, see ``STATUS_TEXT``.
    """

    t_s: np.ndarray
    current_a: np.ndarray
    nu_n_per_v: np.ndarray
    lh_m: np.ndarray
    f_open_n: np.ndarray
    voltage_v: np.ndarray
    s3_m: np.ndarray
    s4_m: np.ndarray
    mode: np.ndarray
    t_contact_s: np.ndarray
    t_open_s: np.ndarray
    success: np.ndarray
    status: np.ndarray

    @property
    def message(self) -> list[str]:
        """One status text per candidate."""
        return [STATUS_TEXT[int(s)] for s in self.status]

    def plateau_stroke_m(self, window_s: tuple[float, float] = PLATEAU_WINDOW_S) -> np.ndarray:
        """Mean plunger stroke s4 over ``window_s`` (s), shape (B,); NaN if the window is not simulated."""
        return plateau_mean(self.t_s, self.s4_m, window_s)


def plateau_samples(t_s: np.ndarray, window_s: tuple[float, float]) -> tuple[int, int] | None:
    """The samples ``k0 <= k < k1`` of the increasing times ``t_s`` (s) with window[0] <= t <= window[1]
    (1 ps slack); None if there are none or the times end before the window does."""
    k0 = int(np.searchsorted(t_s, window_s[0] - 1e-12, side="left"))
    k1 = int(np.searchsorted(t_s, window_s[1] + 1e-12, side="right"))
    if k0 >= k1 or t_s[-1] < window_s[1] - 1e-12:
        return None
    return k0, k1


def plateau_mean(t_s: np.ndarray, values: np.ndarray, window_s: tuple[float, float]) -> np.ndarray:
    """Mean of ``values[..., k]`` over samples with window[0] <= t <= window[1]; NaN if none."""
    ks = plateau_samples(t_s, window_s)
    if ks is None:
        return np.full(np.shape(values)[:-1], np.nan)
    result: np.ndarray = np.mean(values[..., ks[0]:ks[1]], axis=-1)
    return result


_V = TypeVar("_V")


def remember(cache: dict[Any, Any], key: Any, value: _V, limit: int) -> _V:
    """``cache[key] = value`` in a dict of at most ``limit`` entries (the oldest goes); returns ``value``."""
    if len(cache) >= limit:
        cache.pop(next(iter(cache)))
    cache[key] = value
    return value


class FastSimulator:
    """Batched exact-discretisation simulator of the hybrid model (eq. 27).

    Parameters
    ----------
    params : the model parameters (default: the paper's nominal values).
    dt_s : sampling period in s (default 0.5 µs).
    nu_step : N_u grid spacing of the transition-matrix table in N/V.
    """

    def __init__(self, params: InjectorParameters | None = None, dt_s: float = SAMPLE_PERIOD_S,
                 nu_step: float = 0.02) -> None:
        if not (dt_s > 0 and np.isfinite(dt_s)):
            raise ParameterError(f"sample period {dt_s!r} s must be positive")
        self.params = params or load_nominal()
        self.dt_s = float(dt_s)
        self.structure = dyn.build_structure(self.params)
        self._d = dyn.Z_SCALE
        self.automaton = build_automaton(self.structure, self._d)
        psa = self.params.psa
        margin = 2 * nu_step + NU_EXTRAPOLATION_N_PER_V
        self._nu0 = psa.nu_min_n_per_v - margin
        self._dnu = nu_step
        self._ngrid = int(np.ceil((psa.nu_max_n_per_v - psa.nu_min_n_per_v + 2 * margin) / nu_step)) + 1
        self._phi_table: np.ndarray | None = None
        self._no_idx = np.zeros((1, 4), dtype=np.int64)
        self._no_w = np.zeros((1, 4))
        self._t_cache: dict[int, np.ndarray] = {}
        per_region = (dyn.N_REGIONS, dyn.NZ, dyn.NZ)
        a_const = np.ascontiguousarray(self._scaled(self.structure.a_const))
        a_coup = np.ascontiguousarray(np.broadcast_to(self._scaled(self.structure.a_coupling), per_region))
        a_damp = np.ascontiguousarray(np.broadcast_to(self._scaled(self.structure.a_damping), per_region))
        hys = self.params.hysteresis
        self._model = kernel.KernelModel(
            nu0=float(self._nu0), dnu=float(self._dnu), a_const=a_const, a_coup=a_coup, a_damp=a_damp,
            ks=float(psa.ks_n_per_m), rb=float(psa.rb_v2s_per_mn),
            r0a=0.0 if hys.present else float(psa.r0a_ohm),   # the element replaces R(N_u) I
            r0b=float(psa.r0b_v_per_n), z_scale=np.ascontiguousarray(self._d),
            springs=np.ascontiguousarray(dyn.spring_constants(self.params), dtype=float),
            a_pattern=kernel.sparsity(a_const, a_coup, a_damp), hys_on=hys.present,
            hys_thr=np.array(hys.thresholds_c, dtype=float) * PER_MICRO,
            hys_w=np.array(hys.weights_v_per_c, dtype=float) / PER_MICRO,
            hys_rs=float(hys.series_ohm), hys_nu_ref=float(hys.nu_ref_n_per_v))
        # a plain dict, not functools.lru_cache on a bound method: that makes a reference cycle, and
        # a simulator dropped from a pool would then stay in memory until the cyclic GC runs
        self._exact: dict[float, np.ndarray] = {}
        self._free_shared: bool | None = None   # see _columns_share_free_run
        self._handle: KernelHandle | None = None
        self._plateau: dict[tuple[int, tuple[float, float]], tuple[int, int]] = {}   # see valve_prediction

    # ---- discretisation -------------------------------------------------------------------
    def _scaled(self, a_si: np.ndarray) -> np.ndarray:
        """SI matrices -> scaled units (per µs), see dynamics.Z_SCALE."""
        result: np.ndarray = a_si * (self._d[:, None] / self._d[None, :]) / dyn.TIME_SCALE
        return result

    def scaled_matrices(self, nu: np.ndarray) -> np.ndarray:
        """Continuous region matrices in scaled units (per µs), shape (B, 6, NZ, NZ)."""
        return self._scaled(dyn.region_matrices(self.structure, self.params, nu))

    def _exact_uncached(self, nu: float) -> np.ndarray:
        a = self.scaled_matrices(np.array([nu]))[0]
        result: np.ndarray = expm_batch(a * (self.dt_s * dyn.TIME_SCALE))
        return result

    def _exact_cache(self, nu: float) -> np.ndarray:
        """exp(A_r(N_u) h) for one N_u, cached (at most 256 values, oldest out)."""
        phi = self._exact.get(nu)
        if phi is None:
            phi = remember(self._exact, nu, self._exact_uncached(nu), 256)
        return phi

    def transition_table(self) -> np.ndarray:
        """The tabulated one-sample transition matrices (read-only; ≈ 3 MB, ≈ 26 ms to build), to hand
        to :meth:`use_table` of a simulator of the same parameters and sample period elsewhere."""
        view = self._table().view()
        view.setflags(write=False)
        result: np.ndarray = view
        return result

    def use_table(self, table: np.ndarray) -> None:
        """Take a table built by :meth:`transition_table` of an equal simulator (e.g. in another
        process); raises ParameterError if its shape does not match."""
        shape = (self._ngrid, dyn.N_REGIONS, dyn.NZ, dyn.NZ)
        if self._handle is not None:
            raise ParameterError("the simulator's table is in use already")
        if not (isinstance(table, np.ndarray) and table.shape == shape and table.dtype == np.float64):
            raise ParameterError(f"transition table of shape {getattr(table, 'shape', None)}, expected {shape}")
        # the compiled kernels take a writable array: a read-only view (this process) is copied
        self._phi_table = np.ascontiguousarray(table) if table.flags.writeable else np.array(table, order="C")

    def _table(self) -> np.ndarray:
        if self._phi_table is None:
            grid = self._nu0 + self._dnu * np.arange(self._ngrid)
            self._phi_table = expm_batch(self.scaled_matrices(grid) * (self.dt_s * dyn.TIME_SCALE))
        return self._phi_table

    def kernel_handle(self) -> KernelHandle:
        """The compiled model, automaton, transition table and sample period, for compiled callers
        (the candidates' N_u must be within :attr:`nu_range`, their L_h > 0). Built once."""
        if self._handle is None:
            lo, hi = self.nu_range
            self._handle = KernelHandle(self._model, self.automaton, self._table(), float(self.dt_s * dyn.TIME_SCALE),
                                        float(lo), float(hi))
        return self._handle

    def transition_matrices(self, nu: np.ndarray | float, exact: bool = False) -> np.ndarray:
        """One-sample transition matrices exp(A_r h), shape (B, 6, NZ, NZ), scaled units."""
        src, idx, w = self._phi_source(self.check_nu(nu), exact)
        result: np.ndarray = np.einsum("bq,bqrij->brij", w, src[idx])
        return result

    def _phi_source(self, nu: np.ndarray, exact: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if exact:
            uniq, inv = np.unique(nu, return_inverse=True)
            src = np.stack([self._exact_cache(float(v)) for v in uniq])
            idx = np.zeros((nu.size, 4), dtype=np.int64)
            idx[:, 0] = inv.ravel()
            w = np.zeros((nu.size, 4))
            w[:, 0] = 1.0
            return src, idx, w
        idx, w = kernel.lagrange_stencil(nu, self._nu0, self._dnu)
        return self._table(), idx, w

    def _times(self, n: int) -> np.ndarray:
        """Sample times 0, dt, ... (s), cached per length (read-only)."""
        t = self._t_cache.get(n)
        if t is None:
            t = np.arange(n) * self.dt_s
            t.setflags(write=False)
            remember(self._t_cache, n, t, 64)      # bounded: every trace length seen would stay otherwise
        return t

    @property
    def nu_range(self) -> tuple[float, float]:
        """N_u values (N/V) the simulator accepts: Table 1's range widened by ``NU_EXTRAPOLATION_N_PER_V``."""
        return self.params.psa.simulation_nu_range

    def check_nu(self, nu: np.ndarray | float) -> np.ndarray:
        """Validate N_u values (N/V) against :attr:`nu_range`; returns a 1-D float array."""
        return check_nu_in(np.atleast_1d(np.asarray(nu, dtype=float)), *self.nu_range)

    # ---- simulation -----------------------------------------------------------------------
    def simulate(self, current_a: np.ndarray, nu_n_per_v: np.ndarray | float, lh_m: np.ndarray | float,
                 f_open_n: np.ndarray | float | None = None, exact: bool = False) -> BatchResult:
        """Simulate candidates (N_u, L_h, F_open), broadcast to a batch, for the sampled current.

        ``current_a`` holds the current at t = 0, dt, 2 dt, ... (A); it is linear in between.
        Candidates whose initial state is infeasible get ``success=False`` and NaN outputs.
        """
        cur = _current(current_a)
        if f_open_n is None:
            f_open_n = self.params.valve.f_open_n
        nu = np.ascontiguousarray(nu_n_per_v, dtype=float).ravel()
        lh = np.ascontiguousarray(lh_m, dtype=float).ravel()
        fo = np.ascontiguousarray(f_open_n, dtype=float).ravel()
        nb = max(nu.size, lh.size, fo.size)
        if nu.size != nb or lh.size != nb or fo.size != nb:
            try:
                nu, lh, fo = (a if a.size == nb else np.full(nb, a[0]) if a.size == 1 else
                              np.ascontiguousarray(np.broadcast_to(a, (nb,))) for a in (nu, lh, fo))
            except ValueError:
                raise ParameterError(f"candidate arrays of sizes {nu.size}, {lh.size}, {fo.size} "
                                     "do not broadcast") from None
        self._check_inputs(cur, nu, lh, fo)
        n = cur.size
        if exact:
            src, idx, w = self._phi_source(nu, True)
        else:
            src, idx, w = self._table(), self._no_idx, self._no_w
        # starts at rest and pre-compressed starts (L_h <= 0) alike, infeasible ones marked, in the kernel
        u, s3, s4, mode, tc, to, status, success = kernel.run_batch(
            self._model, self.automaton, src, not exact, idx, w, nu, lh, fo, cur, self.dt_s * dyn.TIME_SCALE)
        return BatchResult(t_s=self._times(n), current_a=cur, nu_n_per_v=nu, lh_m=lh, f_open_n=fo, voltage_v=u,
                           s3_m=s3, s4_m=s4, mode=mode, t_contact_s=tc, t_open_s=to, success=success, status=status)

    def valve_prediction(self, current_a: np.ndarray, nu_n_per_v: float, lh_m: float, f_open_n: float,
                         window_s: tuple[float, float] = PLATEAU_WINDOW_S) -> tuple[float, float, float]:
        """Contact time, opening time (s) and mean plunger stroke over ``window_s`` (m) of one candidate:
        the numbers :meth:`simulate` and :meth:`BatchResult.plateau_stroke_m` give (to rounding), without
        building the trajectories in Python (the per-injection valve prediction)."""
        cur = _current(current_a)
        nu, lh, fo = np.array([nu_n_per_v], dtype=float), np.array([lh_m], dtype=float), np.array([f_open_n], dtype=float)
        key = (cur.size, (float(window_s[0]), float(window_s[1])))
        ks = self._plateau.get(key)
        if ks is None:
            found = plateau_samples(self._times(cur.size), window_s)
            ks = remember(self._plateau, key, found if found is not None else (0, 0), 64)
        k0, k1 = ks
        h = self.kernel_handle()
        # the argument types are fixed here (_VALVE_PREDICTION is a DirectCall): float64 arrays, floats, ints
        code, tc, to, stroke = _VALVE_PREDICTION(h.model, h.automaton, h.table, nu, lh, fo, cur, h.h_us,
                                                 int(k0), int(k1), h.nu_lo, h.nu_hi)
        if code != kernel.INPUTS_OK:      # the inputs are checked in the same call: raise as _check_inputs does
            self._check_inputs(cur, nu, lh, fo)
        return float(tc), float(to), float(stroke)

    def _check_inputs(self, cur: np.ndarray, nu: np.ndarray, lh: np.ndarray, fo: np.ndarray) -> int:
        """Raise ParameterError for a non-finite current, an N_u outside the range, a non-finite L_h
        or a bad F_open; else the number of candidates with L_h <= 0."""
        code, n_neg = kernel.check_inputs(cur, nu, lh, fo, *self.nu_range)
        if code == kernel.BAD_CURRENT:
            raise ParameterError(BAD_CURRENT_TEXT)
        if code == kernel.BAD_NU:
            self.check_nu(nu)   # raises with the offending value
        if code == kernel.BAD_LH_FOPEN:
            raise ParameterError("L_h (m) and F_open (N >= 0) must be finite")
        return int(n_neg)

    def _columns_share_free_run(self) -> bool:
        """Whether grid points of one N_u run the same free trajectory until contact: the free
        region's transition rows do not read L_h, and its guards do not read the current (whose
        state entry the kernel sets at each sample). True for the model of eq. 27; checked, not assumed."""
        if self._free_shared is None:
            phi = self._table()
            self._free_shared = bool(np.all(phi[:, 0, :dyn.NX, dyn.ZL] == 0.0)
                                     and np.all(self.automaton.guards[0][:, [dyn.ZI, dyn.ZID]] == 0.0))
        return self._free_shared

    def grid_voltages(self, current_a: np.ndarray, nu_n_per_v: np.ndarray, lh_m: np.ndarray,
                      f_open_n: float) -> tuple[np.ndarray, np.ndarray]:
        """Voltages (B, N) in V and success (B,) of a grid of candidates: what :meth:`simulate` gives
        (bit for bit; NaN rows where not successful), faster when several points share an N_u.

        Points with L_h > 0 are grouped by N_u: each column's free trajectory is simulated once
        and each point continues from the sample of its own contact (:func:`kernel.grid_voltages`).
        Points with L_h <= 0 start pre-compressed and are simulated whole.
        """
        cur = _current(current_a)
        nu = np.ascontiguousarray(nu_n_per_v, dtype=float).ravel()
        lh = np.ascontiguousarray(lh_m, dtype=float).ravel()
        if nu.size != lh.size:
            raise ParameterError(f"grid of {nu.size} N_u and {lh.size} L_h values")
        free = lh > 0.0
        col_nu, col = np.unique(nu[free], return_inverse=True)
        if not self._columns_share_free_run() or col_nu.size == free.sum():
            free[:] = False          # nothing to share
        rest = ~free
        if not rest.any():           # every point shares a free run: the kernel's arrays as they are
            u, ok = self._shared_free_runs(cur, col_nu, col, lh, f_open_n)
        else:
            u = np.full((nu.size, cur.size), np.nan)
            ok = np.zeros(nu.size, dtype=bool)
            res = self.simulate(cur, nu[rest], lh[rest], f_open_n)
            u[rest], ok[rest] = res.voltage_v, res.success
            if free.any():
                u[free], ok[free] = self._shared_free_runs(cur, col_nu, col, lh[free], f_open_n)
        u[~ok] = np.nan
        return u, ok

    def _shared_free_runs(self, cur: np.ndarray, col_nu: np.ndarray, col: np.ndarray, lh: np.ndarray,
                          f_open_n: float) -> tuple[np.ndarray, np.ndarray]:
        """:func:`kernel.grid_voltages` of points with L_h > 0 (m) in the N_u columns ``col_nu[col]`` (N/V)."""
        self._check_inputs(cur, col_nu, lh, np.full(lh.size, float(f_open_n)))
        h = self.kernel_handle()
        return kernel.grid_voltages(h.model, h.automaton, h.table, col_nu, col.astype(np.int64).ravel(), lh,
                                    float(f_open_n), cur, h.h_us, FREE_RUN_LH_M)
