"""numba plumbing: the cache keyed by the compiled sources (:mod:`.cache`), direct calls of one
overload (:mod:`.direct_call`) and filling the cache (:mod:`.precompile`).

Compiled modules take ``njit`` from here, not from numba: numba reads its cache directory when it is
imported, so this package points it at the directory keyed by the compiled sources first. Importing
:mod:`estimator` alone sets nothing up; the first compiled module does.
"""

from estimator._compiled import cache as _cache

_cache.configure()

from numba import njit  # noqa: E402  (after the cache directory is set)

__all__ = ["njit"]
