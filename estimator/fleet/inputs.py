"""Fleet inputs: globs and directories expanded, and grouped by injector key.

Injector key (documented in docs/guide/fleet.md): a trace's metadata ``serial=...`` (or ``injector_key=...``);
traces that share a key are one injector's measurements and are processed in one task, in order of
their ``time_s`` metadata (then file name), with the recursive estimator's state carried from one to
the next. Everything else (traces without a key, captures) is independent: a group of its own. A Dask
task runs one or more groups (:func:`estimator.fleet.run.task_sizes`), each with its own tracker.
"""

from __future__ import annotations

import glob
from dataclasses import dataclass
from pathlib import Path

from estimator.io.captures import CAPTURE_SUFFIXES
from estimator.io.mdf import MDF_SUFFIXES
from estimator.io.traces import csv_head, injector_key
from estimator.pipeline.estimates import is_capture_header

TRACE_SUFFIXES = (".csv", *MDF_SUFFIXES)


@dataclass(frozen=True)
class Group:
    """One injector's inputs in processing order (key None: one independent input)."""

    key: str | None
    paths: tuple[str, ...]


def expand(inputs: list[str]) -> tuple[list[Path], list[str]]:
    """Files from paths, globs (``**`` too) and directories (recursively, by suffix); and the inputs
    that matched nothing (reported, not fatal)."""
    files: list[Path] = []
    missing: list[str] = []
    suffixes = set(TRACE_SUFFIXES) | set(CAPTURE_SUFFIXES)
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            found = sorted(f for f in p.rglob("*") if f.is_file() and f.suffix.lower() in suffixes)
        elif any(ch in item for ch in "*?["):
            found = sorted(Path(f) for f in glob.glob(item, recursive=True) if Path(f).is_file())
        else:
            found = [p] if p.exists() else []
        if not found:
            missing.append(item)
        files.extend(found)
    seen, unique = set(), []
    for f in files:
        if f.resolve() not in seen:
            seen.add(f.resolve())
            unique.append(f)
    return unique, missing


def trace_meta(path: Path) -> dict[str, str]:
    """The ``# key=value`` lines of a CSV trace ({} for a capture CSV, another file or an unreadable
    one); one read of the file's head."""
    if path.suffix.lower() != ".csv":
        return {}
    try:
        meta, first = csv_head(path)
    except OSError:
        return {}
    return {} if is_capture_header(first) else meta


def group(files: list[Path]) -> list[Group]:
    """Groups: keyed traces together in time order, every other input alone."""
    keyed: dict[str, list[tuple[float, str]]] = {}
    alone: list[Group] = []
    for f in files:
        meta = trace_meta(f)
        key = injector_key(meta)
        if key is None:
            alone.append(Group(None, (str(f),)))
            continue
        try:
            t = float(meta.get("time_s", "nan"))
        except ValueError:
            t = float("nan")
        keyed.setdefault(key, []).append((t if t == t else float("inf"), str(f)))
    out = [Group(k, tuple(p for _, p in sorted(v))) for k, v in sorted(keyed.items())]
    return out + alone
