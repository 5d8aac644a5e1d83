"""Imports point one way: model/ident (numpy, scipy) <- codec (cantools) <- service (python-can) <- fleet (dask)."""

from __future__ import annotations

import ast

import pytest

from ..conftest import REPO

FLEET = {"dask", "distributed", "estimator.fleet"}
FORBIDDEN = {
    "estimator/model": {"can", "cantools", "estimator.ident", "estimator.codec", "estimator.service", "sim_bench",
                        "logging", "socket", "threading"} | FLEET,
    "estimator/ident": {"can", "cantools", "estimator.codec", "estimator.service", "sim_bench", "socket",
                        "threading"} | FLEET,
    "estimator/codec": {"can", "estimator.service", "sim_bench", "socket", "threading"} | FLEET,
    "estimator/service": {"sim_bench", "estimator.plots"} | FLEET,
    "estimator/fleet": {"sim_bench"},
    "estimator/io": {"can", "cantools", "estimator.codec", "estimator.service", "estimator.plots", "sim_bench",
                     "socket", "threading"} | FLEET,
    "estimator/plots": {"sim_bench"} | FLEET,
    "estimator/_compiled": {"can", "cantools", "estimator.codec", "estimator.plots", "estimator.io", "sim_bench",
                            "socket", "threading"} | FLEET,
}
ROOT_MODULES = {"__init__.py", "__main__.py", "cli.py", "cli_support.py", "errors.py", "logfmt.py", "pipeline.py",
                "runtime.py", "choices.py"}   # the entry points, the composition root and what every layer shares


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


def test_every_module_is_in_a_layer():
    """A module outside the layers' folders is one of the few the package's root holds on purpose."""
    for f in (REPO / "estimator").rglob("*.py"):
        rel = f.relative_to(REPO / "estimator")
        if len(rel.parts) == 1:
            assert rel.name in ROOT_MODULES, f"estimator/{rel} is in no layer"
        else:
            assert f"estimator/{rel.parts[0]}" in FORBIDDEN, f"estimator/{rel} is in no layer"


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_layer_imports(package):
    files = list((REPO / package).rglob("*.py"))
    assert files, package
    for f in files:
        for mod in imported_modules(f):
            for bad in FORBIDDEN[package]:
                assert not (mod == bad or mod.startswith(bad + ".")), f"{f.relative_to(REPO)} imports {mod}"


def test_numpy_runs_one_blas_thread_under_our_entry_points():
    """Spinning BLAS worker threads stall a loaded machine (docs: design decisions): the command-line
    entry points keep OpenBLAS to the calling thread, unless the environment says otherwise; importing
    the package as a library changes nothing in the environment."""
    import os
    import subprocess
    import sys
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    # the entry point sets the variable (it runs before anything imports numpy), and one thread is what
    # numpy then starts with it
    at_exit = ("import atexit, runpy, sys; sys.argv = ['x', '--version']; "
               "atexit.register(lambda: print('blas', __import__('os').environ.get('OPENBLAS_NUM_THREADS'))); "
               "runpy.run_module('{}', run_name='__main__')")
    for pkg in ("estimator", "sim_bench"):
        r = subprocess.run([sys.executable, "-c", at_exit.format(pkg)], env=env, capture_output=True, text=True,
                           timeout=120, cwd=REPO)
        assert r.stdout.split()[-2:] == ["blas", "1"], (pkg, r.stdout, r.stderr)
    code = "from estimator.runtime import prepare_process; prepare_process(); import numpy, os; print(len(os.listdir('/proc/self/task')))"
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.stdout.strip() == "1", (r.stdout, r.stderr)
    r = subprocess.run([sys.executable, "-c", "import os, estimator; print(os.environ.get('OPENBLAS_NUM_THREADS'))"],
                       env=env, capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.stdout.strip() == "None", r.stderr
