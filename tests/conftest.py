"""Shared fixtures: the nominal parameters and one fast simulator per test session."""

from __future__ import annotations

import logging
from pathlib import Path

from estimator.runtime import prepare_process

prepare_process()   # as the entry points do: one BLAS thread, before numpy loads

import pytest  # noqa: E402

from estimator._compiled.direct_call import verify_types  # noqa: E402
from estimator.model.fast_sim import FastSimulator  # noqa: E402
from estimator.model.parameters import InjectorParameters, load_nominal  # noqa: E402
from sim_bench.hardware.hub import Hub  # noqa: E402
from sim_bench.hardware.procs import BusMonitor  # noqa: E402

REPO = Path(__file__).resolve().parents[1]

# every DirectCall checks its argument types against its overload in the tests (a caller that passes
# another dtype or layout fails instead of being read as the first call's types)
verify_types(True)


@pytest.fixture(autouse=True)
def _process_logging_left_behind():
    """A command run in-process configures logging for its process (``estimator.logfmt.configure``: a
    root handler on the stderr of the moment, which under ``capsys`` is a stream pytest closes after the
    test). That handler goes with the test: left behind, every later record of the worker, such as a
    daemon thread's, fails on the closed stream with a "Logging error" traceback."""
    root = logging.getLogger()
    level = root.level
    yield
    left = [h for h in root.handlers if type(h) is logging.StreamHandler]
    for h in left:
        root.removeHandler(h)
    if left:
        root.setLevel(level)


@pytest.fixture(scope="session")
def params() -> InjectorParameters:
    return load_nominal()


@pytest.fixture(scope="session")
def sim() -> FastSimulator:
    return FastSimulator()


@pytest.fixture()
def hub(tmp_path):
    """A loopback CAN hub (python-can-remote on 127.0.0.1) for real processes."""
    with Hub(log_path=tmp_path / "hub.log") as h:
        yield h


@pytest.fixture()
def monitor(hub, tmp_path):
    """Everything on the hub, decoded, and written to ``tmp_path/capture.log`` (candump -L)."""
    m = BusMonitor(hub.spec, capture=tmp_path / "capture.log")
    m.start()
    yield m
    m.close()
