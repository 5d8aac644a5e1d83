"""The numba cache is keyed by the compiled sources: a change in any of them starts a fresh cache
(numba itself checks only a function's own file, so a caller in another file would load stale)."""

from __future__ import annotations

import os
import subprocess
import sys

from estimator._compiled import cache as numba_cache


def _package(tmp_path):
    root = tmp_path / "pkg"
    (root / "sub").mkdir(parents=True)
    (root / "kernel.py").write_text("from numba import njit\n@njit\ndef f(x):\n    return x + 1\n")
    (root / "sub" / "caller.py").write_text("from numba import njit\n@njit\ndef g(x):\n    return x\n")
    (root / "service.py").write_text("def h():\n    return 1\n")
    return root


def test_the_tag_follows_every_compiled_source_and_nothing_else(tmp_path):
    root = _package(tmp_path)
    tag = numba_cache.source_tag(str(root))
    assert tag.startswith("numba-") and len(tag) == 22
    (root / "service.py").write_text("def h():\n    return 2\n")          # no compiled code in it
    assert numba_cache.source_tag(str(root)) == tag
    (root / "kernel.py").write_text("from numba import njit\n@njit\ndef f(x):\n    return x + 2\n")
    changed = numba_cache.source_tag(str(root))
    assert changed != tag
    (root / "sub" / "caller.py").write_text("from numba import njit\n@njit\ndef g(x):\n    return -x\n")
    assert numba_cache.source_tag(str(root)) not in (tag, changed)


def test_the_cache_directory_under_the_environment_beside_the_sources_or_the_user_cache(tmp_path):
    root = _package(tmp_path)
    tag = numba_cache.source_tag(str(root))
    assert numba_cache.cache_dir(str(root), {"NUMBA_CACHE_DIR": "/var/cache/est"}) == f"/var/cache/est/{tag}"
    # a child process inherits its parent's directory: the tag is replaced, not nested
    assert numba_cache.cache_dir(str(root), {"NUMBA_CACHE_DIR": "/var/cache/est/numba-0123"}) == \
        f"/var/cache/est/{tag}"
    assert numba_cache.cache_dir(str(root), {}) == str(root / "__pycache__" / tag)
    (root / "__pycache__").rmdir()
    (root / "__pycache__").write_text("not a directory")            # sources not writable
    assert numba_cache.cache_dir(str(root), {"XDG_CACHE_HOME": str(tmp_path / "xdg")}) == \
        str(tmp_path / "xdg" / "injector-estimator" / tag)


def test_the_first_compiled_module_points_numba_at_its_tagged_directory(tmp_path):
    """Importing the package sets nothing up (numba not even imported); the first compiled module
    points numba at the directory keyed by the package's compiled sources."""
    code = ("import estimator, os, sys; print('numba' in sys.modules); import estimator.model.kernel, numba; "
            "from estimator._compiled import cache as n; "
            "print(numba.config.CACHE_DIR); print(n.source_tag(os.path.dirname(estimator.__file__)))")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "nc"))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    loaded, where, tag = out.stdout.split()
    assert loaded == "False"
    assert where == str(tmp_path / "nc" / tag)
