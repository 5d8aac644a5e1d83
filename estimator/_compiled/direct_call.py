"""Calling one compiled overload without numba's per-call type dispatch.

numba's dispatcher works out the type of every argument on every call. For the warm cycle's 18
arguments that is 2.3-2.8 µs a call. The two named tuples of arrays (the kernel model and the
automaton) cost 1.3-1.4 µs each: named tuples miss numba's fast fingerprint path. That is about
1 % of a warm update, paid twice per update (warm cycle and valve prediction).

:class:`DirectCall` sends the first call through the dispatcher and later calls straight to the
entry point of the overload for those argument types. This is only for callers whose argument
types cannot change: every array argument built by the caller itself as a C-contiguous float64
array of fixed dimensions, and floats, ints and bools passed as such. Another array layout or
dtype would be read as if it had the first call's type. :func:`verify_types` makes every call check
its types against the overload's and raise ``TypeError`` on a mismatch; the test suite turns it
on (``tests/conftest.py``), so a caller that breaks the rule fails its tests. With numba's JIT
switched off (``NUMBA_DISABLE_JIT=1``, for debugging) the "dispatcher" is the plain Python function,
and a DirectCall simply calls it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

_verify = False


def c_float(a: Any) -> np.ndarray:
    """``a`` as a C-contiguous float64 array (no copy if it is one): the array form of a DirectCall's arguments."""
    return np.ascontiguousarray(a, dtype=float)


def verify_types(on: bool) -> None:
    """Check every direct call's argument types against its overload (slow: for tests)."""
    global _verify
    _verify = bool(on)


class DirectCall:
    """``dispatcher(*args)`` for arguments whose numba types never change (see the module docstring)."""

    def __init__(self, dispatcher: Any) -> None:
        self._dispatcher = dispatcher
        self._entry: Any = None
        self._types: tuple[Any, ...] = ()

    def _types_of(self, args: tuple[Any, ...]) -> tuple[Any, ...]:
        return tuple(self._dispatcher.typeof_pyval(a) for a in args)

    def __call__(self, *args: Any) -> Any:
        entry = self._entry
        if entry is None:
            out = self._dispatcher(*args)            # compiles or loads the overload
            if not hasattr(self._dispatcher, "compile"):   # NUMBA_DISABLE_JIT: a plain function, no overloads
                self._entry = self._dispatcher
                return out
            self._types = self._types_of(args)
            self._entry = self._dispatcher.compile(self._types)   # that overload's entry point
            return out
        if _verify and entry is not self._dispatcher:
            got = self._types_of(args)
            if got != self._types:
                bad = [i for i, (a, b) in enumerate(zip(got, self._types)) if a != b]
                raise TypeError(f"{self._dispatcher.__name__}: argument(s) {bad} have types "
                                f"{[str(got[i]) for i in bad]}, the overload takes "
                                f"{[str(self._types[i]) for i in bad]}")
        return entry(*args)
