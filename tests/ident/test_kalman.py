"""The compiled Kalman steps against the textbook matrix formulas (numpy, written out here)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.ident.tracking import kalman

NOISE = kalman.ProcessNoise(0.004, 0.02, 0.003, 0.001, 0.002, 0.01, 0.003, 1e-4, 600.0,
                            (9.0, 100.0, 0.04, 0.01, 1e-4), 2e-4)


def _reference_predict(x, p, dt, dtemp, noise):
    a = math.exp(-dt / noise.rate_tau_s)
    f = np.eye(5)
    f[0, 2], f[2, 2], f[0, 3], f[1, 4] = noise.rate_tau_s * (1 - a), a, dtemp or 0.0, 1.0
    known = dtemp is not None
    qr = (noise.rate_per_sqrt_s_known_t if known else noise.rate_per_sqrt_s) ** 2
    qn = noise.nu_per_sqrt_s_known_t if known else noise.nu_per_sqrt_s
    q = np.zeros((5, 5))
    q[0, 0] = noise.nu_per_injection ** 2 + qn ** 2 * dt + qr * dt ** 3 / 3
    q[0, 2] = q[2, 0] = qr * dt ** 2 / 2
    q[2, 2] = qr * dt
    q[1, 1] = noise.lh_per_injection_um ** 2 + noise.lh_per_sqrt_s_um ** 2 * dt
    q[3, 3] = noise.slope_per_sqrt_s ** 2 * dt
    q[4, 4] = noise.wear_per_injection_um ** 2
    p = f @ p @ f.T + q
    d = np.sqrt(np.minimum(1.0, np.asarray(noise.max_var) / np.diag(p)))
    return f @ x, p * np.outer(d, d)


def _random_state(rng):
    x = np.array([17.0, 4.0, 0.01, 0.06, 0.003]) + rng.normal(0, 0.1, 5)
    m = rng.normal(0, 0.3, (5, 5))
    return x, m @ m.T + 0.01 * np.eye(5)


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
    ikh = np.eye(5)
    ikh[:, :2] -= k
    p_ref = ikh @ p @ ikh.T + k @ r @ k.T
    xu, pu = kalman.update(x, p, z, r)
    np.testing.assert_allclose(xu, x + k @ e, rtol=1e-12)
    np.testing.assert_allclose(pu, 0.5 * (p_ref + p_ref.T), rtol=1e-10, atol=1e-14)
    assert np.array_equal(pu, pu.T) and np.all(np.linalg.eigvalsh(pu) > 0)


def test_the_filter_follows_steady_wear_without_falling_behind():
    """A part whose idle stroke grows by 0.003 µm per injection (0.45 µm over 150, the compensation
    lot's fastest), raw L_h to 0.04 µm, one injection a second: with the configured noise the filtered
    L_h keeps up (mean error within a fifth of its σ) and its σ covers the error. A filter without the
    wear rate fell 0.03 µm behind with a σ of 0.012 µm (RMS error/σ 2.8)."""
    from estimator.ident.config import TrackerConfig
    from estimator.ident.fit.search import Box
    from estimator.ident.tracking.tracker_state import process_noise, wear_variance

    config = TrackerConfig()
    noise = process_noise(config, Box(np.array([15.0, 0.0]), np.array([21.0, 12.0])))
    r = np.diag([0.02 ** 2, 0.04 ** 2])
    errors, sigmas = [], []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        x = p = None
        for k in range(150):
            z = np.array([18.0, 4.0 + 0.003 * k]) + rng.normal(0.0, [0.02, 0.04])
            if x is None:
                x, p = kalman.initial(z, r, (config.max_rate_n_per_v_s / 3) ** 2, config.slope_n_per_v_degc,
                                      config.slope_sigma ** 2, wear_variance(config))
                continue
            x, p = kalman.predict(x, p, 1.0, None, noise)
            x, p = kalman.update(x, p, z, r)
            if k >= 60:
                errors.append(x[kalman.LH] - (4.0 + 0.003 * k))
                sigmas.append(math.sqrt(p[kalman.LH, kalman.LH]))
    e, s = np.array(errors), np.array(sigmas)
    assert abs(e.mean()) < 0.2 * s.mean()
    assert 0.5 < math.sqrt(np.mean((e / s) ** 2)) < 1.3
