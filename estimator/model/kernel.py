"""Compiled inner loop of the fast hybrid simulator (numba; scaled units, see dynamics.Z_SCALE).

Each candidate is advanced sample by sample with the exact transition matrix of its current
affine region. When a guard changes sign inside a sample, the crossing instant is located by
regula falsi (Illinois) on the exact flow ``exp(A sigma) z`` (a truncated Taylor series, exact to
machine precision for ``|A| sigma < 1``), the reset map is applied, and the rest of the sample is
integrated in the new region. Everything here works on plain arrays: no Python objects.
"""

from __future__ import annotations

import numpy as np
from numba import njit

NZ = 14
NX = 9
S3, Q, S4, V3, V4, ZI, ZID = 4, 6, 7, 5, 8, 9, 10
RESET_OPEN, RESET_CLOSE = 1, 2
MAX_EVENTS_PER_SAMPLE = 12
STATUS_OK, STATUS_EVENT_CAP = 0, 2


@njit(cache=True, nogil=True)
def _flow(a, z, sigma, out):
    """out = exp(a * sigma) @ z by Taylor series (a: (NZ, NZ) per time unit, |a| sigma < 1).

    Rows ZID.. of ``a`` are zero (current slope and constants do not change) and row ZI only reads
    ZID, so after the first term only the first ZI + 1 entries of a term are non-zero: the series
    works on those.
    """
    m = ZI + 1
    term = np.empty(m)
    tmp = np.empty(m)
    size = 0.0
    for i in range(NZ):
        out[i] = z[i]
        size = max(size, abs(z[i]))
    # first term: the full product (the constant inputs act once)
    big = 0.0
    for i in range(m):
        s = 0.0
        for j in range(NZ):
            s += a[i, j] * z[j]
        term[i] = sigma * s
        out[i] += term[i]
        big = max(big, abs(term[i]))
    k = 2
    while big > 1e-17 * size and k < 40:
        c = sigma / k
        big = 0.0
        for i in range(m):
            s = 0.0
            for j in range(m):
                s += a[i, j] * term[j]
            tmp[i] = c * s
        for i in range(m):
            term[i] = tmp[i]
            out[i] += tmp[i]
            big = max(big, abs(tmp[i]))
        k += 1


@njit(cache=True, nogil=True)
def _dot(g, z):
    s = 0.0
    for i in range(NZ):
        s += g[i] * z[i]
    return s


@njit(cache=True, nogil=True)
def _rate(g, a, z):
    """d/dt (g @ z) = g @ a @ z."""
    s = 0.0
    for j in range(NZ):
        c = 0.0
        for i in range(NZ):
            c += g[i] * a[i, j]
        s += c * z[j]
    return s


@njit(cache=True, nogil=True)
def _locate(a, g, z, zn, rem, g0, g1, out, smooth):
    """Crossing time of g @ exp(a s) z in (0, rem] where g0 <= 0 < g1 (zn = state at rem).

    Start from the root of the cubic Hermite interpolant of the guard (values and rates at both
    ends), then Newton on the exact flow inside the bracket (bisection if a step leaves it).
    Returns a time at which the guard is already positive, with the state there in ``out``.
    ``smooth``: the boundary between two spring pieces, across which the force is continuous, so
    the first point found past the root is accepted (a switching-time error δ changes the state
    by O(δ^2) and less); contact, opening and closing are located to 1e-7 of the step.
    """
    d0 = _rate(g, a, z)
    d1 = _rate(g, a, zn)
    # Hermite cubic on u in [0, 1]: p(u) = h00 g0 + h10 rem d0 + h01 g1 + h11 rem d1
    u = -g0 / (g1 - g0)
    for _ in range(8):
        u2 = u * u
        u3 = u2 * u
        pv = ((2 * u3 - 3 * u2 + 1) * g0 + (u3 - 2 * u2 + u) * rem * d0 + (-2 * u3 + 3 * u2) * g1
              + (u3 - u2) * rem * d1)
        dp = ((6 * u2 - 6 * u) * g0 + (3 * u2 - 4 * u + 1) * rem * d0 + (-6 * u2 + 6 * u) * g1
              + (3 * u2 - 2 * u) * rem * d1)
        if dp == 0.0:
            break
        un = u - pv / dp
        if not (un > 0.0 and un < 1.0):
            break
        u = un
    lo, hi = 0.0, rem
    s = u * rem
    tol = 1e-7 * rem
    for _ in range(60):
        _flow(a, z, s, out)
        fs = _dot(g, out)
        if fs > 0.0:
            hi = s
            if smooth:
                return s
        else:
            lo = s
        d = _rate(g, a, out)
        step = s - fs / d if d != 0.0 else 0.5 * (lo + hi)
        if abs(step - s) < tol and fs > 0.0:
            return s
        if abs(step - s) < tol:
            step = s + tol          # converged just below the root: step across it
        if not (step > lo and step < hi):
            step = 0.5 * (lo + hi)
        if hi - lo < tol:
            break
        s = step
    _flow(a, z, hi, out)
    return hi


@njit(cache=True, nogil=True)
def _apply_reset(z, code):
    if code == RESET_OPEN:
        z[V4] = max(z[V3], 0.0)   # the plunger lifts with the piston, never into its seat
    elif code == RESET_CLOSE:
        z[S4] = 0.0
        z[V4] = 0.0


@njit(cache=True, nogil=True)
def _region_phi(phi_src, idx, w, b, r, z, out, const):
    """Rows 0..NX-1 of the transition matrix of region r for candidate b (weighted table rows),
    and ``const[r]``: the contribution of the constant inputs L_h, F_open, 1 (columns 11..13)."""
    for i in range(NX):
        for j in range(NZ):
            out[r, i, j] = (w[b, 0] * phi_src[idx[b, 0], r, i, j] + w[b, 1] * phi_src[idx[b, 1], r, i, j]
                            + w[b, 2] * phi_src[idx[b, 2], r, i, j] + w[b, 3] * phi_src[idx[b, 3], r, i, j])
        c = 0.0
        for j in range(ZID + 1, NZ):
            c += out[r, i, j] * z[j]
        const[r, i] = c


@njit(cache=True, nogil=True)
def _region_a(a_const, a_coup, a_damp, cpl, dmp, r, out):
    for i in range(NZ):
        for j in range(NZ):
            out[i, j] = a_const[r, i, j] + cpl * a_coup[r, i, j] + dmp * a_damp[r, i, j]


@njit(cache=True, nogil=True)
def simulate_kernel(phi_src, idx, w, a_const, a_coup, a_damp, cpl, dmp, guards, target, reset,
                    open_index, open_seated, region_mode, z0, region0, cur, h, cout,
                    out_u, out_s3, out_s4, out_mode, t_contact, t_open, status):
    """Advance B candidates over the samples of ``cur`` (all arrays in scaled units, time in µs).

    The transition matrix of region r for candidate b is ``sum_q w[b,q] phi_src[idx[b,q], r]``
    (a 4-point interpolation in N_u, or one exact matrix with weight 1); it is formed the first
    time the candidate enters the region. The continuous matrix, needed only to locate events, is
    ``a_const[r] + cpl[b] a_coup[r] + dmp[b] a_damp[r]``. guards (6, 3, NZ), target/reset (6, 3)
    are the automaton; z0 (B, NZ), region0 (B,) the initial state; cur (N,) the current in A;
    cout (B, NZ) the output rows. Outputs are written in place; t_contact/t_open in µs (NaN: none).
    """
    nb = z0.shape[0]
    n = cur.shape[0]
    nreg = a_const.shape[0]
    z = np.empty(NZ)
    zn = np.empty(NZ)
    zt = np.empty(NZ)
    zb = np.empty(NZ)
    phi = np.empty((nreg, NX, NZ))
    const = np.empty((nreg, NX))
    have = np.zeros(nreg, dtype=np.bool_)
    amat = np.empty((nreg, NZ, NZ))
    have_a = np.zeros(nreg, dtype=np.bool_)
    for b in range(nb):
        have[:] = False
        have_a[:] = False
        seated = False
        for i in range(NZ):
            z[i] = z0[b, i]
        r = region0[b]
        t_contact[b] = np.nan
        t_open[b] = np.nan
        status[b] = STATUS_OK
        if region_mode[r] == 2 or region_mode[r] == 3:
            t_contact[b] = 0.0
        z[ZI] = cur[0]
        out_u[b, 0] = _dot(cout[b], z)
        out_s3[b, 0] = z[S3]
        out_s4[b, 0] = z[S4]
        out_mode[b, 0] = region_mode[r]
        for k in range(n - 1):
            z[ZI] = cur[k]
            z[ZID] = (cur[k + 1] - cur[k]) / h
            rem = h
            nev = 0
            while True:
                if rem == h:
                    if not have[r]:
                        _region_phi(phi_src, idx, w, b, r, z, phi, const)
                        have[r] = True
                    # the valve plunger states are held at rest while the valve is closed
                    nx = NX if region_mode[r] >= 3 else S4
                    zi = z[ZI]
                    zd = z[ZID]
                    for i in range(nx):
                        s = const[r, i] + phi[r, i, ZI] * zi + phi[r, i, ZID] * zd
                        for j in range(nx):
                            s += phi[r, i, j] * z[j]
                        zn[i] = s
                    for i in range(nx, NZ):
                        zn[i] = z[i]
                    zn[ZI] = zi + h * zd
                else:
                    if not have_a[r]:
                        _region_a(a_const, a_coup, a_damp, cpl[b], dmp[b], r, amat[r])
                        have_a[r] = True
                    _flow(amat[r], z, rem, zn)
                best = -1
                best_s = rem
                for j in range(3):
                    if target[r, j] < 0:
                        continue
                    g = guards[r, j]
                    g0 = _dot(g, z)
                    g1 = _dot(g, zn)
                    if seated and j == open_index[r]:
                        # lift-off from the seat needs both forces: min(ordinary, spring-only) > 0
                        gs = open_seated[r]
                        gs0, gs1 = _dot(gs, z), _dot(gs, zn)
                        g0 = min(g0, gs0)
                        if gs1 < g1:
                            g, g1 = gs, gs1
                    if g0 <= 0.0 and g1 > 0.0:
                        if not have_a[r]:
                            _region_a(a_const, a_coup, a_damp, cpl[b], dmp[b], r, amat[r])
                            have_a[r] = True
                        s = _locate(amat[r], g, z, zn, rem, g0, g1, zt,
                                    reset[r, j] == 0 and region_mode[target[r, j]] == region_mode[r])
                        if s < best_s or best < 0:
                            best_s = s
                            best = j
                            for i in range(NZ):
                                zb[i] = zt[i]
                if best < 0:
                    for i in range(NZ):
                        z[i] = zn[i]
                    break
                if nev >= MAX_EVENTS_PER_SAMPLE:
                    status[b] = STATUS_EVENT_CAP
                    for i in range(NZ):
                        z[i] = zn[i]
                    break
                for i in range(NZ):
                    z[i] = zb[i]
                t_ev = k * h + (h - rem) + best_s
                # take the transition, then any that are already enabled at the new state
                j = best
                while j >= 0 and nev < MAX_EVENTS_PER_SAMPLE:
                    _apply_reset(z, reset[r, j])
                    if reset[r, j] == RESET_CLOSE:
                        seated = True
                    elif reset[r, j] == RESET_OPEN:
                        seated = False
                    r = target[r, j]
                    nev += 1
                    md = region_mode[r]
                    if (md == 2 or md == 3) and np.isnan(t_contact[b]):
                        t_contact[b] = t_ev
                    if md == 3 and np.isnan(t_open[b]):
                        t_open[b] = t_ev
                    j = -1
                    for jj in range(3):
                        if target[r, jj] < 0:
                            continue
                        gv = _dot(guards[r, jj], z)
                        if seated and jj == open_index[r]:
                            gv = min(gv, _dot(open_seated[r], z))
                        if gv > 0.0:
                            j = jj
                            break
                rem = rem - best_s
                if rem <= 1e-12 * h:
                    break
            z[ZI] = cur[k + 1]
            if seated and open_index[r] >= 0 and _dot(guards[r, open_index[r]], z) <= 0.0:
                seated = False   # the full opening force fell below F_open: the ordinary guard re-arms
            out_u[b, k + 1] = _dot(cout[b], z)
            out_s3[b, k + 1] = z[S3]
            out_s4[b, k + 1] = z[S4]
            out_mode[b, k + 1] = region_mode[r]


@njit(cache=True, nogil=True)
def lagrange_stencil(nu, nu0, dnu):
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
def lti_foh_kernel(phi, g0, g1, c, d, cur, h, out_y, out_x):
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
def run_batch(src, stencil, idx_in, w_in, nu0, dnu, a_const, a_coup, a_damp, guards, target, reset, open_index,
              open_seated, region_mode, nu, lh, fo, z0_given, region0, cur, h, ks, rb, r0a, r0b, d):
    """One call for a whole batch: set up each candidate, interpolate its matrices, simulate.

    ``stencil``: interpolate the table ``src`` at ``nu`` (else ``idx_in``/``w_in`` select exact
    matrices). Rows of ``z0_given`` with a finite first entry are initial states given in scaled
    units (pre-compressed starts); the others start at rest. ``d`` is the scaling vector. Returns
    (u, s3, s4, mode, t_contact, t_open, status, success) with s3, s4 in m and times in s.
    """
    nb = nu.shape[0]
    n = cur.shape[0]
    if stencil:
        idx, w = lagrange_stencil(nu, nu0, dnu)
    else:
        idx, w = idx_in, w_in
    z0 = np.zeros((nb, NZ))
    cout = np.zeros((nb, NZ))
    cpl = np.empty(nb)
    dmp = np.empty(nb)
    for b in range(nb):
        if np.isfinite(z0_given[b, 0]):
            for i in range(NZ):
                z0[b, i] = z0_given[b, i]
        else:
            z0[b, ZID + 1] = lh[b] * d[ZID + 1]
            z0[b, ZID + 2] = fo[b]
            z0[b, ZID + 3] = 1.0
        ks_nu = ks / nu[b]
        cout[b, S3] = -ks_nu / d[S3]
        cout[b, S3 - 2] = ks_nu / d[S3 - 2]
        cout[b, Q] = ks_nu / nu[b] / d[Q]
        cout[b, ZI] = r0a * np.exp(-r0b * nu[b])
        cpl[b] = ks_nu
        dmp[b] = rb * nu[b] * nu[b]
    u = np.empty((nb, n))
    s3 = np.empty((nb, n))
    s4 = np.empty((nb, n))
    mode = np.empty((nb, n), dtype=np.int8)
    tc = np.empty(nb)
    to = np.empty(nb)
    status = np.empty(nb, dtype=np.int64)
    simulate_kernel(src, idx, w, a_const, a_coup, a_damp, cpl, dmp, guards, target, reset, open_index, open_seated,
                    region_mode, z0, region0, cur, h, cout, u, s3, s4, mode, tc, to, status)
    success = np.empty(nb, dtype=np.bool_)
    for b in range(nb):
        for k in range(n):
            s3[b, k] *= 1e-6
            s4[b, k] *= 1e-6
        tc[b] *= 1e-6
        to[b] *= 1e-6
        success[b] = status[b] == STATUS_OK
    return u, s3, s4, mode, tc, to, status, success


@njit(cache=True, nogil=True)
def check_inputs(cur, nu, lh, fo, nu_min, nu_max):
    """0 if all inputs are usable, else 1 (current), 2 (N_u), 3 (L_h or F_open); and the number of
    candidates with L_h <= 0 (which need their pre-compressed initial state)."""
    for k in range(cur.shape[0]):
        if not np.isfinite(cur[k]):
            return 1, 0
    for b in range(nu.shape[0]):
        if not (np.isfinite(nu[b]) and nu_min <= nu[b] <= nu_max):
            return 2, 0
    n_neg = 0
    for b in range(lh.shape[0]):
        if not (np.isfinite(lh[b]) and np.isfinite(fo[b]) and fo[b] >= 0.0):
            return 3, 0
        if lh[b] <= 0.0:
            n_neg += 1
    return 0, n_neg
