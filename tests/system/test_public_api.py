"""The public API: ``estimator.__all__``, imported when first used, documented from that list, and
the module docstring's example works as written."""

from __future__ import annotations

import re
import subprocess
import sys

import numpy as np
import pytest

import estimator

from ..conftest import REPO


def test_import_estimator_loads_nothing_heavy():
    code = ("import sys, estimator; heavy = [m for m in ('numpy', 'scipy', 'numba', 'can', 'cantools') "
            "if m in sys.modules]; print(heavy)")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr


def test_every_public_name_resolves_and_nothing_else_does():
    for name in estimator.__all__:
        assert getattr(estimator, name) is not None, name
    assert set(estimator.__all__) <= set(dir(estimator))
    with pytest.raises(AttributeError):
        estimator.no_such_thing  # noqa: B018


def test_the_api_page_is_built_from_all():
    text = (REPO / "docs" / "reference" / "api.md").read_text()
    assert re.search(r"automodule:: estimator\n", text)
    # no hand-written list of deep paths beside it
    assert not re.search(r"auto(function|class):: estimator\.\w+\.", text)


def test_the_docstring_example(tmp_path):
    from sim_bench.hardware.plant import Plant, PlantConfig

    m = Plant(PlantConfig()).measure(17.0, 3.0e-6, 28.0, np.random.default_rng(1))
    path = tmp_path / "shot.csv"
    estimator.write_trace(path, {"t_s": np.arange(m.current_a.size) * m.dt_s, "current_A": m.current_a,
                                 "voltage_V": m.voltage_v}, {"preload_force_n": 28.0})
    inj = estimator.injection_from_trace(estimator.read_trace(path))
    est = estimator.identify(inj)
    assert est.status == estimator.Status.OK and abs(est.lh_m * 1e6 - 3.0) < 0.3
    res = estimator.Tracker().update(inj)
    assert isinstance(res, estimator.TrackResult)
    rows = list(estimator.iter_estimates(path))
    assert len(rows) == 1 and rows[0]["status"] == "ok" and "drive_scale" in rows[0]
