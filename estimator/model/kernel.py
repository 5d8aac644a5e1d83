"""Compiled inner loop of the fast hybrid simulator (numba; scaled units, see dynamics.Z_SCALE).

Each candidate is advanced sample by sample with the exact transition matrix of its current
affine region. When a guard changes sign inside a sample, the exact flow ``exp(A sigma) z`` over
the sample's rest is expanded once in its Taylor series (exact to machine precision for
``|A| sigma < 1``); along it the guard is a scalar polynomial in time, whose root is the crossing
instant. The reset map is applied there, and the rest of the sample is integrated in the new
region. Everything here works on plain arrays: no Python objects.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from estimator._compiled import njit
from estimator.model.automaton import Automaton, apply_reset, dot, guard_value, in_contact, rearmed
from estimator.model.dynamics import (
    MODE_OPEN,
    NX,
    NZ,
    S3,
    S4,
    STATUS_EVENT_CAP,
    STATUS_INFEASIBLE,
    STATUS_OK,
    V4,
    Z1,
    ZF,
    ZI,
    ZID,
    ZL,
    coupling_jit,
    damping_jit,
    output_row_into,
    precompressed_starts,
)
from estimator.model.hysteresis import play_sum_into
from estimator.units import M_PER_UM, S_PER_US

MAX_EVENTS_PER_SAMPLE = 12
# the sample step in simulate_kernel is written out for these nine physical states, the plunger last
assert NX == 9 and (S4, V4) == (7, 8), "simulate_kernel's written-out step expects NX = 9, S4 = 7, V4 = 8"
LOCATE_MARGIN = 1e-7      # a located event is taken this fraction of the interval past the root
MAX_TAYLOR_TERMS = 40     # of exp(A sigma) z with |A| sigma < 1: far more than the ~12 that reach 1e-17
INPUTS_OK, BAD_CURRENT, BAD_NU, BAD_LH_FOPEN = 0, 1, 2, 3   # codes of check_inputs


class KernelModel(NamedTuple):
    """The N_u-independent numbers of one parameter set, in the kernel's scaled units (per µs).

    The table of transition matrices is passed beside it: the exact mode replaces it per call.
    """

    nu0: float              # N/V, first N_u of the interpolation table
    dnu: float              # N/V, its step
    a_const: np.ndarray     # (6, NZ, NZ) region matrices without the N_u terms
    a_coup: np.ndarray      # (6, NZ, NZ) multiplies k_s / N_u
    a_damp: np.ndarray      # (6, NZ, NZ) multiplies R_b N_u^2
    ks: float               # k_s in N/m
    rb: float               # R_b in V^2 s/(m N)
    r0a: float              # R_0a in Ohm
    r0b: float              # R_0b in V/N
    z_scale: np.ndarray     # (NZ,) dynamics.Z_SCALE
    springs: np.ndarray     # (6,) dynamics.spring_constants (SI): the static pre-compression of L_h <= 0
    a_pattern: np.ndarray   # (6, ZI + 1, NZ + 2) uint64: the non-zero columns of the region matrices (sparsity)
    # the hysteresis element (estimator.model.hysteresis), added to the voltage after a simulation;
    # with it, r0a is 0 (the element replaces R(N_u) I)
    hys_on: bool
    hys_thr: np.ndarray     # (M,) play half-widths in µC
    hys_w: np.ndarray       # (M,) their weights in V/µC
    hys_rs: float           # series resistance in Ohm
    hys_nu_ref: float       # N/V where the element's temperature scale is 1


@njit(cache=True, nogil=True, _nrt=False)
def _taylor(a: np.ndarray, pat: np.ndarray, z: np.ndarray, sigma: float, c: np.ndarray) -> int:
    """The Taylor series of exp(a sigma) z (a: (NZ, NZ) per time unit, |a| sigma < 1): row k of ``c``
    holds (a sigma)^k z / k!, k = 0 .. K - 1, until a term is below 1e-17 of the state; returns K.

    Rows ZID.. of ``a`` are zero (current slope and constants do not change) and row ZI only reads
    ZID, so only the first ZI + 1 entries of a term are non-zero after the first (the rest of the
    state is constant): the series works on those, and on the non-zero entries of each row of ``a``
    only (``pat``, :func:`sparsity`; in index order, so the sums are the dense ones). The state at
    u sigma (0 <= u <= 1) is the polynomial sum_k c[k] u^k (:func:`_state_at`), a guard g along it the
    scalar polynomial sum_k (g . c[k]) u^k (:func:`_locate`)."""
    m = ZI + 1
    size = 0.0
    for i in range(NZ):
        size = max(size, abs(z[i]))
    for i in range(m):
        c[0, i] = z[i]
    big = 0.0
    for i in range(m):
        s = 0.0
        for q in range(pat[i, 0]):
            j = pat[i, 2 + q]
            s += a[i, j] * z[j]
        c[1, i] = sigma * s
        big = max(big, abs(c[1, i]))
    k = 2
    while big > 1e-17 * size and k < MAX_TAYLOR_TERMS:
        f = sigma / k
        big = 0.0
        for i in range(m):
            s = 0.0
            for q in range(pat[i, 1]):
                j = pat[i, 2 + q]
                s += a[i, j] * c[k - 1, j]
            c[k, i] = f * s
            big = max(big, abs(c[k, i]))
        k += 1
    return k


@njit(cache=True, nogil=True)
def sparsity(a_const: np.ndarray, a_coup: np.ndarray, a_damp: np.ndarray) -> np.ndarray:
    """Per region, per row i < ZI + 1 of the continuous matrix: ``[n, n_m, j_1 .. j_n]``, the columns
    that can be non-zero (in a_const, a_coup or a_damp) in order, n_m of them below ZI + 1
    (:attr:`KernelModel.a_pattern`)."""
    nreg = a_const.shape[0]
    m = ZI + 1
    pat = np.zeros((nreg, m, NZ + 2), dtype=np.uint64)   # unsigned: no wraparound test when indexing
    for r in range(nreg):
        for i in range(m):
            for j in range(NZ):
                if a_const[r, i, j] != 0.0 or a_coup[r, i, j] != 0.0 or a_damp[r, i, j] != 0.0:
                    pat[r, i, 2 + pat[r, i, 0]] = j
                    pat[r, i, 0] += 1
                    if j < m:
                        pat[r, i, 1] += 1
    return pat


@njit(cache=True, nogil=True, _nrt=False)
def _flow(amat: np.ndarray, pattern: np.ndarray, r: int, z: np.ndarray, sigma: float, out: np.ndarray, terms: np.ndarray) -> None:
    """out = exp(a * sigma) @ z for region r's continuous matrix a = ``amat[r]`` (per time unit,
    |a| sigma < 1) and its pattern ``pattern[r]``: the Taylor series of :func:`_taylor`, its terms
    kept in ``terms``, summed by :func:`_state_at`. Takes the whole arrays and r, not the region's
    slices: a slice taken in the caller costs two reference-count calls (the note above :func:`_guard_ends`)."""
    _state_at(terms, _taylor(amat[r], pattern[r], z, sigma, terms), z, 1.0, out)


@njit(cache=True, nogil=True, _nrt=False)
def _state_at(c: np.ndarray, nterms: int, z: np.ndarray, u: float, out: np.ndarray) -> None:
    """out = the state at the fraction u of the interval of :func:`_taylor`'s terms ``c`` (Horner)."""
    m = ZI + 1
    # Horner per entry, the entries advanced together (term by term): each entry's operations and
    # their order are a row-by-row Horner's, but the m chains are independent and overlap
    for i in range(m):
        out[i] = c[nterms - 1, i]
    for k in range(nterms - 2, -1, -1):
        for i in range(m):
            out[i] = out[i] * u + c[k, i]
    for i in range(m, NZ):
        out[i] = z[i]


@njit(cache=True, nogil=True, _nrt=False)
def _locate(c: np.ndarray, nterms: int, g: np.ndarray, z: np.ndarray, rem: float, out: np.ndarray, poly: np.ndarray) -> float:
    """Crossing time of the guard g in (0, rem] along the flow whose Taylor terms over rem are ``c``
    (:func:`_taylor`), the guard being <= 0 at the start and > 0 at the end of the interval.

    The guard along the flow is a scalar polynomial in u = t / rem: its root is found by Newton's
    method kept inside the bracket (bisection when a step leaves it) to 1e-13 of the interval, and
    the event is taken ``LOCATE_MARGIN`` of the interval past it, where the guard is positive.
    Returns that time, with the state there in ``out`` (``poly``: scratch of MAX_TAYLOR_TERMS).
    """
    m = ZI + 1
    p = poly
    p[0] = dot(g, z)
    # p[k] = g . c[k], each summed over i in order; the terms advanced together (independent chains)
    for k in range(1, nterms):
        p[k] = 0.0
    for i in range(m):
        gi = g[i]
        for k in range(1, nterms):
            p[k] += gi * c[k, i]
    lo, hi = 0.0, 1.0
    p1 = 0.0
    for k in range(nterms):
        p1 += p[k]
    u = -p[0] / (p1 - p[0]) if p1 > p[0] and p[0] <= 0.0 else 0.5
    if not (u > 0.0 and u < 1.0):
        u = 0.5
    if p[0] > 0.0:            # already positive (seated guard pair): the earliest time after the start
        hi = 1e-7
    else:
        for _ in range(100):
            pv = p[nterms - 1]
            dp = 0.0
            for k in range(nterms - 2, -1, -1):
                dp = dp * u + pv
                pv = pv * u + p[k]
            if pv > 0.0:
                hi = u
            else:
                lo = u
            if hi - lo <= 1e-13:
                break
            un = u - pv / dp if dp != 0.0 else 0.5 * (lo + hi)
            if abs(un - u) <= 1e-14:
                un = u + 1e-13 if pv <= 0.0 else u - 1e-13   # converged: step across the root
            if not (un > lo and un < hi):
                un = 0.5 * (lo + hi)
            u = un
    # a little past the root (1e-7 of the interval, the tolerance of the regula falsi this replaced):
    # a state exactly on the boundary lets rounding send a grazing trajectory back and forth
    u = min(hi + LOCATE_MARGIN, 1.0)
    _state_at(c, nterms, z, u, out)
    for _ in range(8):        # the state's own guard value decides (rounding of the polynomial)
        if dot(g, out) > 0.0 or u >= 1.0:
            break
        u = min(u + 1e-12, 1.0)
        _state_at(c, nterms, z, u, out)
    return u * rem


@njit(cache=True, nogil=True, _nrt=False)
def _region_phi(src: np.ndarray, idx: np.ndarray, w: np.ndarray, b: int, r: int, out: np.ndarray) -> None:
    """Rows 0..NX-1 of the transition matrix of region r for candidate b: the table rows ``idx[b]``
    weighted by ``w[b]``. Depends on N_u only: candidates with the same rows and weights share it."""
    i0, i1, i2, i3 = idx[b, 0], idx[b, 1], idx[b, 2], idx[b, 3]
    w0, w1, w2, w3 = w[b, 0], w[b, 1], w[b, 2], w[b, 3]
    for i in range(NX):
        for j in range(NZ):
            out[r, i, j] = (w0 * src[i0, r, i, j] + w1 * src[i1, r, i, j]
                            + w2 * src[i2, r, i, j] + w3 * src[i3, r, i, j])


@njit(cache=True, nogil=True, _nrt=False)
def _region_const(phi: np.ndarray, r: int, z: np.ndarray, const: np.ndarray) -> None:
    """``const[r]``: the contribution of the constant inputs L_h, F_open, 1 (columns ZID + 1 ..) of
    the state ``z`` through region r's transition rows (per candidate: L_h is its own)."""
    for i in range(NX):
        c = 0.0
        for j in range(ZID + 1, NZ):
            c += phi[r, i, j] * z[j]
        const[r, i] = c


@njit(cache=True, nogil=True, _nrt=False)
def _region_a(model: KernelModel, cpl: float, dmp: float, r: int, out: np.ndarray) -> None:
    """``out[r]`` = the continuous matrix of region r: a_const + cpl a_coup + dmp a_damp (scaled, per µs)."""
    for i in range(NZ):
        for j in range(NZ):
            out[r, i, j] = model.a_const[r, i, j] + cpl * model.a_coup[r, i, j] + dmp * model.a_damp[r, i, j]


class Candidates(NamedTuple):
    """Per-candidate inputs of :func:`simulate_kernel` (B candidates, scaled units)."""

    idx: np.ndarray       # (B, 4) int64: table rows of the N_u interpolation
    w: np.ndarray         # (B, 4): their weights (one exact matrix: weight 1 on row idx[b, 0])
    cpl: np.ndarray       # (B,) k_s / N_u, the coupling factor of the continuous matrix
    dmp: np.ndarray       # (B,) R_b N_u^2, its damping factor
    z0: np.ndarray        # (B, NZ) initial augmented state
    region0: np.ndarray   # (B,) int64 initial region
    cout: np.ndarray      # (B, NZ) output rows, U = cout[b] @ z


class Trajectories(NamedTuple):
    """Outputs of :func:`simulate_kernel`, written in place (scaled units, times in µs)."""

    u: np.ndarray          # (B, N) voltage in V
    s3: np.ndarray         # (B, N) bottom plate in µm
    s4: np.ndarray         # (B, N) plunger in µm
    mode: np.ndarray       # (B, N) int8 automaton mode
    t_contact: np.ndarray  # (B,) first contact (NaN: none)
    t_open: np.ndarray     # (B,) first opening (NaN: none)
    status: np.ndarray     # (B,) int64 STATUS_*


# The per-sample code takes plain arrays: a call, or an array taken out of a named tuple, costs
# ~30 ns per sample, as much as the step itself; the step is written out in simulate_kernel.
#
# The functions of the event path (locating a crossing, the reset, the rest of a sample) are compiled
# without numba's reference counting (``_nrt=False``; they allocate nothing and keep no array): with
# it, every array they take or slice cost an atomic increment and decrement, ~26 calls per event and
# 8 per partial sample, 4,300 calls in one valve prediction (37 events); without, 81 -> 75 µs.

@njit(cache=True, nogil=True, inline="always")
def _guard_ends(guards: np.ndarray, open_seated: np.ndarray, open_index: np.ndarray, r: int, j: int, z: np.ndarray, zn: np.ndarray,
                seated: bool) -> tuple[float, float, bool]:
    """Guard j of region r at z and at zn: (g0, g1, spring_only). After a re-seat the opening
    guard is min(ordinary, spring-only); ``spring_only`` says that the spring-only row is the lower
    one at zn, the row to locate the crossing with."""
    g = guards[r, j]
    g0 = dot(g, z)
    g1 = dot(g, zn)
    spring_only = False
    if seated and j == open_index[r]:
        # lift-off from the seat needs both forces: min(ordinary, spring-only) > 0
        g0 = min(g0, dot(open_seated[r], z))
        gs1 = dot(open_seated[r], zn)
        if gs1 < g1:
            g1 = gs1
            spring_only = True
    return g0, g1, spring_only


@njit(cache=True, nogil=True, _nrt=False)
def _locate_first(guards: np.ndarray, open_seated: np.ndarray, open_index: np.ndarray, target: np.ndarray, amat: np.ndarray, pat: np.ndarray, r: int, z: np.ndarray,
                  zn: np.ndarray, rem: float, seated: bool, zt: np.ndarray, zb: np.ndarray, terms: np.ndarray, poly: np.ndarray) -> tuple[int, float]:
    """The guard of region r that fires first between z and zn (``rem`` µs later; ``amat[r]`` the
    region's continuous matrix, ``pat[r]`` its pattern). Returns (j, s): the guard (-1: none) and the time after z at which
    it is positive; the state there is left in zb. Called only when some guard crosses.
    """
    best = -1
    best_s = rem
    nterms = 0
    for j in range(3):
        if target[r, j] < 0:
            continue
        g0, g1, spring_only = _guard_ends(guards, open_seated, open_index, r, j, z, zn, seated)
        if g0 <= 0.0 and g1 > 0.0:
            g = open_seated[r] if spring_only else guards[r, j]
            if nterms == 0:     # the flow's terms, shared by the guards that cross in this interval
                nterms = _taylor(amat[r], pat[r], z, rem, terms)
            s = _locate(terms, nterms, g, z, rem, zt, poly)
            if s < best_s or best < 0:
                best_s = s
                best = j
                for i in range(NZ):
                    zb[i] = zt[i]
    return best, best_s


@njit(cache=True, nogil=True, _nrt=False)
def _transition(guards: np.ndarray, target: np.ndarray, reset: np.ndarray, open_index: np.ndarray, open_seated: np.ndarray, region_mode: np.ndarray, r: int,
                j: int, z: np.ndarray, seated: bool, nev: int, t_ev: float, b: int, t_contact: np.ndarray,
                t_open: np.ndarray) -> tuple[int, bool, int]:
    """Take transition j of region r at z (time t_ev µs), then any already enabled at the new state.

    Records the first contact and opening times of candidate b in ``t_contact``, ``t_open``; returns
    (region, seated, events). Takes the automaton's arrays, not the tuple (see :func:`simulate_kernel`).
    """
    while j >= 0 and nev < MAX_EVENTS_PER_SAMPLE:
        seated = apply_reset(z, reset[r, j], seated)
        r = target[r, j]
        nev += 1
        md = region_mode[r]
        if in_contact(md) and np.isnan(t_contact[b]):
            t_contact[b] = t_ev
        if md == MODE_OPEN and np.isnan(t_open[b]):
            t_open[b] = t_ev
        j = -1
        for jj in range(3):
            if target[r, jj] < 0:
                continue
            if guard_value(guards, open_seated, open_index, r, jj, z, seated) > 0.0:
                j = jj
                break
    return r, seated, nev


@njit(cache=True, nogil=True)
def _nonzeros(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``rows`` (R, NZ): the indices of its non-zero entries in order (R, NZ) and their count."""
    nr = rows.shape[0]
    idx = np.zeros((nr, NZ), dtype=np.uint64)     # unsigned: indexing with them needs no wraparound test
    cnt = np.zeros(nr, dtype=np.int64)
    for a in range(nr):
        for i in range(NZ):
            if rows[a, i] != 0.0:
                idx[a, cnt[a]] = i
                cnt[a] += 1
    return idx, cnt


@njit(cache=True, nogil=True, fastmath={"contract"})
def simulate_kernel(src: np.ndarray, model: KernelModel, aut: Automaton, cand: Candidates, cur: np.ndarray, h: float,
                    out: Trajectories, k0: np.ndarray, zrec: np.ndarray) -> None:
    """Advance B candidates over the samples of ``cur`` (all arrays in scaled units, time in µs).

    Candidate b starts at sample ``k0[b]`` in the state ``cand.z0[b]`` (its outputs before that
    sample are left as they are); the first ``zrec.shape[0]`` candidates record the state at the
    start of every sample in ``zrec[b, k]`` (see :func:`grid_voltages`).

    The transition matrix of region r for candidate b is ``sum_q w[b,q] src[idx[b,q], r]``
    (a 4-point interpolation in N_u, or one exact matrix with weight 1); it is formed the first
    time the candidate enters the region, and kept for the next candidate if that one has the same
    N_u (a grid column: ≈ 0.3 µs per region and point saved). The continuous matrix, needed only to
    locate events, is ``a_const[r] + cpl[b] a_coup[r] + dmp[b] a_damp[r]`` (kept the same way).
    Functions called on the event path take arrays, not the named tuples: with the tuples passed
    (``_transition`` and the continuous matrix's lookup), the valve prediction took 6–11 % longer. ``aut`` is the automaton
    (:class:`automaton.Automaton`), ``cand`` the candidates, ``cur`` (N,) the current in A. Per
    sample: the step (written out), then, if a guard crosses, :func:`_locate_first` and :func:`_transition`
    and the rest of the sample from there. Multiply-adds may be fused (``fastmath={"contract"}``, the only
    relaxation: no reassociation, no finite-math assumptions): each product-sum of the step is then
    rounded once instead of twice, 4-5 % faster (valve prediction 76 -> 72 µs) and different from
    the unfused sums in the last bits only. The :class:`Trajectories` ``out`` are written in place;
    t_contact/t_open in µs (NaN: none).
    """
    nb = cand.z0.shape[0]
    n = cur.shape[0]
    nreg = model.a_const.shape[0]
    guards, target, reset, open_index, open_seated, region_mode = aut
    cout, out_u, out_s3, out_s4, out_mode = cand.cout, out.u, out.s3, out.s4, out.mode
    t_contact, t_open = out.t_contact, out.t_open
    z = np.empty(NZ)
    zn = np.empty(NZ)
    zt = np.empty(NZ)
    zb = np.empty(NZ)
    phi = np.empty((nreg, NX, NZ))
    const = np.empty((nreg, NX))
    have = np.zeros(nreg, dtype=np.bool_)     # phi[r] formed (for this candidate's N_u)
    have_c = np.zeros(nreg, dtype=np.bool_)   # const[r] formed (for this candidate)
    amat = np.empty((nreg, NZ, NZ))
    have_a = np.zeros(nreg, dtype=np.bool_)
    terms = np.empty((MAX_TAYLOR_TERMS, ZI + 1))
    poly = np.empty(MAX_TAYLOR_TERMS)
    nrec = zrec.shape[0]
    # the guards and output rows read few states: per sample they are summed over their non-zero
    # entries only, in index order (the dense sum's order; the skipped terms are exact zeros)
    g_idx, g_cnt = _nonzeros(guards.reshape((nreg * 3, NZ)))
    s_idx, s_cnt = _nonzeros(open_seated)
    c_idx, c_cnt = _nonzeros(cout)
    pattern = model.a_pattern
    idx, w, cpl, dmp = cand.idx, cand.w, cand.cpl, cand.dmp
    for b in range(nb):
        # a candidate with the previous one's N_u (the points of a grid column) keeps its matrices
        if not (b > 0 and idx[b, 0] == idx[b - 1, 0] and idx[b, 1] == idx[b - 1, 1] and idx[b, 2] == idx[b - 1, 2]
                and idx[b, 3] == idx[b - 1, 3] and w[b, 0] == w[b - 1, 0] and w[b, 1] == w[b - 1, 1]
                and w[b, 2] == w[b - 1, 2] and w[b, 3] == w[b - 1, 3]):
            have[:] = False
        if not (b > 0 and cpl[b] == cpl[b - 1] and dmp[b] == dmp[b - 1]):
            have_a[:] = False
        have_c[:] = False
        seated = False
        for i in range(NZ):
            z[i] = cand.z0[b, i]
        r = cand.region0[b]
        out.t_contact[b] = np.nan
        out.t_open[b] = np.nan
        out.status[b] = STATUS_OK
        if in_contact(region_mode[r]):
            out.t_contact[b] = 0.0
        rec = b < nrec
        z[ZI] = cur[k0[b]]
        for k in range(k0[b], n):
            if rec:
                for i in range(NZ):
                    zrec[b, k, i] = z[i]
            u = 0.0
            for q in range(c_cnt[b]):
                u += cout[b, c_idx[b, q]] * z[c_idx[b, q]]
            out_u[b, k] = u
            out_s3[b, k] = z[S3]
            out_s4[b, k] = z[S4]
            out_mode[b, k] = region_mode[r]
            if k == n - 1:
                break
            z[ZI] = cur[k]
            z[ZID] = (cur[k + 1] - cur[k]) / h
            rem = h
            nev = 0
            while True:
                if rem == h:
                    if not have_c[r]:
                        if not have[r]:
                            _region_phi(src, idx, w, b, r, phi)
                            have[r] = True
                        _region_const(phi, r, z, const)
                        have_c[r] = True
                    # one full sample with the transition rows phi[r] and the constant part const[r]. The NX
                    # rows are summed in NX local accumulators, each in the order const, I, dI/dt, z_0 .. z_nx-1
                    # (a row-by-row loop's order: the same to the bit), so the processor overlaps the sums instead
                    # of waiting on one chain of additions, and no array is passed to a helper (a call or an inlined
                    # function taking arrays cost reference counting every sample): 7-12 % per simulation. The
                    # valve plunger states (S4, V4) are held at rest while the valve is closed (nx = S4).
                    nx = NX if region_mode[r] >= MODE_OPEN else S4
                    zi = z[ZI]
                    zd = z[ZID]
                    s0 = const[r, 0] + phi[r, 0, ZI] * zi + phi[r, 0, ZID] * zd
                    s1 = const[r, 1] + phi[r, 1, ZI] * zi + phi[r, 1, ZID] * zd
                    s2 = const[r, 2] + phi[r, 2, ZI] * zi + phi[r, 2, ZID] * zd
                    s3 = const[r, 3] + phi[r, 3, ZI] * zi + phi[r, 3, ZID] * zd
                    s4 = const[r, 4] + phi[r, 4, ZI] * zi + phi[r, 4, ZID] * zd
                    s5 = const[r, 5] + phi[r, 5, ZI] * zi + phi[r, 5, ZID] * zd
                    s6 = const[r, 6] + phi[r, 6, ZI] * zi + phi[r, 6, ZID] * zd
                    s7 = const[r, 7] + phi[r, 7, ZI] * zi + phi[r, 7, ZID] * zd
                    s8 = const[r, 8] + phi[r, 8, ZI] * zi + phi[r, 8, ZID] * zd
                    for j in range(nx):
                        zj = z[j]
                        s0 += phi[r, 0, j] * zj
                        s1 += phi[r, 1, j] * zj
                        s2 += phi[r, 2, j] * zj
                        s3 += phi[r, 3, j] * zj
                        s4 += phi[r, 4, j] * zj
                        s5 += phi[r, 5, j] * zj
                        s6 += phi[r, 6, j] * zj
                        s7 += phi[r, 7, j] * zj
                        s8 += phi[r, 8, j] * zj
                    for i in range(NZ):
                        zn[i] = z[i]
                    zn[0] = s0
                    zn[1] = s1
                    zn[2] = s2
                    zn[3] = s3
                    zn[4] = s4
                    zn[5] = s5
                    zn[6] = s6
                    if nx == NX:
                        zn[S4] = s7
                        zn[V4] = s8
                    zn[ZI] = zi + h * zd
                else:   # the rest of a sample after an event
                    if not have_a[r]:    # the region's continuous matrix, formed at the candidate's first event in it
                        _region_a(model, cpl[b], dmp[b], r, amat)
                        have_a[r] = True
                    _flow(amat, pattern, r, z, rem, zn, terms)
                # does a guard cross? automaton.guard_value at both ends, written out: as an inlined
                # call it made the whole simulation 35 % slower (speed-sim)
                crosses = False
                for j in range(3):
                    if target[r, j] < 0:
                        continue
                    rj = 3 * r + j
                    g0 = 0.0
                    g1 = 0.0
                    for q in range(g_cnt[rj]):
                        i = g_idx[rj, q]
                        g0 += guards[r, j, i] * z[i]
                        g1 += guards[r, j, i] * zn[i]
                    if seated and j == open_index[r]:
                        s0 = 0.0
                        s1 = 0.0
                        for q in range(s_cnt[r]):
                            i = s_idx[r, q]
                            s0 += open_seated[r, i] * z[i]
                            s1 += open_seated[r, i] * zn[i]
                        g0 = min(g0, s0)
                        g1 = min(g1, s1)
                    if g0 <= 0.0 and g1 > 0.0:
                        crosses = True
                if not crosses:
                    for i in range(NZ):
                        z[i] = zn[i]
                    break
                if nev >= MAX_EVENTS_PER_SAMPLE:
                    out.status[b] = STATUS_EVENT_CAP
                    for i in range(NZ):
                        z[i] = zn[i]
                    break
                if not have_a[r]:
                    _region_a(model, cpl[b], dmp[b], r, amat)
                    have_a[r] = True
                best, best_s = _locate_first(guards, open_seated, open_index, target, amat, pattern, r, z, zn,
                                             rem, seated, zt, zb, terms, poly)
                for i in range(NZ):
                    z[i] = zb[i]
                t_ev = k * h + (h - rem) + best_s
                r, seated, nev = _transition(guards, target, reset, open_index, open_seated, region_mode, r, best, z,
                                             seated, nev, t_ev, b, t_contact, t_open)
                rem = rem - best_s
                if rem <= 1e-12 * h:
                    break
            z[ZI] = cur[k + 1]
            if seated:
                seated = rearmed(guards, open_index, r, z, seated)


@njit(cache=True, nogil=True)
def lagrange_stencil(nu: np.ndarray, nu0: float, dnu: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (B, 4) and weights (B, 4) of 4-point Lagrange interpolation on the grid nu0 + i*dnu."""
    nb = nu.shape[0]
    idx = np.empty((nb, 4), dtype=np.int64)
    w = np.empty((nb, 4))
    for b in range(nb):
        t = (nu[b] - nu0) / dnu
        i = int(np.floor(t))
        f = t - i
        for q in range(4):
            idx[b, q] = i - 1 + q
        w[b, 0] = -f * (f - 1.0) * (f - 2.0) / 6.0
        w[b, 1] = (f + 1.0) * (f - 1.0) * (f - 2.0) / 2.0
        w[b, 2] = -(f + 1.0) * f * (f - 2.0) / 2.0
        w[b, 3] = (f + 1.0) * f * (f - 1.0) / 6.0
    return idx, w


@njit(cache=True, nogil=True)
def lti_foh_kernel(phi: np.ndarray, g0: np.ndarray, g1: np.ndarray, c: np.ndarray, d: float, cur: np.ndarray, h: float, out_y: np.ndarray,
                   out_x: np.ndarray) -> None:
    """x_{k+1} = phi x_k + g0 I_k + g1 (I_{k+1} - I_k)/h from x_0 = 0; y_k = c x_k + d I_k; out_x = x."""
    n = cur.shape[0]
    m = phi.shape[0]
    x = np.zeros(m)
    xn = np.empty(m)
    for k in range(n):
        y = d * cur[k]
        for i in range(m):
            y += c[i] * x[i]
            out_x[k, i] = x[i]
        out_y[k] = y
        if k == n - 1:
            break
        slope = (cur[k + 1] - cur[k]) / h
        for i in range(m):
            s = g0[i] * cur[k] + g1[i] * slope
            for j in range(m):
                s += phi[i, j] * x[j]
            xn[i] = s
        for i in range(m):
            x[i] = xn[i]


@njit(cache=True, nogil=True)
def _candidates(model: KernelModel, idx: np.ndarray, w: np.ndarray, nu: np.ndarray, lh: np.ndarray, fo: np.ndarray, z0_given: np.ndarray,
                region0: np.ndarray) -> Candidates:
    """The :class:`Candidates` of a batch: initial states, output rows and the N_u factors."""
    nb = nu.shape[0]
    d = model.z_scale
    z0 = np.zeros((nb, NZ))
    cout = np.zeros((nb, NZ))
    cpl = np.empty(nb)
    dmp = np.empty(nb)
    for b in range(nb):
        if np.isfinite(z0_given[b, 0]):
            for i in range(NZ):
                z0[b, i] = z0_given[b, i]
        else:
            z0[b, ZL] = lh[b] * d[ZL]
            z0[b, ZF] = fo[b]
            z0[b, Z1] = 1.0
        output_row_into(model.ks, model.r0a, model.r0b, nu[b], cout[b])
        for i in range(NZ):
            cout[b, i] /= d[i]
        cpl[b] = coupling_jit(model.ks, nu[b])
        dmp[b] = damping_jit(model.rb, nu[b])
    return Candidates(idx, w, cpl, dmp, z0, region0, cout)


@njit(cache=True, nogil=True)
def _add_element(model: KernelModel, cur: np.ndarray, h: float, nu: np.ndarray, u: np.ndarray) -> None:
    """Add the hysteresis element's voltage R_s I + s(N_u) H[Q] to the voltages ``u`` (B, N) of the
    candidates at ``nu`` (B,) driven by ``cur`` (N,) A with step ``h`` µs; nothing without the element."""
    if not model.hys_on:
        return
    n = cur.shape[0]
    hq = np.empty(n)
    play_sum_into(cur, h, model.hys_thr, model.hys_w, hq)
    for b in range(u.shape[0]):
        s = np.exp(-model.r0b * (nu[b] - model.hys_nu_ref))
        for k in range(n):
            u[b, k] += s * hq[k] + model.hys_rs * cur[k]


@njit(cache=True, nogil=True)
def run_batch(model: KernelModel, aut: Automaton, src: np.ndarray, stencil: bool, idx_in: np.ndarray, w_in: np.ndarray, nu: np.ndarray,
              lh: np.ndarray, fo: np.ndarray, cur: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One call for a whole batch: set up each candidate, interpolate its matrices, simulate.

    ``stencil``: interpolate the table ``src`` at ``nu`` (else ``idx_in``/``w_in`` select exact
    matrices). A candidate with L_h > 0 starts at rest; one with L_h <= 0 starts pre-compressed
    (the static equilibrium, :func:`dynamics.precompressed_starts`), and fails with
    ``STATUS_INFEASIBLE`` and NaN outputs where its valve would start open. Returns
    (u, s3, s4, mode, t_contact, t_open, status, success) with s3, s4 in m and times in s.
    """
    nb = nu.shape[0]
    n = cur.shape[0]
    if stencil:
        idx, w = lagrange_stencil(nu, model.nu0, model.dnu)
    else:
        idx, w = idx_in, w_in
    z0_given = np.full((nb, NZ), np.nan)
    region0 = np.zeros(nb, dtype=np.int64)
    feasible = precompressed_starts(model.springs, nu, lh, fo, model.z_scale, z0_given, region0)
    cand = _candidates(model, idx, w, nu, lh, fo, z0_given, region0)
    out = Trajectories(np.empty((nb, n)), np.empty((nb, n)), np.empty((nb, n)), np.empty((nb, n), dtype=np.int8),
                       np.empty(nb), np.empty(nb), np.empty(nb, dtype=np.int64))
    simulate_kernel(src, model, aut, cand, cur, h, out, np.zeros(nb, dtype=np.int64), np.empty((0, n, NZ)))
    u, s3, s4, mode, tc, to, status = out
    _add_element(model, cur, h, nu, u)
    success = np.empty(nb, dtype=np.bool_)
    for b in range(nb):
        if not feasible[b]:
            status[b] = STATUS_INFEASIBLE
            tc[b] = np.nan
            to[b] = np.nan
            for k in range(n):
                u[b, k] = np.nan
                s3[b, k] = np.nan
                s4[b, k] = np.nan
        for k in range(n):
            s3[b, k] *= M_PER_UM
            s4[b, k] *= M_PER_UM
        tc[b] *= S_PER_US
        to[b] *= S_PER_US
        success[b] = status[b] == STATUS_OK
    return u, s3, s4, mode, tc, to, status, success


@njit(cache=True, nogil=True)
def run_table(model: KernelModel, aut: Automaton, src: np.ndarray, nu: np.ndarray, lh: np.ndarray, fo: np.ndarray, cur: np.ndarray,
              h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`run_batch` with every candidate's N_u interpolated in the table ``src``."""
    out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] = run_batch(
        model, aut, src, True, np.zeros((1, 4), dtype=np.int64), np.zeros((1, 4)), nu, lh, fo, cur, h)
    return out


@njit(cache=True, nogil=True)
def valve_prediction(model: KernelModel, aut: Automaton, src: np.ndarray, nu: np.ndarray, lh: np.ndarray, fo: np.ndarray, cur: np.ndarray, h: float,
                     k0: int, k1: int, nu_min: float, nu_max: float) -> tuple[int, float, float, float]:
    """(code, contact time, opening time (s), mean plunger stroke (m) over samples k0 <= k < k1 (NaN if
    k0 >= k1)) of one candidate (``nu``, ``lh``, ``fo`` of size 1); ``code`` is
    :func:`check_inputs`' (nothing is simulated unless ``INPUTS_OK``)."""
    code, _ = check_inputs(cur, nu, lh, fo, nu_min, nu_max)
    if code != INPUTS_OK:
        return code, np.nan, np.nan, np.nan
    _, _, s4, _, tc, to, _, _ = run_table(model, aut, src, nu, lh, fo, cur, h)
    stroke = np.nan
    if k1 > k0:
        stroke = np.mean(s4[0, k0:k1])
    return code, tc[0], to[0], stroke


@njit(cache=True, nogil=True)
def check_inputs(cur: np.ndarray, nu: np.ndarray, lh: np.ndarray, fo: np.ndarray, nu_min: float, nu_max: float) -> tuple[int, int]:
    """``INPUTS_OK`` if all inputs are usable, else ``BAD_CURRENT``, ``BAD_NU`` or ``BAD_LH_FOPEN``;
    and the number of candidates with L_h <= 0 (which need their pre-compressed initial state)."""
    for k in range(cur.shape[0]):
        if not np.isfinite(cur[k]):
            return BAD_CURRENT, 0
    for b in range(nu.shape[0]):
        if not (np.isfinite(nu[b]) and nu_min <= nu[b] <= nu_max):
            return BAD_NU, 0
    n_neg = 0
    for b in range(lh.shape[0]):
        if not (np.isfinite(lh[b]) and np.isfinite(fo[b]) and fo[b] >= 0.0):
            return BAD_LH_FOPEN, 0
        if lh[b] <= 0.0:
            n_neg += 1
    return INPUTS_OK, n_neg


@njit(cache=True, nogil=True)
def grid_voltages(model: KernelModel, aut: Automaton, src: np.ndarray, col_nu: np.ndarray, col: np.ndarray, lh: np.ndarray, fo: float, cur: np.ndarray,
                  h: float, lh_free: float) -> tuple[np.ndarray, np.ndarray]:
    """Voltages (B, N) in V and success (B,) of grid points (N_u = ``col_nu[col[b]]``, L_h = ``lh[b]`` > 0 m).

    The points of one N_u column run the same free trajectory until contact: L_h only enters the
    contact guard (the free region's transition rows do not read it, checked by the caller). So
    each column is simulated once with L_h = ``lh_free`` (never reached), recording its state at
    every sample, and each point starts from the recorded state at the sample in which its own
    contact guard crosses, with its own L_h. The result is the one :func:`run_batch` gives, bit for
    bit, at the cost of the post-contact part plus one free run per column.
    """
    nc = col_nu.shape[0]
    nb = lh.shape[0]
    n = cur.shape[0]
    d = model.z_scale
    idx, w = lagrange_stencil(col_nu, model.nu0, model.dnu)
    cols = _candidates(model, idx, w, col_nu, np.full(nc, lh_free), np.full(nc, fo), np.full((nc, NZ), np.nan),
                       np.zeros(nc, dtype=np.int64))
    outc = Trajectories(np.empty((nc, n)), np.empty((nc, n)), np.empty((nc, n)), np.empty((nc, n), dtype=np.int8),
                        np.empty(nc), np.empty(nc), np.empty(nc, dtype=np.int64))
    zrec = np.empty((nc, n, NZ))
    simulate_kernel(src, model, aut, cols, cur, h, outc, np.zeros(nc, dtype=np.int64), zrec)
    u = np.empty((nb, n))
    k0 = np.zeros(nb, dtype=np.int64)
    z0 = np.full((nb, NZ), np.nan)
    gend = np.empty(3)
    guards, target = aut.guards, aut.target
    f_idx, f_cnt = _nonzeros(guards[0])      # the free region's guards, as simulate_kernel sums them
    for b in range(nb):
        c = col[b]
        if outc.status[c] != STATUS_OK or not np.isnan(outc.t_contact[c]):
            continue                      # the column left the free region: simulate the point whole
        # the first sample whose step crosses a guard of the free region, as simulate_kernel tests it:
        # each guard summed over its non-zero entries in index order, the recorded state with this
        # point's own L_h; a guard's value at a sample's end is the next sample's start value
        kc = n - 1
        zl_b = lh[b] * d[ZL]
        for j in range(3):
            gend[j] = 0.0
            if target[0, j] < 0:
                continue
            for q in range(f_cnt[j]):
                i = f_idx[j, q]
                gend[j] += guards[0, j, i] * (zl_b if i == ZL else zrec[c, 0, i])
        for k in range(n - 1):
            crosses = False
            for j in range(3):
                if target[0, j] < 0:
                    continue
                g0 = gend[j]
                g1 = 0.0
                for q in range(f_cnt[j]):
                    i = f_idx[j, q]
                    g1 += guards[0, j, i] * (zl_b if i == ZL else zrec[c, k + 1, i])
                gend[j] = g1
                if g0 <= 0.0 and g1 > 0.0:
                    crosses = True
            if crosses:
                kc = k
                break
        k0[b] = kc
        for i in range(NZ):
            z0[b, i] = zrec[c, kc, i]
        z0[b, ZL] = lh[b] * d[ZL]
        for k in range(kc):
            u[b, k] = outc.u[c, k]
    nu = np.empty(nb)
    for b in range(nb):
        nu[b] = col_nu[col[b]]
    idx, w = lagrange_stencil(nu, model.nu0, model.dnu)
    cand = _candidates(model, idx, w, nu, lh, np.full(nb, fo), z0, np.zeros(nb, dtype=np.int64))
    out = Trajectories(u, np.empty((nb, n)), np.empty((nb, n)), np.empty((nb, n), dtype=np.int8),
                       np.empty(nb), np.empty(nb), np.empty(nb, dtype=np.int64))
    simulate_kernel(src, model, aut, cand, cur, h, out, k0, np.empty((0, n, NZ)))
    _add_element(model, cur, h, nu, u)
    success = np.empty(nb, dtype=np.bool_)
    for b in range(nb):
        success[b] = out.status[b] == STATUS_OK
    return u, success
