"""Shared fixtures: the nominal parameters and one fast simulator per test session."""

from __future__ import annotations

from pathlib import Path

import estimator  # noqa: F401  (first: it limits BLAS to one thread before numpy loads)

import pytest

from estimator.model.fast_sim import FastSimulator
from estimator.model.parameters import InjectorParameters, load_nominal

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def params() -> InjectorParameters:
    return load_nominal()


@pytest.fixture(scope="session")
def sim() -> FastSimulator:
    return FastSimulator()
