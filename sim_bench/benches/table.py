"""Fixed-width benchmark tables: a title row, a unit row, one row per report, a verdict at the end."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Column:
    """One column: its title and unit (headers), a format spec (``<16``, ``>8.3f``) and its value."""

    title: str
    unit: str
    spec: str
    value: Callable[[dict], Any]

    def head(self, text: str) -> str:
        m = re.match(r"([<>]?)(\d+)", self.spec)
        if m is None:
            raise ValueError(f"column spec {self.spec!r} must start with an alignment and a width")
        align, width = m.groups()
        return f"{text:{align or '>'}{width}}"


def keyed(title: str, unit: str, spec: str, key: str, scale: float = 1.0) -> Column:
    """A column showing ``row[key]`` (times ``scale``; unscaled values keep their type, e.g. int counts)."""
    return Column(title, unit, spec, (lambda s: scale * s[key]) if scale != 1.0 else (lambda s: s[key]))


def render(columns: list[Column], rows: list[dict], verdict: Callable[[dict], str]) -> str:
    """The table as text: titles (then ``verdict``), units, and per row the values and its verdict."""
    lines = [" ".join(c.head(c.title) for c in columns) + "  verdict",
             " ".join(c.head(c.unit) for c in columns)]
    lines += [" ".join(f"{c.value(r):{c.spec}}" for c in columns) + f"  {verdict(r)}" for r in rows]
    return "\n".join(lines)


def plant(s: dict) -> str:
    """The plant column of the accuracy and tracking tables."""
    if s.get("plant"):
        return s["plant"]
    return "mismatch" if s["mismatch"] else "matched"


def verdict(row: dict) -> str:
    """A row's verdict: PASS, or FAIL with its ``failures``."""
    return "PASS" if not row["failures"] else "FAIL: " + "; ".join(row["failures"])
