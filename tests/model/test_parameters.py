"""Parameter data file and validated parameter objects."""

from __future__ import annotations

import dataclasses
import math
import re

import pytest

from estimator.errors import ParameterError
from estimator.model.parameters import NOMINAL_FILE, PsaParameters, ValveParameters, load_nominal


def test_every_value_is_traced_to_a_table():
    for line in NOMINAL_FILE.read_text().splitlines():
        if "=" in line and not line.lstrip().startswith("#"):
            assert re.search(r"# Table [12]: ", line), f"untraced parameter line: {line}"


def test_nominal_values_in_si(params):
    assert params.psa.kp_n_per_m == 62.15e6
    assert params.psa.m1_kg == pytest.approx(27.764e-3)
    assert params.valve.sp_m == pytest.approx(2.04e-6)
    # "N/ms" in the paper is N/(m/s): b_v = 93.4 N*s/m, and R_b is V^2*s/(m*N)
    assert params.valve.bv_ns_per_m == 93.4
    assert params.psa.damping_ns_per_m(16.39) == pytest.approx(3.33 * 16.39 ** 2)


def test_derived_relations(params):
    nu = 17.0
    assert params.psa.capacitance_f(nu) == pytest.approx(nu ** 2 / 118.72e6)           # eq. 21
    assert params.psa.resistance_ohm(nu) == pytest.approx(1764.4 * math.exp(-0.4558 * nu))  # eq. 22


def test_objects_are_frozen(params):
    with pytest.raises(dataclasses.FrozenInstanceError):
        params.psa.m1_kg = 1.0  # type: ignore[misc]


@pytest.mark.parametrize("field,value,needle", [
    ("m1_kg", -1.0, "m1_kg = -1.0 kg"),
    ("ks_n_per_m", float("nan"), "ks_n_per_m = nan N/m"),
    ("bg1_ns_per_m", -5.0, "N*s/m: must be >= 0"),
])
def test_invalid_psa_values_name_value_and_unit(params, field, value, needle):
    with pytest.raises(ParameterError, match=re.escape(needle)):
        dataclasses.replace(params.psa, **{field: value})


def test_invalid_valve_value(params):
    with pytest.raises(ParameterError, match=r"m4_kg = 0.0 kg"):
        dataclasses.replace(params.valve, m4_kg=0.0)


def test_nu_range_is_configurable_and_checked(params):
    narrow = params.psa.with_nu_range(16.0, 17.0)
    assert narrow.check_nu(16.5) == 16.5
    with pytest.raises(ParameterError, match=r"N_u = 17.5 N/V is outside \[16.0, 17.0\] N/V"):
        narrow.check_nu(17.5)
    with pytest.raises(ParameterError):
        params.psa.with_nu_range(18.0, 17.0)


def test_unknown_or_missing_fields_rejected():
    with pytest.raises(ParameterError, match="unknown PSA parameter"):
        PsaParameters.from_mapping({"m1_kg": 1.0, "bogus": 2.0})
    with pytest.raises(ParameterError, match="incomplete"):
        ValveParameters.from_mapping({"m4_kg": 1.0})


def test_load_nominal_is_cached():
    assert load_nominal() is load_nominal()
