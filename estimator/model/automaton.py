"""The hybrid automaton of :mod:`dynamics` in the form the simulators run it (one source for both).

:func:`build_automaton` turns the guards, targets and resets of a :class:`dynamics.HybridStructure`
into plain arrays on the scaled state (guard rows normalised once); the compiled kernel
(:mod:`kernel`) and the reference simulator (:mod:`reference_sim`) both take transitions with
:func:`apply_reset`, evaluate guards with :func:`guard_value` (the re-seated plunger's opening guard
included) and re-arm that guard with :func:`rearmed`. All three are numba functions that plain
Python may call too; they take the automaton's arrays, not the tuple (inside the kernel's sample
loop, taking an array out of a tuple costs a reference count each time).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from estimator._compiled import njit
from estimator.model.dynamics import (
    MODE_CONTACT,
    MODE_OPEN,
    NZ,
    REGION_MODE,
    RESET_CLOSE,
    RESET_OPEN,
    S4,
    V3,
    V4,
    HybridStructure,
)


class Automaton(NamedTuple):
    """Guards and transitions on the scaled augmented state (:data:`dynamics.Z_SCALE`).

    A transition j of region r fires when ``guards[r, j] @ z`` crosses from <= 0 to > 0; it leads to
    ``target[r, j]`` (-1: no guard j) and applies reset ``reset[r, j]`` (``RESET_*``).
    ``open_index[r]`` is the Σ2 -> Σ3 guard (-1: none), ``open_seated[r]`` its spring-only form used
    after the plunger has re-seated; ``region_mode[r]`` the automaton mode of region r.
    """

    guards: np.ndarray        # (6, 3, NZ) float, rows normalised to max |entry| = 1
    target: np.ndarray        # (6, 3) int64
    reset: np.ndarray         # (6, 3) int64
    open_index: np.ndarray    # (6,) int64
    open_seated: np.ndarray   # (6, NZ) float, normalised
    region_mode: np.ndarray   # (6,) int8


def _normalised(rows: np.ndarray) -> np.ndarray:
    """Rows divided by their largest absolute entry (zero rows stay zero)."""
    norm = np.max(np.abs(rows), axis=-1, keepdims=True)
    return np.ascontiguousarray(rows / np.where(norm > 0, norm, 1.0))


def build_automaton(structure: HybridStructure, z_scale: np.ndarray) -> Automaton:
    """The automaton of ``structure`` acting on ``z_scaled = z_scale * z_SI``."""
    return Automaton(guards=_normalised(structure.guards / z_scale),
                     target=np.ascontiguousarray(structure.guard_target, dtype=np.int64),
                     reset=np.ascontiguousarray(structure.guard_reset, dtype=np.int64),
                     open_index=np.ascontiguousarray(structure.open_index, dtype=np.int64),
                     open_seated=_normalised(structure.open_seated / z_scale),
                     region_mode=np.ascontiguousarray(REGION_MODE, dtype=np.int8))


@njit(cache=True, nogil=True, inline="always")
def dot(g: np.ndarray, z: np.ndarray) -> float:
    """g @ z over the NZ augmented states."""
    s = 0.0
    for i in range(NZ):
        s += g[i] * z[i]
    return s


@njit(cache=True, nogil=True, inline="always")
def apply_reset(z: np.ndarray, code: int, seated: bool) -> bool:
    """Apply reset ``code`` to the scaled state z in place; returns the new re-seated flag.

    Opening (``RESET_OPEN``): the plunger lifts with the piston, ``v4 := max(v3, 0)`` (never into its
    seat). Closing (``RESET_CLOSE``): it seats inelastically, ``s4 := 0, v4 := 0``, and is re-seated.
    """
    if code == RESET_OPEN:
        z[V4] = max(z[V3], 0.0)
        return False
    if code == RESET_CLOSE:
        z[S4] = 0.0
        z[V4] = 0.0
        return True
    return seated


@njit(cache=True, nogil=True, inline="always")
def guard_value(guards: np.ndarray, open_seated: np.ndarray, open_index: np.ndarray, r: int, j: int,
                z: np.ndarray, seated: bool) -> float:
    """Value of guard j of region r at z (the arrays of an :class:`Automaton`); after a re-seat the
    opening needs min(ordinary, spring-only) > 0."""
    v = dot(guards[r, j], z)
    if seated and j == open_index[r]:
        v = min(v, dot(open_seated[r], z))
    return v


@njit(cache=True, nogil=True, inline="always")
def rearmed(guards: np.ndarray, open_index: np.ndarray, r: int, z: np.ndarray, seated: bool) -> bool:
    """The re-seated flag after a sample: cleared once the full opening force falls below F_open."""
    if seated:
        oi = open_index[r]
        if oi >= 0 and dot(guards[r, oi], z) <= 0.0:
            return False
    return seated


@njit(cache=True, nogil=True, inline="always")
def in_contact(mode: int) -> bool:
    """True for the modes in which piston and actuator touch (Σ2 and Σ3)."""
    return mode in (MODE_CONTACT, MODE_OPEN)
