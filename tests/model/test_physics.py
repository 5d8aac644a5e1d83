"""Physics from the paper's own numbers, each computed independently of the model code."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.model import dynamics as dyn
from estimator.model.parameters import InjectorParameters

NU = 16.39


def _static_free(params, q):
    """Static equilibrium of the model's A matrix with charge q and no current or contact."""
    a, _, c, _ = dyn.psa_state_space(params, NU)
    mech = [0, 1, 2, 3, 4, 5]
    # 0 = A_mm x_m + A_mq q  ->  x_m = -A_mm^-1 A_mq q
    x_m = np.linalg.solve(a[np.ix_(mech, mech)], -a[mech, 6] * q)
    x = np.append(x_m, q)
    return x, float(c[0] @ x)


def test_free_elongation_per_coulomb_and_per_volt(params):
    ks, kp = params.psa.ks_n_per_m, params.psa.kp_n_per_m
    q = 1e-3
    x, u = _static_free(params, q)
    delta = x[4] - x[2]
    # eqs. 18/19 static, F_ext = 0: (kp + ks) delta = (ks/Nu) Q
    assert delta / q == pytest.approx(ks / (NU * (kp + ks)), rel=1e-10)
    # eqs. 12/13 with k -> kp: F = kp delta - Nu U = 0  ->  delta / U = Nu / kp
    assert delta / u == pytest.approx(NU / kp, rel=1e-10)
    # the mounting carries no force in free elongation
    assert abs(x[0]) < 1e-18 and abs(x[2]) < 1e-18


def test_blocked_force_per_volt(params):
    # hold s1 = s2 = s3 = 0: the force needed on m3 is (ks/Nu) Q, and U = Q / C
    a, b, c, _ = dyn.psa_state_space(params, NU)
    q = 1e-3
    x = np.zeros(7)
    x[6] = q
    accel_m3 = a[5] @ x                    # m3 acceleration without external force
    f_block = accel_m3 * params.psa.m3_kg   # = force that must be taken up to stay blocked
    u = float(c[0] @ x)
    assert f_block / u == pytest.approx(NU, rel=1e-12)   # blocked force F = N_u U (eq. 12)
    assert -b[5, 1] * params.psa.m3_kg == pytest.approx(1.0)  # F_ext enters eq. 19 with -1/m3


def test_capacitance_relation(params):
    ks, kp = params.psa.ks_n_per_m, params.psa.kp_n_per_m
    c_blocked = NU ** 2 / ks                          # eq. 21
    x = np.zeros(7)
    x[6] = 1e-3
    _, _, c, _ = dyn.psa_state_space(params, NU)
    assert 1e-3 / float(c[0] @ x) == pytest.approx(c_blocked, rel=1e-12)
    q = 1e-3
    _, u_free = _static_free(params, q)
    # free capacitance: Q = Nu delta + C U with delta = Nu U / kp
    assert q / u_free == pytest.approx(c_blocked + NU ** 2 / kp, rel=1e-10)


def test_eigenfrequencies_of_the_free_stack(params: InjectorParameters):
    undamped = InjectorParameters(dataclasses.replace(params.psa, rb_v2s_per_mn=0.0), params.valve)
    a, _, _, _ = dyn.psa_state_space(undamped, NU)
    p = params.psa
    kt = p.kp_n_per_m + p.ks_n_per_m   # charge held constant: stack stiffness kp + Nu^2/C
    m = np.diag([p.m1_kg, p.m2_kg, p.m3_kg])
    k = np.array([[p.kg1_n_per_m + p.kg2_n_per_m, -p.kg2_n_per_m, 0.0],
                  [-p.kg2_n_per_m, p.kg2_n_per_m + kt, -kt],
                  [0.0, -kt, kt]])
    omega = np.sort(np.sqrt(np.linalg.eigvals(np.linalg.solve(m, k)).real))
    lam = np.linalg.eigvals(a)
    model = np.sort(np.abs(lam.imag[lam.imag > 1.0]))
    np.testing.assert_allclose(model, omega, rtol=1e-9)
    # the free stack modes are in the 10-40 kHz range, far below the 1 MHz sampling rate
    assert 10e3 < omega[0] / (2 * np.pi) < omega[-1] / (2 * np.pi) < 60e3


def test_precompressed_start_is_static_and_discharged(params):
    z0, region = dyn.initial_state(params, NU, -1e-6, 28.0)
    assert region == 1
    a = dyn.region_matrices(dyn.build_structure(params), params, np.array([NU]))[0, region]
    np.testing.assert_allclose((a @ z0)[:9], 0.0, atol=1e-6)       # at rest
    assert abs(dyn.output_row(params, NU) @ z0) < 1e-9                # U = 0
    assert z0[dyn.Q] == pytest.approx(NU * (z0[dyn.S3] - z0[dyn.S2]))  # Q = Nu (s3 - s2)


def test_start_in_sigma3_is_infeasible(params):
    lh_min = dyn.min_feasible_lh_m(params, 28.0)
    assert -2.7e-6 < lh_min < -2.5e-6
    dyn.initial_state(params, NU, lh_min * 0.99, 28.0)
    with pytest.raises(dyn.InfeasibleError, match="would start open"):
        dyn.initial_state(params, NU, lh_min * 1.01, 28.0)


def test_batched_precompressed_starts_are_initial_state_scaled(params):
    """The simulators' batch of pre-compressed starts is initial_state's, row by row (soft and
    stiff contact pieces, a start at rest left alone, an infeasible one marked and left alone)."""
    lh_min = dyn.min_feasible_lh_m(params, 28.0)
    lh = np.array([-0.2e-6, -1.9e-6, lh_min * 0.999, 3e-6, lh_min * 1.01])
    nu = np.array([15.5, NU, 20.5, NU, NU])
    fo = np.full(lh.size, 28.0)
    z0 = np.full((lh.size, dyn.NZ), np.nan)
    region0 = np.zeros(lh.size, dtype=np.int64)
    feasible = dyn.precompressed_starts(dyn.spring_constants(params), nu, lh, fo, dyn.Z_SCALE, z0, region0)
    assert feasible.tolist() == [True, True, True, True, False]
    regions = []
    for b in range(3):
        z, r = dyn.initial_state(params, nu[b], lh[b], 28.0)
        np.testing.assert_array_equal(z0[b], z * dyn.Z_SCALE)
        assert region0[b] == r
        regions.append(r)
    assert set(regions) == {1, 2}                   # both contact pieces are covered
    assert np.all(np.isnan(z0[3:])) and region0[3:].tolist() == [0, 0]
