"""The hysteresis element: its voltage, its simulation in both simulators, parameter files, and what it
does for a part whose hysteresis R(N_u)·I cannot explain."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from estimator.errors import ParameterError
from estimator.ident.fit.idle_stroke import identify
from estimator.ident.status import Status
from estimator.model.drive import StandardDrive, sample_times
from estimator.model.fast_sim import FastSimulator
from estimator.model.hysteresis import NO_HYSTERESIS, Hysteresis, element_voltage, play_sum_into
from estimator.model.parameters import InjectorParameters, load_nominal
from estimator.model.reference_sim import simulate_reference
from sim_bench.benches.ident_bench import _injection
from sim_bench.hardware.plant import (
    PI_NU_REF_N_PER_V,
    PI_THRESHOLDS_C,
    PI_WEIGHTS_V_PER_C,
    SERIES_RESISTANCE_OHM,
    Plant,
    PlantConfig,
    pi_hysteresis,
)

#: the mismatch plant's own hysteresis as an element
PLANTS = Hysteresis(tuple(PI_THRESHOLDS_C), tuple(PI_WEIGHTS_V_PER_C), SERIES_RESISTANCE_OHM, PI_NU_REF_N_PER_V)


def _current() -> np.ndarray:
    return StandardDrive().current(sample_times(200e-6, 0.5e-6))


def test_the_play_sum_is_the_prandtl_ishlinskii_operator_of_the_charge():
    """Against the plant's own operator (play operators of the trapezoidal charge, written apart)."""
    rng = np.random.default_rng(2)
    cur = np.concatenate([np.linspace(0, 8, 60), rng.normal(5, 3, 200), np.linspace(2, -6, 80)])
    dt = 0.5e-6
    q = np.concatenate(([0.0], np.cumsum(0.5 * (cur[1:] + cur[:-1]) * dt)))
    out = np.empty(cur.size)
    play_sum_into(cur, dt, np.array(PI_THRESHOLDS_C), np.array(PI_WEIGHTS_V_PER_C), out)
    np.testing.assert_allclose(out, pi_hysteresis(q), rtol=1e-12, atol=1e-12)


def test_the_element_replaces_r_i_by_its_own_voltage_in_the_fast_and_the_reference_simulator():
    """U with the element = U without it - R(N_u) I + R_s I + s(N_u) H[Q], at several N_u; the
    reference simulator (ODE solver) agrees with the fast one; the valve's motion is the same."""
    p = load_nominal()
    ph = replace(p, hysteresis=PLANTS)
    cur = _current()
    nu = np.array([15.5, 17.0, 21.0])
    plain, with_element = FastSimulator(p).simulate(cur, nu, 3e-6, 100.0), FastSimulator(ph).simulate(cur, nu, 3e-6, 100.0)
    for b, n in enumerate(nu):
        expected = plain.voltage_v[b] - p.psa.resistance_ohm(n) * cur + element_voltage(PLANTS, p.psa.r0b_v_per_n, cur, 0.5e-6, n)
        np.testing.assert_allclose(with_element.voltage_v[b], expected, atol=1e-9)
        np.testing.assert_array_equal(with_element.s4_m[b], plain.s4_m[b])
    assert element_voltage(PLANTS, p.psa.r0b_v_per_n, cur, 0.5e-6, 17.0).max() > 3.0   # volts: not a rounding
    ref = simulate_reference(cur, 17.0, 3e-6, 100.0, params=ph)
    np.testing.assert_allclose(ref.voltage_v[0], with_element.voltage_v[1], atol=1e-6)


def test_without_an_element_nothing_changes():
    p = load_nominal()
    assert p.hysteresis == NO_HYSTERESIS and not p.hysteresis.present
    cur = _current()
    a = FastSimulator(p).simulate(cur, 17.0, 3e-6, 100.0).voltage_v
    b = FastSimulator(replace(p, hysteresis=Hysteresis())).simulate(cur, 17.0, 3e-6, 100.0).voltage_v
    np.testing.assert_array_equal(a, b)
    assert element_voltage(NO_HYSTERESIS, 0.1, cur, 0.5e-6, 17.0).tolist() == [0.0] * cur.size


def test_a_part_whose_hysteresis_the_tables_cannot_explain_is_estimated_ok_with_its_element():
    """The mismatch plant (Goldfarb–Celanovic hysteresis and a series resistance): the paper's model
    calls every injection model_mismatch; with the part's element every one is ok and within 3 sigma."""
    p = load_nominal()
    plant = Plant(PlantConfig(mismatch=True), p)
    sim0, simh = FastSimulator(p), FastSimulator(replace(p, hysteresis=PLANTS))
    rng = np.random.default_rng(11)
    for _ in range(4):
        nu, lh, f = rng.uniform(16, 21), rng.uniform(1e-6, 8e-6), rng.uniform(28, 300)
        inj = _injection(plant.measure(nu, lh, f, rng), f)
        assert identify(inj, sim0).status == Status.MODEL_MISMATCH
        est = identify(inj, simh)
        assert est.status == Status.OK
        assert abs(est.lh_m * 1e6 - lh * 1e6) <= 3 * np.sqrt(est.cov_um[1, 1]) + 0.01
        assert abs(est.nu_n_per_v - nu) <= 3 * np.sqrt(est.cov_um[0, 0]) + 0.01


def test_a_parameter_file_carries_the_element_and_refuses_a_bad_one(tmp_path):
    ph = replace(load_nominal(), hysteresis=Hysteresis((0.0, 0.05e-3, 0.15e-3), (80e3, -70e3, -3e3), 0.2))
    path = tmp_path / "part.toml"
    path.write_text(ph.to_toml())
    assert "[hysteresis]" in path.read_text()
    assert InjectorParameters.from_toml(path) == ph
    assert InjectorParameters.from_mapping(ph.to_mapping()) == ph
    assert "[hysteresis]" not in load_nominal().to_toml() and "hysteresis" not in load_nominal().to_mapping()
    for bad, needle in (({"thresholds_c": [0.0, 1e-4], "weights_v_per_c": [1.0]}, "same length"),
                        ({"thresholds_c": [1e-4, 0.0], "weights_v_per_c": [1.0, 1.0]}, "rise strictly"),
                        ({"thresholds_c": [0.0], "weights_v_per_c": [float("nan")]}, "weights_v_per_c"),
                        ({"series_ohm": -1.0}, "series_ohm"), ({"gain": 1.0}, "unknown hysteresis"),
                        ({"thresholds_c": "0.0"}, "list of numbers")):
        with pytest.raises(ParameterError, match=needle):
            Hysteresis.from_mapping(bad)
