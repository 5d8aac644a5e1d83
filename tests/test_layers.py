"""Imports point one way: model/ident (numpy, scipy) <- codec (cantools) <- service (python-can) <- fleet (dask)."""

from __future__ import annotations

import ast

import pytest

from .conftest import REPO

FLEET = {"dask", "distributed", "estimator.fleet"}
FORBIDDEN = {
    "estimator/model": {"can", "cantools", "estimator.ident", "estimator.codec", "estimator.service", "sim_bench",
                        "logging", "socket", "threading"} | FLEET,
    "estimator/ident": {"can", "cantools", "estimator.codec", "estimator.service", "sim_bench", "socket",
                        "threading"} | FLEET,
    "estimator/codec": {"can", "estimator.service", "sim_bench", "socket", "threading"} | FLEET,
    "estimator/service": {"sim_bench"} | FLEET,
    "estimator/fleet": {"sim_bench"},
}


def imported_modules(path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module


def test_only_the_service_layer_imports_the_daemon():
    """The pipeline is built in :mod:`estimator.pipeline`; the daemon is one of its users, not its source."""
    for f in [*(REPO / "estimator").rglob("*.py"), *(REPO / "sim_bench").rglob("*.py")]:
        if f.parent.name == "service" and f.parent.parent.name == "estimator":
            continue
        bad = [m for m in imported_modules(f) if m == "estimator.service.daemon"]
        assert not bad, f"{f.relative_to(REPO)} imports estimator.service.daemon"


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_layer_imports(package):
    files = list((REPO / package).rglob("*.py"))
    assert files, package
    for f in files:
        for mod in imported_modules(f):
            for bad in FORBIDDEN[package]:
                assert not (mod == bad or mod.startswith(bad + ".")), f"{f.relative_to(REPO)} imports {mod}"


def test_numpy_runs_one_blas_thread_under_our_entry_points():
    """Spinning BLAS worker threads stall a loaded machine (docs: design decisions): importing the
    package first keeps OpenBLAS to the calling thread, unless the environment says otherwise."""
    import os
    import subprocess
    import sys
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    code = "import {}, numpy, os; print(len(os.listdir('/proc/self/task')))"
    for pkg in ("estimator", "sim_bench"):
        r = subprocess.run([sys.executable, "-c", code.format(pkg)], env=env, capture_output=True, text=True,
                           timeout=120, cwd=REPO)
        assert r.stdout.strip() == "1", (pkg, r.stdout, r.stderr)
