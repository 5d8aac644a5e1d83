"""Imports point one way: model/ident (numpy, scipy) <- codec (cantools) <- service (python-can)."""

from __future__ import annotations

import ast

import pytest

from .conftest import REPO

FORBIDDEN = {
    "estimator/model": {"can", "cantools", "estimator.ident", "estimator.codec", "estimator.service", "sim_bench",
                        "logging", "socket", "threading"},
    "estimator/ident": {"can", "cantools", "estimator.codec", "estimator.service", "sim_bench", "socket",
                        "threading"},
    "estimator/codec": {"can", "estimator.service", "sim_bench", "socket", "threading"},
    "estimator/service": {"sim_bench"},
}


def imported_modules(path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_layer_imports(package):
    files = list((REPO / package).rglob("*.py"))
    assert files, package
    for f in files:
        for mod in imported_modules(f):
            for bad in FORBIDDEN[package]:
                assert not (mod == bad or mod.startswith(bad + ".")), f"{f.relative_to(REPO)} imports {mod}"
