"""The words a user chooses among, one Enum each, shared by the command lines, the configuration and
the code (no imports: the CLI builds its parser from these without loading numpy or numba)."""

from __future__ import annotations

from enum import Enum


class Choice(str, Enum):
    """A setting's word (a ``str``: comparisons with the word and JSON keep working)."""

    def __str__(self) -> str:
        result: str = self.value
        return result

    @classmethod
    def words(cls) -> tuple[str, ...]:
        """The words a user may write (CLI choices, config values)."""
        return tuple(m.value for m in cls)


class Robust(Choice):
    """Model-error handling: decided per injection by a likelihood ratio, always on, or off."""

    AUTO = "auto"
    ON = "on"
    OFF = "off"


class Norm(Choice):
    """The search's cost: least squares, or the paper's absolute error (eq. 28)."""

    L2 = "l2"
    L1 = "l1"


class ColdStart(Choice):
    """A checked local fit from the start point (the global search where it fails), or the global search."""

    LOCAL_FIRST = "local-first"
    GLOBAL = "global"


class Switch(Choice):
    """A feature switched off or on."""

    OFF = "off"
    ON = "on"
