"""The fast simulator and the event-located reference against each other and the exact LTI solution."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from estimator.model.drive import sample_times, standard_drive
from estimator.model.reference_sim import simulate_reference

DT = 0.5e-6


def independent_psa_lti(p, nu):
    """A, b, c, d of eqs. 23-24 written out from eqs. 17-20 (current input, F_ext = 0)."""
    a, v = p.psa, nu
    c_el = v ** 2 / a.ks_n_per_m
    bp = a.rb_v2s_per_mn * v ** 2
    kt = a.kp_n_per_m + v ** 2 / c_el
    m1, m2, m3 = a.m1_kg, a.m2_kg, a.m3_kg
    kg1, kg2, bg1, bg2 = a.kg1_n_per_m, a.kg2_n_per_m, a.bg1_ns_per_m, a.bg2_ns_per_m
    A = np.zeros((7, 7))
    A[0, 1] = A[2, 3] = A[4, 5] = 1.0
    A[1] = [-(kg1 + kg2) / m1, -(bg1 + bg2) / m1, kg2 / m1, bg2 / m1, 0, 0, 0]
    A[3] = [kg2 / m2, bg2 / m2, -(kg2 + kt) / m2, -(bg2 + bp) / m2, kt / m2, bp / m2, -(v / c_el) / m2]
    A[5] = [0, 0, kt / m3, bp / m3, -kt / m3, -bp / m3, (v / c_el) / m3]
    b = np.zeros(7)
    b[6] = 1.0
    c = np.array([0, 0, v / c_el, 0, -v / c_el, 0, 1 / c_el])
    d = a.r0a_ohm * np.exp(-a.r0b_v_per_n * v)
    return A, b, c, d


def exact_foh_response(A, b, c, d, current, dt):
    """Exact response to a current that is linear between samples (block matrix exponential)."""
    n = A.shape[0]
    m = np.zeros((n + 2, n + 2))
    m[:n, :n] = A
    m[:n, n] = b
    m[n, n + 1] = 1.0
    e = expm(m * dt)
    phi, g0, g1 = e[:n, :n], e[:n, n], e[:n, n + 1]
    x = np.zeros(n)
    u = np.empty(current.size)
    u[0] = c @ x + d * current[0]
    for k in range(current.size - 1):
        x = phi @ x + g0 * current[k] + g1 * (current[k + 1] - current[k]) / dt
        u[k + 1] = c @ x + d * current[k + 1]
    return u


@pytest.mark.parametrize("nu", [15.2, 16.39, 20.7])
def test_no_contact_matches_exact_lti(params, sim, nu):
    t = sample_times(400e-6)
    rng = np.random.default_rng(3)
    current = standard_drive(t) * (1 + 0.03 * rng.standard_normal(t.size))
    exact = exact_foh_response(*independent_psa_lti(params, nu), current, DT)
    lh_far = 1e-3  # 1 mm: the stack never reaches the piston
    scale = np.max(np.abs(exact))
    for result in (sim.simulate(current, nu, lh_far, exact=True), sim.simulate(current, nu, lh_far),
                   simulate_reference(current, nu, lh_far)):
        assert result.success[0]
        assert np.all(result.mode == 1)
        assert np.max(np.abs(result.voltage_v[0] - exact)) <= 1e-9 * scale


@pytest.mark.parametrize("lh_um", [-1.0, 0.6, 2.5, 6.8, 8.4])
def test_fast_matches_reference_with_contact(sim, lh_um):
    t = sample_times(500e-6)
    current = standard_drive(t)
    fast = sim.simulate(current, 16.39, lh_um * 1e-6)
    ref = simulate_reference(current, 16.39, lh_um * 1e-6)
    assert fast.success[0] and ref.success[0]
    assert np.max(np.abs(fast.voltage_v - ref.voltage_v)) <= 0.05
    assert abs(fast.t_open_s[0] - ref.t_open_s[0]) <= 0.25e-6
    assert abs(fast.plateau_stroke_m()[0] - ref.plateau_stroke_m()[0]) <= 0.02e-6
    assert np.isfinite(fast.t_open_s[0]) and fast.plateau_stroke_m()[0] > 10e-6
    assert np.mean(fast.mode == ref.mode) > 0.998


def test_rippled_current_full_cycle_with_closing(sim):
    """A chopper-like current with a kink at every sample, through opening and closing."""
    t = sample_times(800e-6)
    current = standard_drive(t) * (1 + 0.05 * np.sin(2 * np.pi * t / 7.3e-6))
    fast = sim.simulate(current, 18.0, 3.0e-6)
    ref = simulate_reference(current, 18.0, 3.0e-6)
    assert np.max(np.abs(fast.voltage_v - ref.voltage_v)) <= 0.05
    assert np.max(np.abs(fast.s4_m - ref.s4_m)) <= 0.02e-6
    modes = fast.mode[0]
    assert {1, 2, 3} <= set(modes.tolist())
    assert modes[-1] in (1, 2) and fast.s4_m[0, -1] == 0.0  # the valve has closed again


def test_table_interpolation_matches_direct_expm(sim):
    nu = np.array([15.013, 16.39, 17.777, 20.991])
    interp = sim.transition_matrices(nu)
    exact = sim.transition_matrices(nu, exact=True)
    assert np.max(np.abs(interp - exact)) <= 1e-12 * np.max(np.abs(exact))


def test_batch_equals_individual_runs(sim):
    t = sample_times(100e-6)
    current = standard_drive(t)
    nu = np.array([15.5, 16.4, 19.0, 20.5])
    lh = np.array([-1.5e-6, 0.3e-6, 4e-6, 9e-6])
    batch = sim.simulate(current, nu, lh)
    for i in range(nu.size):
        one = sim.simulate(current, nu[i], lh[i])
        np.testing.assert_array_equal(one.voltage_v[0], batch.voltage_v[i])
        assert one.t_contact_s[0] == batch.t_contact_s[i] or np.isnan(one.t_contact_s[0])


def test_infeasible_candidates_are_reported_not_raised(sim):
    t = sample_times(100e-6)
    res = sim.simulate(standard_drive(t), 16.39, [-3e-6, 2e-6])
    assert res.success.tolist() == [False, True]
    assert res.message[0] == "infeasible initial state"
    assert np.all(np.isnan(res.voltage_v[0])) and np.all(np.isfinite(res.voltage_v[1]))


def test_absurd_inputs_raise_clear_errors(sim):
    t = sample_times(100e-6)
    cur = standard_drive(t)
    with pytest.raises(ValueError, match=r"N_u = 30.0 N/V is outside"):
        sim.simulate(cur, 30.0, 1e-6)
    with pytest.raises(ValueError, match="finite"):
        sim.simulate(np.full(10, np.nan), 16.0, 1e-6)
    with pytest.raises(ValueError, match="finite"):
        sim.simulate(cur, 16.0, np.nan)


def test_higher_preload_delays_opening(sim):
    t = sample_times(200e-6)
    res = sim.simulate(standard_drive(t), 16.39, 2.5e-6, f_open_n=[28.0, 150.0])
    assert res.t_contact_s[0] == pytest.approx(res.t_contact_s[1])
    assert res.t_open_s[1] > res.t_open_s[0] + 1e-6


@pytest.mark.parametrize("nu,lh_um,phase", [(20.969906, 9.2585, 0.3), (19.734610, 9.929008, 0.1)])
def test_valve_hovering_at_its_threshold_does_not_chatter(sim, nu, lh_um, phase):
    """Charge held while the valve is at its opening threshold and the piston rings: the reset
    v4 := v3 would send the plunger into its seat (Zeno); the model lifts it from rest instead and,
    after a re-seat, asks for a positive net lift-off force. Both simulators agree."""
    from sim_bench.hardware.plant import PlantConfig, true_current

    t = sample_times(300e-6)
    cur = np.where(t <= 100e-6 + 1e-12, true_current(t, PlantConfig(), phase), 0.0)
    fast = sim.simulate(cur, nu, lh_um * 1e-6)
    ref = simulate_reference(cur, nu, lh_um * 1e-6)
    assert fast.success[0] and ref.success[0]
    assert np.max(np.abs(fast.voltage_v - ref.voltage_v)) <= 0.05
    assert np.max(np.abs(fast.s4_m - ref.s4_m)) <= 0.02e-6
    assert np.isfinite(fast.t_open_s[0]) and fast.t_open_s[0] > 100e-6     # opened after the current stopped


def test_plant_window_longer_than_the_plateau_window():
    """A measuring window past 490 µs (the end of Table 3's plateau window) is simulated in full."""
    from sim_bench.hardware.plant import Plant, PlantConfig

    m = Plant(PlantConfig(window_s=600e-6)).measure(17.0, 3e-6, 28.0, np.random.default_rng(1))
    assert m.current_a.size == 1201 and np.isfinite(m.voltage_v).all() and np.isfinite(m.stroke_m)
