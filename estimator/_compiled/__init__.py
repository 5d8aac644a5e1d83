"""numba plumbing: the cache keyed by the compiled sources (:mod:`.cache`), direct calls of one
overload (:mod:`.direct_call`) and filling the cache (:mod:`.precompile`).

Compiled modules take ``njit`` from here, not from numba: numba reads its cache directory when it is
imported, so this package points it at the directory keyed by the compiled sources first. Importing
:mod:`estimator` alone sets nothing up; the first compiled module does.

For the type checker ``njit(**options)`` returns the function it decorates with its own signature
(numba's decorator is untyped), so that a call of a compiled function is checked against its
annotations and returns what they declare.
"""

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from estimator._compiled import cache as _cache

_cache.configure()

if TYPE_CHECKING:
    _F = TypeVar("_F", bound=Callable[..., Any])

    def njit(**options: Any) -> Callable[[_F], _F]:
        """numba's ``njit`` with options, as the type checker sees it."""
else:
    from numba import njit

__all__ = ["njit"]
