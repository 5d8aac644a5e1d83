"""The matrix exponential of many small matrices in one compiled call.

The fast simulator discretises each affine region exactly, ``exp(A_r(N_u) h)``, for every N_u of its
table and, in exact mode, for every distinct N_u a calibration asks for: thousands of 14 × 14
matrices per calibration. ``scipy.linalg.expm`` took about half the time of a hysteresis part's
first calibration (profiled), mostly its per-call and per-matrix Python; written out for small
matrices in one compiled call, that window's calibration took a third of the time.

:func:`expm_batch` is Higham's scaling and squaring with diagonal Padé approximants (N. J. Higham,
"The scaling and squaring method for the matrix exponential revisited", SIAM J. Matrix Anal. Appl.
26(4), 2005, Algorithm 2.3): the lowest Padé degree m in (3, 5, 7, 9, 13) whose θ_m bounds the
matrix's 1-norm, else degree 13 after scaling by 2^-s with ||A/2^s||_1 <= θ_13, and s squarings.
Its backward error is at most the unit roundoff in exact arithmetic; against scipy (Al-Mohy and
Higham's 2009 variant of the same method) the results agree to about 1e-15 relative
(``tests/model/test_matrix_exponential.py``).
"""

from __future__ import annotations

import math

import numpy as np

from estimator._compiled import njit

THETA = (1.495585217958292e-2, 2.539398330063230e-1, 9.504178996162932e-1, 2.097847961257068e0,
         5.371920351148152e0)   # θ_m for m = 3, 5, 7, 9, 13 (Higham 2005, Table 2.3)

_B3 = np.array([120.0, 60.0, 12.0, 1.0])
_B5 = np.array([30240.0, 15120.0, 3360.0, 420.0, 30.0, 1.0])
_B7 = np.array([17297280.0, 8648640.0, 1995840.0, 277200.0, 25200.0, 1512.0, 56.0, 1.0])
_B9 = np.array([17643225600.0, 8821612800.0, 2075673600.0, 302702400.0, 30270240.0, 2162160.0, 110880.0,
                3960.0, 90.0, 1.0])
_B13 = np.array([64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0,
                 129060195264000.0, 10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0,
                 40840800.0, 960960.0, 16380.0, 182.0, 1.0])


@njit(cache=True, nogil=True)
def _norm1(a: np.ndarray) -> float:
    """The 1-norm (largest absolute column sum) of a square matrix."""
    n = a.shape[0]
    best = 0.0
    for j in range(n):
        s = 0.0
        for i in range(n):
            s += abs(a[i, j])
        best = max(best, s)
    return best


@njit(cache=True, nogil=True)
def _mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b of two small square matrices, written out (BLAS's call overhead exceeds the work)."""
    n = a.shape[0]
    out = np.zeros((n, n))
    for i in range(n):
        for k in range(n):
            aik = a[i, k]
            if aik != 0.0:
                for j in range(n):
                    out[i, j] += aik * b[k, j]
    return out


@njit(cache=True, nogil=True)
def _solve(m: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The solution x of m x = r (square, small), by Gaussian elimination with partial pivoting;
    ``m`` and ``r`` are overwritten."""
    n = m.shape[0]
    for c in range(n):
        p = c
        for i in range(c + 1, n):
            if abs(m[i, c]) > abs(m[p, c]):
                p = i
        if p != c:
            for j in range(n):
                m[c, j], m[p, j] = m[p, j], m[c, j]
                r[c, j], r[p, j] = r[p, j], r[c, j]
        piv = m[c, c]
        for i in range(c + 1, n):
            f = m[i, c] / piv
            if f != 0.0:
                for j in range(c + 1, n):
                    m[i, j] -= f * m[c, j]
                for j in range(n):
                    r[i, j] -= f * r[c, j]
    for c in range(n - 1, -1, -1):
        for j in range(n):
            v = r[c, j]
            for k in range(c + 1, n):
                v -= m[c, k] * r[k, j]
            r[c, j] = v / m[c, c]
    return r


@njit(cache=True, nogil=True)
def _low_degree(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """U and V of the diagonal Padé approximant of degree m = len(b) - 1 (odd, at most 9):
    U = A Σ_k b_{2k+1} A^{2k}, V = Σ_k b_{2k} A^{2k}."""
    n = a.shape[0]
    a2 = _mul(a, a)
    power = np.eye(n)
    u_sum = b[1] * power
    v = b[0] * power
    for k in range(1, (b.shape[0] - 1) // 2 + 1):
        power = _mul(power, a2)
        u_sum += b[2 * k + 1] * power
        v += b[2 * k] * power
    return _mul(a, u_sum), v


@njit(cache=True, nogil=True)
def _degree13(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """U and V of the degree-13 diagonal Padé approximant, evaluated as in Higham's (2.7)."""
    b = _B13
    n = a.shape[0]
    ident = np.eye(n)
    a2 = _mul(a, a)
    a4 = _mul(a2, a2)
    a6 = _mul(a4, a2)
    u = _mul(a, _mul(a6, b[13] * a6 + b[11] * a4 + b[9] * a2) + b[7] * a6 + b[5] * a4 + b[3] * a2 + b[1] * ident)
    v = _mul(a6, b[12] * a6 + b[10] * a4 + b[8] * a2) + b[6] * a6 + b[4] * a4 + b[2] * a2 + b[0] * ident
    return u, v


@njit(cache=True, nogil=True)
def expm_one(a: np.ndarray) -> np.ndarray:
    """exp(a) of one square float64 matrix (Higham 2005, Algorithm 2.3); NaN if ``a`` is not finite."""
    n = a.shape[0]
    if not np.all(np.isfinite(a)):
        return np.full((n, n), np.nan)
    norm = _norm1(a)
    squarings = 0
    if norm <= THETA[0]:
        u, v = _low_degree(a, _B3)
    elif norm <= THETA[1]:
        u, v = _low_degree(a, _B5)
    elif norm <= THETA[2]:
        u, v = _low_degree(a, _B7)
    elif norm <= THETA[3]:
        u, v = _low_degree(a, _B9)
    else:
        squarings = max(0, int(math.ceil(math.log2(norm / THETA[4]))))
        u, v = _degree13(a / 2.0 ** squarings)
    x = _solve(v - u, v + u)
    for _ in range(squarings):
        x = _mul(x, x)
    return x


@njit(cache=True, nogil=True)
def _expm_flat(a: np.ndarray) -> np.ndarray:
    """exp of each matrix of ``a`` (K, n, n)."""
    out = np.empty_like(a)
    for k in range(a.shape[0]):
        out[k] = expm_one(a[k].copy())
    return out


def expm_batch(a: np.ndarray) -> np.ndarray:
    """exp of each square matrix in the last two axes of ``a`` (shape (..., n, n), float64), like
    ``scipy.linalg.expm`` on a stack; a C-contiguous array of the same shape."""
    arr = np.ascontiguousarray(a, dtype=float)
    if arr.ndim < 2 or arr.shape[-1] != arr.shape[-2]:
        raise ValueError(f"expm_batch needs square matrices in the last two axes, got shape {arr.shape}")
    n = arr.shape[-1]
    flat = arr.reshape((-1, n, n))
    result: np.ndarray = _expm_flat(flat).reshape(arr.shape)
    return result
