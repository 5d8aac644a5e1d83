"""The compiled Kalman steps against the textbook matrix formulas (numpy, written out here)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.ident.tracking import kalman

NOISE = kalman.ProcessNoise(0.004, 0.02, 0.003, 0.001, 0.002, 0.01, 0.003, 1e-4, 600.0,
                            (9.0, 100.0, 0.04, 0.01))


def _reference_predict(x, p, dt, dtemp, noise):
    a = math.exp(-dt / noise.rate_tau_s)
    f = np.eye(4)
    f[0, 2], f[2, 2], f[0, 3] = noise.rate_tau_s * (1 - a), a, dtemp or 0.0
    known = dtemp is not None
    qr = (noise.rate_per_sqrt_s_known_t if known else noise.rate_per_sqrt_s) ** 2
    qn = noise.nu_per_sqrt_s_known_t if known else noise.nu_per_sqrt_s
    q = np.zeros((4, 4))
    q[0, 0] = noise.nu_per_injection ** 2 + qn ** 2 * dt + qr * dt ** 3 / 3
    q[0, 2] = q[2, 0] = qr * dt ** 2 / 2
    q[2, 2] = qr * dt
    q[1, 1] = noise.lh_per_injection_um ** 2 + noise.lh_per_sqrt_s_um ** 2 * dt
    q[3, 3] = noise.slope_per_sqrt_s ** 2 * dt
    p = f @ p @ f.T + q
    d = np.sqrt(np.minimum(1.0, np.asarray(noise.max_var) / np.diag(p)))
    return f @ x, p * np.outer(d, d)


def _random_state(rng):
    x = np.array([17.0, 4.0, 0.01, 0.06]) + rng.normal(0, 0.1, 4)
    m = rng.normal(0, 0.3, (4, 4))
    return x, m @ m.T + 0.01 * np.eye(4)


@pytest.mark.parametrize("seed", range(5))
def test_kalman_steps_are_the_matrix_formulas(seed):
    rng = np.random.default_rng(seed)
    x, p = _random_state(rng)
    for dt, dtemp in ((0.04, None), (1.0, 2.5), (3600.0, None)):   # the last one hits the variance caps
        xp, pp = kalman.predict(x, p, dt, dtemp, NOISE)
        xr, pr = _reference_predict(x, p, dt, dtemp, NOISE)
        np.testing.assert_allclose(xp, xr, rtol=1e-13)
        np.testing.assert_allclose(pp, pr, rtol=1e-12, atol=1e-15)
    z = x[:2] + rng.normal(0, 0.2, 2)
    r = np.array([[0.02, 0.005], [0.005, 0.09]])
    s = p[:2, :2] + r
    e = z - x[:2]
    inn = kalman.innovation(x, p, z, r)
    np.testing.assert_allclose(inn.e, e, rtol=1e-14)
    np.testing.assert_allclose(inn.s, s, rtol=1e-14)
    assert inn.d2 == pytest.approx(float(e @ np.linalg.solve(s, e)), rel=1e-12)
    k = p[:, :2] @ np.linalg.inv(s)
    ikh = np.eye(4)
    ikh[:, :2] -= k
    p_ref = ikh @ p @ ikh.T + k @ r @ k.T
    xu, pu = kalman.update(x, p, z, r)
    np.testing.assert_allclose(xu, x + k @ e, rtol=1e-12)
    np.testing.assert_allclose(pu, 0.5 * (p_ref + p_ref.T), rtol=1e-10, atol=1e-14)
    assert np.array_equal(pu, pu.T) and np.all(np.linalg.eigvalsh(pu) > 0)
