"""Where numba keeps the compiled kernels: a directory named after the compiled sources.

numba checks a cached function against the time stamp of its own source file only. A compiled
function that calls one in another file (``fit_kernel.warm_cycle`` calling ``kernel.run_batch``,
the kernel calling ``automaton`` and ``dynamics``) is therefore loaded stale from the cache after
that other file changed: silently the old arithmetic. Keying the cache directory by a hash of every
source file that defines compiled functions makes any change start a fresh cache.

The directory is ``$NUMBA_CACHE_DIR/numba-<hash>`` when the environment names a cache directory
(the systemd units do), else ``estimator/__pycache__/numba-<hash>`` beside the sources (shared by
every process of one installation, the fleet's workers included), else, if that is not writable,
``${XDG_CACHE_HOME:-~/.cache}/injector-estimator/numba-<hash>``. Directories of older versions are
left in place (a few MB each). This must run before numba is imported: :mod:`estimator._compiled`,
through which every compiled module gets ``njit``, calls :func:`configure` first.
"""

from __future__ import annotations

import hashlib
import os
import sys
from collections.abc import Mapping

PREFIX = "numba-"


def source_tag(root: str) -> str:
    """``numba-`` and 16 hex digits of the SHA-1 of every ``.py`` file under ``root`` that uses njit
    (its path relative to ``root`` and its bytes, in sorted order)."""
    h = hashlib.sha1()
    for dirpath, dirnames, files in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
        for name in sorted(files):
            if not name.endswith(".py"):
                continue
            path = os.path.join(dirpath, name)
            with open(path, "rb") as f:
                data = f.read()
            if b"njit" in data:
                h.update(os.path.relpath(path, root).encode())
                h.update(b"\0")
                h.update(data)
    return PREFIX + h.hexdigest()[:16]


def _writable(path: str) -> bool:
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return False
    return os.access(path, os.W_OK)


def cache_dir(root: str, environ: Mapping[str, str]) -> str:
    """The cache directory for the sources under ``root`` given the environment ``environ``."""
    tag = source_tag(root)
    base = environ.get("NUMBA_CACHE_DIR")
    if base:
        base = os.path.normpath(base)
        if os.path.basename(base).startswith(PREFIX):   # set by a parent process of ours
            base = os.path.dirname(base)
        return os.path.join(base, tag)
    beside = os.path.join(root, "__pycache__")
    if _writable(beside):
        return os.path.join(beside, tag)
    xdg = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(xdg, "injector-estimator", tag)


def configure() -> str:
    """Point numba's cache at :func:`cache_dir` for this package (environment, and numba's config if
    numba is already imported); returns the directory."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))   # the estimator package
    path = cache_dir(root, dict(os.environ))
    os.environ["NUMBA_CACHE_DIR"] = path
    numba = sys.modules.get("numba")
    if numba is not None:
        numba.config.CACHE_DIR = path
    return path
