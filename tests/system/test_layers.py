"""Imports point one way: model/ident (numpy, scipy; inside ident: fit <- learning <- tracking) <- codec (cantools) <- io (trace files, python-can's
capture files) <- pipeline (configuration, builders, processing, offline runs) <- service (the live bus,
threads) <- fleet (dask) <- the command lines. Lazy imports inside functions count too."""

from __future__ import annotations

import ast

import pytest

from ..conftest import REPO

FLEET = {"dask", "distributed", "estimator.fleet"}
ENTRY = {"estimator.cli", "estimator.cli_support", "estimator.runtime", "estimator.__main__"}
ABOVE_PIPELINE = {"estimator.service", "estimator.plots", "sim_bench", "socket", "threading"} | FLEET | ENTRY
ABOVE_IO = {"estimator.pipeline"} | ABOVE_PIPELINE
ABOVE_CODEC = {"can", "estimator.io"} | ABOVE_IO
FORBIDDEN = {
    "estimator/_compiled": {"cantools", "estimator.model", "estimator.ident", "estimator.codec"} | ABOVE_CODEC,
    "estimator/model": {"cantools", "estimator.ident", "estimator.codec", "logging"} | ABOVE_CODEC,
    "estimator/ident": {"cantools", "estimator.codec", "estimator.drive"} | ABOVE_CODEC,
    # inside it, rooms: one injection's fit <- an injector's own model <- the recursive estimator
    "estimator/ident/fit": {"estimator.ident.tracking", "estimator.ident.learning", "cantools", "estimator.codec",
                            "estimator.drive"} | ABOVE_CODEC,
    "estimator/ident/learning": {"estimator.ident.tracking", "cantools", "estimator.codec",
                                 "estimator.drive"} | ABOVE_CODEC,
    "estimator/drive": {"cantools", "estimator.codec"} | ABOVE_CODEC,
    "estimator/codec": ABOVE_CODEC,
    "estimator/io": ABOVE_IO,
    "estimator/pipeline": {"can"} | ABOVE_PIPELINE,
    "estimator/service": {"sim_bench", "estimator.plots"} | FLEET | ENTRY,
    "estimator/plots": {"sim_bench"} | FLEET | ENTRY,
    "estimator/fleet": {"sim_bench"} | ENTRY,
    # the simulated hardware knows nothing of the benches that score it
    "sim_bench/hardware": {"sim_bench.benches", "sim_bench.cli", "sim_bench.entry"},
}
#: the modules the package's root holds on purpose, each with what it must not import: what every layer
#: shares imports no layer; the entry points and the command lines may import any
ROOT_MODULES = {
    "errors.py": {"estimator", "can", "cantools", "numpy"},
    "choices.py": {"estimator", "can", "cantools", "numpy"},
    "logfmt.py": {"estimator", "can", "cantools", "numpy"},
    "units.py": {"estimator", "can", "cantools", "numpy"},
    "__init__.py": {"can", "cantools", "numpy"},   # lazy: importlib by name, checked in test_public_api
    "runtime.py": {"can", "cantools", "numpy", "estimator.service", "estimator.pipeline"},
    "__main__.py": set(),
    "cli.py": set(),
    "cli_support.py": set(),
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


def test_every_module_is_in_a_layer():
    """A module outside the layers' folders is one of the few the package's root holds on purpose."""
    for f in (REPO / "estimator").rglob("*.py"):
        rel = f.relative_to(REPO / "estimator")
        if len(rel.parts) == 1:
            assert rel.name in ROOT_MODULES, f"estimator/{rel} is in no layer"
        else:
            assert f"estimator/{rel.parts[0]}" in FORBIDDEN, f"estimator/{rel} is in no layer"


def _upward(mod: str, forbidden: set[str]) -> str | None:
    return next((bad for bad in forbidden if mod == bad or mod.startswith(bad + ".")), None)


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_layer_imports(package):
    files = list((REPO / package).rglob("*.py"))
    assert files, package
    for f in files:
        for mod in imported_modules(f):
            own = mod == package.replace("/", ".") or mod.startswith(package.replace("/", ".") + ".")
            bad = None if own else _upward(mod, FORBIDDEN[package])
            assert bad is None, f"{f.relative_to(REPO)} imports {mod}"


@pytest.mark.parametrize("name", sorted(ROOT_MODULES))
def test_root_module_imports(name):
    f = REPO / "estimator" / name
    for mod in imported_modules(f):
        allowed = mod in ("estimator.errors",) and name != "errors.py"
        bad = None if allowed else _upward(mod, ROOT_MODULES[name])
        assert bad is None, f"estimator/{name} imports {mod}"


def test_the_layer_rules_catch_an_upward_import(tmp_path):
    """The check itself: a lazy import of the daemon's configuration inside a pipeline function is caught."""
    f = tmp_path / "x.py"
    f.write_text("def f():\n    from estimator.service.config import DaemonConfig\n    return DaemonConfig\n")
    mods = list(imported_modules(f))
    assert mods == ["estimator.service.config"]
    assert _upward(mods[0], FORBIDDEN["estimator/pipeline"]) == "estimator.service"
    assert _upward("estimator.pipeline.config", FORBIDDEN["estimator/io"]) == "estimator.pipeline"


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


#: the functions allowed past 80 lines, each with its reason in docs/design.md
LONG_FUNCTIONS = {("estimator/model/kernel.py", "simulate_kernel"), ("estimator/model/reference_sim.py", "simulate_reference"),
                  ("estimator/cli.py", "build_parser"), ("sim_bench/cli.py", "build_parser")}


def test_functions_a_reader_can_hold():
    """No function over 80 lines but the compiled kernel, the reference integrator and the argparse
    builders (docs/design.md says why)."""
    long = set()
    for f in [*(REPO / "estimator").rglob("*.py"), *(REPO / "sim_bench").rglob("*.py")]:
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > 80:
                long.add((str(f.relative_to(REPO)), node.name))
    assert long <= LONG_FUNCTIONS, sorted(long - LONG_FUNCTIONS)
    assert "reference integrator" in (REPO / "docs" / "design.md").read_text()


def _bare_factors(path):
    """Float literals 1e6 / 1e-6 outside a named module-level constant and argparse defaults."""
    tree = ast.parse(path.read_text())
    named = set()
    for node in tree.body:   # NAME = 1e6: a constant with its own name is its one source
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            named |= {id(n) for n in ast.walk(node)}
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == "default":
            named |= {id(n) for n in ast.walk(node)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, float) and node.value in (1e6, 1e-6) \
                and id(node) not in named:
            yield node.lineno


def test_units_are_converted_through_their_names():
    """µm <-> m, µs <-> s and the micro prefix: every factor is a name of estimator.units."""
    found = [f"{f.relative_to(REPO)}:{line}" for f in (REPO / "estimator").rglob("*.py") if f.name != "units.py"
             for line in _bare_factors(f)]
    assert not found, found


def test_the_units_check_catches_a_bare_factor(tmp_path):
    f = tmp_path / "x.py"
    f.write_text("SCALE = 1e6\n\ndef lh_um(lh_m):\n    return lh_m * 1e6\n")
    assert list(_bare_factors(f)) == [4]


def test_every_package_ships_in_the_wheel():
    """Each folder of the package with an ``__init__.py`` is listed in pyproject's setuptools packages
    (a folder left out installs nowhere; only the wheel's own test would notice)."""
    import sys

    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "estimator").rglob("__init__.py")}
    assert found <= listed, sorted(found - listed)
