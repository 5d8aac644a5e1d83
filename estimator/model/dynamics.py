"""PSA (eqs. 17-24) and hybrid valve mechanics (eq. 27, Figs. 10-12) as affine regions, guards and resets.

State and augmented state
-------------------------
The continuous state of eq. 27 is ``x = [s1, v1, s2, v2, s3, v3, Q, s4, v4]`` (m, m/s, C).
For exact discretisation every affine region is written as a homogeneous linear system
``dz/dt = A_r z`` on the augmented vector ``z = [x, I, dI/dt, L_h, F_open, 1]`` (14 entries):
the current is piecewise linear between samples (first-order hold), L_h and F_open are constant
per injection. Then one matrix exponential per region and N_u serves every L_h and F_open.

Regions (affine pieces) and automaton modes
-------------------------------------------
======  ======  ==========================================================================
region  mode    meaning
======  ======  ==========================================================================
0       1 (Σ1)  no contact between PSA bottom plate and valve piston, valve closed
1       2 (Σ2)  contact, compression s < s_p (stiffness k_v1), contact force below F_open
2       2 (Σ2)  contact, compression s >= s_p (stiffness k_v2), contact force below F_open
3       3 (Σ3)  valve open, in contact, s < s_p
4       3 (Σ3)  valve open, in contact, s >= s_p
5       4       valve open, contact lost: plunger in flight, returning under F_open + k_f s4
======  ======  ==========================================================================

The compression is ``s = s3 - s4 - L_h``; the contact force on the piston is
``F_c = F_v(s) + b_v (v3 - v4)`` (Fig. 11 spring plus damper) and acts as F_ext in eq. 19.

Guards (a transition fires when the guard value crosses from <= 0 to > 0):

* Σ1 -> Σ2: s crosses 0 upwards (contact); Σ2 -> Σ1: s crosses 0 downwards. Contact is
  geometric, as in the paper's spring-damper contact (section 5.2): the damper makes the force
  jump at contact, and a momentarily pulling damper force is accepted while s > 0.
* s crosses s_p: switch between the k_v1 and k_v2 pieces (same mode, no reset).
* Σ2 -> Σ3: F_c crosses F_open upwards; reset ``v4 := v3`` (paper, section 5.2), but not below 0:
  when the valve reaches its threshold while the piston already retracts (the charge held, the
  stack ringing), the plunger lifts from rest instead of being launched into its seat.
* Σ3 -> Σ2 (valve closes while in contact) and flight -> Σ1 (valve closes without contact):
  s4 crosses 0 downwards; the plunger seats inelastically: reset ``s4 := 0, v4 := 0``.
* Σ3 -> flight: s crosses 0 downwards while the valve is open; flight -> Σ3: s crosses 0 upwards.
* Re-seated plunger: after a close, Σ2 -> Σ3 needs the net force on a plunger that lifts with the
  piston to be positive, F_v + b_v min(v3, 0) >= F_open, i.e. the ordinary guard *and* the spring
  force alone (until the full force falls below F_open, which re-arms the ordinary guard). Without
  this the reset v4 := v3 removes the damper share of the force that triggered the opening, the
  plunger drops back onto the seat, and the guard is true again at once: an endless (Zeno) sequence
  of events when the valve hovers at its opening threshold.

Negative L_h (pre-compressed piston) starts in Σ2 from the static equilibrium with U = 0,
see :func:`initial_state`; a start in Σ3 is infeasible.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator._compiled import njit
from estimator.errors import InfeasibleError
from estimator.model.parameters import InjectorParameters, contact_force
from estimator.units import UM_PER_M

# indices into the augmented state z
S1, V1, S2, V2, S3, V3, Q, S4, V4, ZI, ZID, ZL, ZF, Z1 = range(14)
NX = 9   # physical states
NZ = 14  # augmented states
N_REGIONS = 6
MAX_GUARDS = 3

# automaton modes (Figs. 10-12) and the mode of each region
MODE_FREE, MODE_CONTACT, MODE_OPEN, MODE_FLIGHT = 1, 2, 3, 4
REGION_MODE = np.array([MODE_FREE, MODE_CONTACT, MODE_CONTACT, MODE_OPEN, MODE_OPEN, MODE_FLIGHT], dtype=np.int8)
RESET_NONE, RESET_OPEN, RESET_CLOSE = 0, 1, 2
# outcome of a simulated candidate
STATUS_OK, STATUS_INFEASIBLE, STATUS_EVENT_CAP = 0, 1, 2
STATUS_TEXT = {STATUS_OK: "ok", STATUS_INFEASIBLE: "infeasible initial state",
               STATUS_EVENT_CAP: "too many mode switches in one sample (chattering)"}
REGION_NAMES = ("free", "contact-soft", "contact-stiff", "open-soft", "open-stiff", "flight")

# Scaling used inside the numerical kernels only: µm, m/s (= µm/µs), µC, A, A/µs, N; time in µs.
# z_scaled = Z_SCALE * z_SI and A_scaled = 1e-6 * diag(Z_SCALE) A_SI diag(1/Z_SCALE). This keeps
# every matrix entry O(1) so that truncated Taylor series and guard root finding are well conditioned.
Z_SCALE = np.array([1e6, 1.0, 1e6, 1.0, 1e6, 1.0, 1e6, 1e6, 1.0, 1.0, 1e-6, 1e6, 1.0, 1.0])
TIME_SCALE = 1e6  # s -> µs


@dataclass(frozen=True)
class HybridStructure:
    """Parameter-dependent but N_u-independent pieces of the hybrid model (SI).

    ``a_const + (k_s/N_u) * a_coupling + (R_b N_u^2) * a_damping`` gives the region matrices.
    """

    a_const: np.ndarray      # (6, 14, 14)
    a_coupling: np.ndarray   # (14, 14), same in every region, multiplies k_s / N_u
    a_damping: np.ndarray    # (14, 14), same in every region, multiplies b_p = R_b N_u^2
    guards: np.ndarray       # (6, 3, 14) guard rows, value = guards[r, j] @ z
    guard_target: np.ndarray  # (6, 3) region after the transition, -1 where no guard
    guard_reset: np.ndarray  # (6, 3) RESET_* code
    open_index: np.ndarray   # (6,) index of the Σ2 -> Σ3 guard in the region's list, -1 if none
    open_seated: np.ndarray  # (6, 14) that guard without the damper term (used after a re-seat)


def _contact_force_row(p: InjectorParameters, stiff: bool) -> np.ndarray:
    """Row vector f with F_c = f @ z for the soft (k_v1) or stiff (k_v2) piece (N)."""
    v = p.valve
    f = np.zeros(NZ)
    k = v.kv2_n_per_m if stiff else v.kv1_n_per_m
    f[S3], f[S4], f[ZL] = k, -k, -k
    if stiff:
        f[Z1] = (v.kv1_n_per_m - v.kv2_n_per_m) * v.sp_m
    f[V3], f[V4] = v.bv_ns_per_m, -v.bv_ns_per_m
    return f


def build_structure(p: InjectorParameters) -> HybridStructure:
    """Assemble region matrices, guards and resets from the parameters (eqs. 17-19, 27)."""
    a, m = p.psa, p.valve
    m1, m2, m3, m4 = a.m1_kg, a.m2_kg, a.m3_kg, m.m4_kg
    ktot = a.kp_n_per_m + a.ks_n_per_m  # k_p + N_u^2/C = k_p + k_s (eq. 21)

    base = np.zeros((NZ, NZ))
    coup = np.zeros((NZ, NZ))
    damp = np.zeros((NZ, NZ))
    base[S1, V1] = base[S2, V2] = base[S3, V3] = 1.0
    # eq. 17: m1 s1'' = -kg1 s1 - bg1 v1 + kg2 (s2 - s1) + bg2 (v2 - v1)
    base[V1, S1] = (-a.kg1_n_per_m - a.kg2_n_per_m) / m1
    base[V1, S2] = a.kg2_n_per_m / m1
    base[V1, V1] = (-a.bg1_ns_per_m - a.bg2_ns_per_m) / m1
    base[V1, V2] = a.bg2_ns_per_m / m1
    # eq. 18: m2 s2'' = -kg2 (s2-s1) - bg2 (v2-v1) + (kp+ks)(s3-s2) + bp (v3-v2) - (ks/Nu) Q
    base[V2, S1] = a.kg2_n_per_m / m2
    base[V2, S2] = (-a.kg2_n_per_m - ktot) / m2
    base[V2, S3] = ktot / m2
    base[V2, V1] = a.bg2_ns_per_m / m2
    base[V2, V2] = -a.bg2_ns_per_m / m2
    damp[V2, V2], damp[V2, V3] = -1.0 / m2, 1.0 / m2
    coup[V2, Q] = -1.0 / m2
    # eq. 19: m3 s3'' = -(kp+ks)(s3-s2) + (ks/Nu) Q - bp (v3-v2) - F_ext
    base[V3, S2], base[V3, S3] = ktot / m3, -ktot / m3
    damp[V3, V2], damp[V3, V3] = 1.0 / m3, -1.0 / m3
    coup[V3, Q] = 1.0 / m3
    # Q' = I, I' = dI/dt (first-order hold of the sampled current)
    base[Q, ZI] = 1.0
    base[ZI, ZID] = 1.0

    f_soft, f_stiff = _contact_force_row(p, False), _contact_force_row(p, True)
    a_const = np.repeat(base[None], N_REGIONS, axis=0)
    for r, f in ((1, f_soft), (2, f_stiff), (3, f_soft), (4, f_stiff)):
        a_const[r, V3] -= f / m3            # F_ext = F_c on the PSA bottom plate
    plunger_rows: tuple[tuple[int, np.ndarray | None], ...] = ((3, f_soft), (4, f_stiff), (5, None))
    for r, f_row in plunger_rows:
        row = np.zeros(NZ)
        if f_row is not None:
            row += f_row
        row[ZF] -= 1.0                      # preload F_open
        row[S4] -= m.kf_n_per_m             # valve spring k_f s4
        row[V4] -= m.bf_ns_per_m            # valve damper b_f v4
        a_const[r, S4, V4] = 1.0
        a_const[r, V4] = row / m4

    g_c = np.zeros(NZ)
    g_c[S3], g_c[S4], g_c[ZL] = 1.0, -1.0, -1.0          # compression s
    g_sp = g_c.copy()
    g_sp[Z1] = -m.sp_m                                   # s - s_p
    f_open = np.zeros(NZ)
    f_open[ZF] = 1.0
    g_s4 = np.zeros(NZ)
    g_s4[S4] = -1.0
    guards = np.zeros((N_REGIONS, MAX_GUARDS, NZ))
    target = -np.ones((N_REGIONS, MAX_GUARDS), dtype=np.int64)
    reset = np.zeros((N_REGIONS, MAX_GUARDS), dtype=np.int64)
    table = {
        0: [(g_c, 1, RESET_NONE)],
        1: [(-g_c, 0, RESET_NONE), (g_sp, 2, RESET_NONE), (f_soft - f_open, 3, RESET_OPEN)],
        2: [(-g_sp, 1, RESET_NONE), (f_stiff - f_open, 4, RESET_OPEN)],
        3: [(-g_c, 5, RESET_NONE), (g_sp, 4, RESET_NONE), (g_s4, 1, RESET_CLOSE)],
        4: [(-g_sp, 3, RESET_NONE), (g_s4, 2, RESET_CLOSE)],
        5: [(g_c, 3, RESET_NONE), (g_s4, 0, RESET_CLOSE)],
    }
    for r, rows in table.items():
        for j, (g, t, rs) in enumerate(rows):
            guards[r, j], target[r, j], reset[r, j] = g, t, rs
    open_index = np.array([-1, 2, 1, -1, -1, -1], dtype=np.int64)
    open_seated = np.zeros((N_REGIONS, NZ))
    for r, f in ((1, f_soft), (2, f_stiff)):
        g = f - f_open
        g[V3] = g[V4] = 0.0          # spring force only
        open_seated[r] = g
    return HybridStructure(a_const, coup, damp, guards, target, reset, open_index, open_seated)


def region_matrices(structure: HybridStructure, p: InjectorParameters, nu: np.ndarray) -> np.ndarray:
    """Region matrices A_r(N_u) in SI, shape (len(nu), 6, 14, 14)."""
    nu = np.atleast_1d(np.asarray(nu, dtype=float))
    c = np.asarray(coupling(p.psa.ks_n_per_m, nu))[:, None, None, None]
    d = np.asarray(damping(p.psa.rb_v2s_per_mn, nu))[:, None, None, None]
    result: np.ndarray = structure.a_const[None] + c * structure.a_coupling[None] + d * structure.a_damping[None]
    return result


def output_rows(p: InjectorParameters, nu: np.ndarray) -> np.ndarray:
    """Rows c with U = c @ z (eq. 20, H[Q] replaced by R(N_u) I, eq. 22), shape (len(nu), 14), V per SI unit."""
    nu = np.atleast_1d(np.asarray(nu, dtype=float))
    c = np.zeros((nu.size, NZ))
    for b in range(nu.size):
        output_row_into(p.psa.ks_n_per_m, p.psa.r0a_ohm, p.psa.r0b_v_per_n, float(nu[b]), c[b])
    return c


def coupling(ks_n_per_m: float, nu: float | np.ndarray) -> float | np.ndarray:
    """The factor k_s / N_u of ``HybridStructure.a_coupling`` (N/(V m) per N/V; scalar or array)."""
    return ks_n_per_m / nu


def damping(rb_v2s_per_mn: float, nu: float | np.ndarray) -> float | np.ndarray:
    """Material damping b_p = R_b N_u^2 (N s/m), the factor of ``HybridStructure.a_damping``."""
    return rb_v2s_per_mn * (nu * nu)


coupling_jit = njit(cache=True, nogil=True)(coupling)
damping_jit = njit(cache=True, nogil=True)(damping)


@njit(cache=True, nogil=True)
def output_row_into(ks_n_per_m: float, r0a_ohm: float, r0b_v_per_n: float, nu: float, out: np.ndarray) -> None:
    """Write the output row c (U = c @ z, SI) for one N_u into ``out`` (14 entries, S2/S3/Q/ZI set).

    Eq. 20 with H[Q] replaced by R(N_u) I (eq. 22): U = (k_s/N_u)(s2 - s3) + Q/C + R(N_u) I with
    1/C = k_s / N_u^2 (eq. 21). The kernel divides by :data:`Z_SCALE` for the scaled state.
    """
    ks_nu = ks_n_per_m / nu
    out[S3] = -ks_nu
    out[S2] = ks_nu
    out[Q] = ks_nu / nu
    out[ZI] = r0a_ohm * np.exp(-r0b_v_per_n * nu)


def output_row(p: InjectorParameters, nu: float) -> np.ndarray:
    """The output row of :func:`output_rows` for one N_u (N/V)."""
    result: np.ndarray = output_rows(p, np.array([nu]))[0]
    return result


def psa_state_space(p: InjectorParameters, nu: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The 7-state LTI PSA model of eqs. 23-24: x=[s1,v1,s2,v2,s3,v3,Q], u=[I, F_ext], y=U."""
    st = build_structure(p)
    full = region_matrices(st, p, np.array([nu]))[0, 0]
    a = full[:7, :7].copy()
    b = np.zeros((7, 2))
    b[Q, 0] = 1.0
    b[V3, 1] = -1.0 / p.psa.m3_kg
    c_full = output_row(p, nu)
    return a, b, c_full[:7].reshape(1, 7), np.array([[c_full[ZI], 0.0]])


def spring_constants(p: InjectorParameters) -> np.ndarray:
    """(k_g1, k_g2, k_p, k_v1, k_v2, s_p) in SI units: the numbers of the static pre-compression."""
    a, v = p.psa, p.valve
    return np.array([a.kg1_n_per_m, a.kg2_n_per_m, a.kp_n_per_m, v.kv1_n_per_m, v.kv2_n_per_m, v.sp_m])


@njit(cache=True, nogil=True)
def _precompressed_into(k: np.ndarray, nu: float, lh_m: float, x: np.ndarray) -> float:
    """The static Σ2 equilibrium of :func:`precompressed_state` written into ``x`` (NX,); returns the
    contact force in N. ``k`` is :func:`spring_constants`."""
    kg1, kg2, kp, kv1, kv2, sp = k[0], k[1], k[2], k[3], k[4], k[5]
    kappa = 1.0 / kg1 + 1.0 / kg2 + 1.0 / kp
    target = -lh_m
    # F_v is piecewise linear: try the soft piece, then the stiff one.
    s = target / (1.0 + kv1 * kappa)
    if s > sp:
        s = (target - kappa * (kv1 - kv2) * sp) / (1.0 + kv2 * kappa)
    force = contact_force(kv1, kv2, sp, s)
    for i in range(NX):
        x[i] = 0.0
    x[S1] = -force / kg1
    x[S2] = x[S1] - force / kg2
    x[S3] = x[S2] - force / kp
    x[Q] = nu * (x[S3] - x[S2])
    return force


@njit(cache=True, nogil=True)
def precompressed_starts(k: np.ndarray, nu: np.ndarray, lh_m: np.ndarray, f_open_n: np.ndarray, z_scale: np.ndarray, z0: np.ndarray, region0: np.ndarray) -> np.ndarray:
    """Initial states of the candidates with L_h <= 0 (all arrays (B,), SI units): rows of ``z0``
    (B, NZ) get the scaled augmented state (times ``z_scale``) and ``region0`` the region of
    :func:`initial_state`; returns a (B,) mask, False where the start is infeasible (the valve
    would start open; that row is left as it is). Rows with L_h > 0 are not touched."""
    nb = nu.shape[0]
    feasible = np.ones(nb, dtype=np.bool_)
    x = np.empty(NX)
    for b in range(nb):
        if not lh_m[b] <= 0.0:
            continue
        force = _precompressed_into(k, nu[b], lh_m[b], x)
        if force >= f_open_n[b]:
            feasible[b] = False
            continue
        for i in range(NZ):
            z0[b, i] = 0.0
        for i in range(NX):
            z0[b, i] = x[i] * z_scale[i]
        z0[b, ZL] = lh_m[b] * z_scale[ZL]
        z0[b, ZF] = f_open_n[b] * z_scale[ZF]
        z0[b, Z1] = 1.0 * z_scale[Z1]
        region0[b] = 1 if (x[S3] - lh_m[b]) <= k[5] else 2
    return feasible


def precompressed_state(p: InjectorParameters, nu: float, lh_m: float) -> tuple[np.ndarray, float]:
    """Static Σ2 equilibrium for L_h <= 0 with the actuator discharged to U = 0.

    With U = 0, eq. 20 gives Q = N_u (s3 - s2); the force balance of eqs. 17-19 then gives
    k_p (s3 - s2) = -F_v, k_g2 (s2 - s1) = k_g1 s1 = -F_v, so the compression s solves
    ``s + F_v(s) (1/k_g1 + 1/k_g2 + 1/k_p) = -L_h``. Returns (x (9,), contact force F_v in N).
    """
    x = np.zeros(NX)
    force = _precompressed_into(spring_constants(p), float(nu), float(lh_m), x)
    return x, float(force)


def initial_state(p: InjectorParameters, nu: float, lh_m: float, f_open_n: float,
                  current0_a: float = 0.0, didt0_a_per_s: float = 0.0) -> tuple[np.ndarray, int]:
    """Augmented initial state z0 (SI) and initial region for one injection.

    L_h > 0 starts at rest in Σ1. L_h <= 0 starts in Σ2 from :func:`precompressed_state`.
    Raises :class:`InfeasibleError` when the pre-compression force would already open the
    valve (a start in Σ3, which the paper excludes by a lower bound on L_h).
    """
    if not (math.isfinite(lh_m) and math.isfinite(f_open_n)):
        raise InfeasibleError(f"L_h = {lh_m!r} m and F_open = {f_open_n!r} N must be finite")
    if lh_m > 0.0:
        z = np.zeros(NZ)
        z[ZI], z[ZID], z[ZL], z[ZF], z[Z1] = current0_a, didt0_a_per_s, lh_m, f_open_n, 1.0
        return z, 0
    z0 = np.full((1, NZ), np.nan)
    region0 = np.zeros(1, dtype=np.int64)
    if not precompressed_starts(spring_constants(p), np.array([float(nu)]), np.array([float(lh_m)]),
                                np.array([float(f_open_n)]), np.ones(NZ), z0, region0)[0]:
        _, force = precompressed_state(p, nu, lh_m)
        raise InfeasibleError(
            f"L_h = {lh_m * UM_PER_M:.3f} µm pre-compresses the piston with {force:.2f} N >= F_open = "
            f"{f_open_n:.2f} N: the valve would start open (Σ3), which the model excludes")
    z = z0[0]
    z[ZI], z[ZID] = current0_a, didt0_a_per_s
    return z, int(region0[0])


def min_feasible_lh_m(p: InjectorParameters, f_open_n: float) -> float:
    """The most negative L_h (m) whose pre-compression force stays below F_open."""
    v, a = p.valve, p.psa
    kappa = 1.0 / a.kg1_n_per_m + 1.0 / a.kg2_n_per_m + 1.0 / a.kp_n_per_m
    if f_open_n <= v.kv1_n_per_m * v.sp_m:
        s = f_open_n / v.kv1_n_per_m
    else:
        s = v.sp_m + (f_open_n - v.kv1_n_per_m * v.sp_m) / v.kv2_n_per_m
    return -(s + f_open_n * kappa)
