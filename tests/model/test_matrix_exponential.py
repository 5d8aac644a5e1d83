"""The compiled matrix exponential against scipy's, on the simulator's own matrices and beyond."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from estimator.model import dynamics as dyn
from estimator.model.matrix_exponential import THETA, expm_batch


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    """Largest 1-norm error of the matrices of ``a`` relative to those of ``b``."""
    flat_a, flat_b = a.reshape((-1, *a.shape[-2:])), b.reshape((-1, *b.shape[-2:]))
    return max(np.linalg.norm(x - y, 1) / np.linalg.norm(y, 1) for x, y in zip(flat_a, flat_b))


def test_the_simulators_transition_matrices_agree_with_scipy(sim) -> None:
    """Every region at N_u across the table's range, one sample long (as the table is built)."""
    a = sim.scaled_matrices(np.linspace(*sim.nu_range, 9)) * (sim.dt_s * dyn.TIME_SCALE)
    assert a.shape[1:] == (dyn.N_REGIONS, dyn.NZ, dyn.NZ)
    assert _rel(expm_batch(a), expm(a)) < 1e-14


@pytest.mark.parametrize("norm", [0.5 * THETA[0], 0.5 * (THETA[0] + THETA[1]), 0.5 * (THETA[1] + THETA[2]),
                                  0.5 * (THETA[2] + THETA[3]), 0.5 * (THETA[3] + THETA[4]), 40.0])
def test_every_pade_degree_and_the_squarings_agree_with_scipy(norm: float) -> None:
    """Random 14 × 14 matrices scaled to a 1-norm in each degree's band, and one that needs squarings."""
    rng = np.random.default_rng(7)
    m = rng.normal(size=(20, 14, 14))
    m *= norm / np.linalg.norm(m, 1, axis=(1, 2))[:, None, None]
    assert _rel(expm_batch(m), expm(m)) < (1e-14 if norm <= THETA[4] else 1e-12)


def test_shapes_and_what_cannot_be_exponentiated() -> None:
    """A single matrix, a stack of any depth; NaN for a matrix with a non-finite entry (only that one);
    a clear error for a non-square input."""
    one = np.array([[0.0, 1.0], [-1.0, 0.0]])
    np.testing.assert_allclose(expm_batch(one), [[np.cos(1), np.sin(1)], [-np.sin(1), np.cos(1)]], rtol=1e-15, atol=1e-15)
    stack = np.stack([one, 2 * one, np.full((2, 2), np.nan)]).reshape((3, 1, 2, 2))
    out = expm_batch(stack)
    assert out.shape == (3, 1, 2, 2) and out.flags.c_contiguous
    np.testing.assert_allclose(out[1, 0], expm(2 * one), rtol=1e-14, atol=1e-15)
    assert np.isnan(out[2]).all() and np.isfinite(out[:2]).all()
    with pytest.raises(ValueError, match="square"):
        expm_batch(np.zeros((3, 2)))
