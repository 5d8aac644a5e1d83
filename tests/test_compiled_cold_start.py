"""The automatic local-first cold start in one compiled call against its Python reference."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.ident import compiled_cold_start as ccs
from estimator.ident import idle_stroke
from estimator.ident.config import IdentConfig
from estimator.model.fast_sim import FastSimulator
from sim_bench.plant import AdcConfig

from .helpers import measured

# (N_u, L_h µm, seed, mismatch plant, plant options): lot-like injectors, the edges of the N_u range
# (one fit at a bound: refused), contact in the first samples, pre-compressed starts and a contact
# near the L_h bound (the Python path), noise, and the hysteresis plant (the robust fit chosen; at low
# noise its residual check fails)
CASES = [(17.0, 3.0, 1, False, {}), (16.2, 4.5, 2, False, {}), (18.6, 6.0, 3, False, {}), (15.2, 2.0, 4, False, {}),
         (20.8, 5.0, 5, False, {}), (21.0995, 4.0, 7, False, {}), (14.9005, 3.0, 8, False, {}),
         (17.5, 0.05, 6, False, {}), (16.0, 0.4, 7, False, {}), (17.0, -0.5, 4, False, {}), (16.0, 9.95, 3, False, {}),
         (17.0, 3.5, 9, False, {"adc": AdcConfig(voltage_noise_v=0.5)}), (16.0, 4.0, 48, True, {}),
         (18.0, 2.5, 10, True, {}), (15.5, 6.5, 11, True, {}),
         (15.3, 4.3, 31, True, {"adc": AdcConfig(voltage_noise_v=0.05)}),
         (18.156, 7.886, 298, True, {})]   # the last: the ring finds a lower point (1 of 600 random injections)


def _auto(sim, inj, cfg, compiled):
    box = idle_stroke.search_box(cfg, sim, inj.f_open_n)
    m_p = idle_stroke._cost_model(sim, inj, cfg, False)
    m_r = idle_stroke._cost_model(sim, inj, cfg, True)
    est = idle_stroke._local_first_auto(sim, inj, m_p, m_r, np.array(cfg.start_point), box, cfg, compiled=compiled)
    return est, (m_p.evaluations, m_r.evaluations)


def test_the_compiled_automatic_cold_start_is_the_python_one(monkeypatch):
    """The same outcome (an estimate, or None: the global search follows), the same simulations counted,
    the same estimate to the bit and the same plain/robust choice; the model-error statistic to rounding
    (its projection is summed in loops). Every outcome occurs: done, the local fits refused, and a
    hand-over to Python (an L_h <= 0 point), which then counts only the Python path's simulations; a
    ring that finds a lower point; and with the threshold moved just above or below the statistic
    (both fits ringed, the choice flipped) in both."""
    sim = FastSimulator()
    codes: list[int] = []
    real = ccs._local_first_auto

    def recording(*args):
        out = real(*args)
        codes.append(int(out[0]))
        return out
    monkeypatch.setattr(ccs, "_local_first_auto", recording)
    cfg = IdentConfig()
    robust_seen = 0
    for nu, lh, seed, mismatch, kw in CASES:
        inj, _ = measured(nu, lh, seed, mismatch, **kw)
        configs = [cfg]
        got, ev = _auto(sim, inj, cfg, True)
        want, ev_py = _auto(sim, inj, cfg, False)
        if want is not None:   # the choice made close (the other fit ringed too), either way
            stat = abs(want.model_error_stat)
            configs += [IdentConfig(model_error_threshold=stat + 4.0), IdentConfig(model_error_threshold=max(stat - 0.5, 0.1))]
        for c in configs:
            got, ev = _auto(sim, inj, c, True)
            want, ev_py = _auto(sim, inj, c, False)
            case = (nu, lh, seed, mismatch, c.model_error_threshold)
            assert (got is None) == (want is None) and ev == ev_py, case
            if want is None:
                continue
            assert (got.nu_n_per_v, got.lh_m, got.status, got.evaluations, got.robust) == \
                (want.nu_n_per_v, want.lh_m, want.status, want.evaluations, want.robust), case
            assert np.array_equal(got.cov, want.cov) and got.t_open_s == want.t_open_s, case
            assert got.model_error_stat == pytest.approx(want.model_error_stat, rel=1e-9, abs=1e-9), case
            robust_seen += got.robust
    assert {ccs.AUTO_DONE, ccs.AUTO_GLOBAL, ccs.AUTO_PYTHON} <= set(codes), codes
    assert robust_seen >= 10


def test_compiled_statistics_are_the_python_ones():
    """The likelihood ratio and the excess-residual test of :mod:`compiled_cold_start` equal
    :func:`model_selection.likelihood_ratio` and :func:`cold_start.excess_residual_z` to rounding."""
    from estimator.ident.cold_start import excess_residual_z
    from estimator.ident.compiled_cycle import run_forward_fit
    from estimator.ident.local_fit import FD_STEP, from_cycle_fit
    from estimator.ident.model_selection import likelihood_ratio
    from estimator.model.direct_call import c_float
    sim = FastSimulator()
    cfg = IdentConfig()
    for mismatch in (False, True):
        inj, _ = measured(16.5, 3.5, 21, mismatch)
        box = idle_stroke.search_box(cfg, sim, inj.f_open_n)
        m_p = idle_stroke._cost_model(sim, inj, cfg, False)
        m_r = idle_stroke._cost_model(sim, inj, cfg, True)
        cf_p = run_forward_fit(m_p, np.array([16.45, 3.45]), FD_STEP, box)
        cf_r = run_forward_fit(m_r, np.array([16.52, 3.55]), FD_STEP, box)
        f_p, f_r = from_cycle_fit(cf_p), from_cycle_fit(cf_r)
        want = likelihood_ratio(m_p, f_p, m_r, f_r)
        assert ccs.likelihood_ratio(tuple(cf_p), tuple(cf_r), c_float(m_p.basis)) == pytest.approx(want, rel=1e-9)
        for m, f, cf in ((m_p, f_p, cf_p), (m_r, f_r, cf_r)):
            z = ccs.excess_residual_z(tuple(cf), m.n, c_float(m.basis), m.robust)
            assert z == pytest.approx(excess_residual_z(m, f), rel=1e-9)
