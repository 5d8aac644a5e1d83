"""Traces from ASAM MDF4 files (INCA, CANape, asammdf): two channels, resampled to a uniform period.

Resampling, documented because the estimator needs one sample period: the uniform grid starts at the
later of the two channels' first samples and ends at the earlier last sample; its period is
``sample_period_s`` if given, else the median interval of the current channel; both signals are
linearly interpolated onto it (``numpy.interp``). Where a channel was already sampled on that grid
the values are reproduced exactly. A channel whose own intervals stray more than 1 % from the period
is still resampled, and the returned trace says so in its metadata (``resampled_from``).

Metadata come from the MDF header comment as ``key=value`` lines (the keys of the CSV traces:
``preload_force_n``, ``temperature_c``, ``injector_id``, ``time_s``), overridden by ``meta``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from estimator.errors import EstimatorError, TraceError
from estimator.io.traces import Trace

if TYPE_CHECKING:
    from estimator.ident.measurement import Injection

MDF_SUFFIXES = (".mf4", ".mdf")


def is_mdf(path: str | Path) -> bool:
    """True for a file name MDF readers take."""
    return Path(path).suffix.lower() in MDF_SUFFIXES


def read_mdf_trace(path: str | Path, current_channel: str, voltage_channel: str, s3_channel: str | None = None,
                   sample_period_s: float | None = None, meta: dict[str, str] | None = None) -> Trace:
    """A :class:`Trace` (columns t_s, current_A, voltage_V[, s3_m]) from an MDF4 file. TraceError on problems."""
    try:
        from asammdf import MDF
    except ImportError:
        raise TraceError("reading MDF4 needs asammdf: pip install '.[mdf]'") from None
    path = Path(path)
    if not current_channel or not voltage_channel:
        raise TraceError(f"{path}: MDF traces need --current-channel and --voltage-channel")
    try:
        mdf = MDF(str(path))
    except Exception as exc:   # asammdf raises many types for a file that is not MDF
        raise TraceError(f"cannot read MDF file {path}: {exc}") from None
    try:
        names = [current_channel, voltage_channel] + ([s3_channel] if s3_channel else [])
        sigs = []
        for name in names:
            if name not in mdf.channels_db:
                known = ", ".join(sorted(n for n in mdf.channels_db if n != "time")[:20])
                raise TraceError(f"{path}: no channel {name!r} (channels: {known})")
            s = mdf.get(name)
            t, v = np.asarray(s.timestamps, dtype=float), np.asarray(s.samples, dtype=float)
            if t.size < 3 or not (np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)):
                raise TraceError(f"{path}: channel {name!r} has no increasing time base")
            sigs.append((t, v))
        comment = str(mdf.header.comment or "")
    finally:
        mdf.close()
    dt = sample_period_s if sample_period_s is not None else float(np.median(np.diff(sigs[0][0])))
    if not (np.isfinite(dt) and 1e-9 <= dt <= 1e-3):
        raise TraceError(f"{path}: sample period {dt!r} s is not usable (give --sample-period-us)")
    t0 = max(t[0] for t, _ in sigs)
    t1 = min(t[-1] for t, _ in sigs)
    n = int(np.floor((t1 - t0) / dt * (1 + 1e-12))) + 1
    grid = t0 + dt * np.arange(n)
    cols = {"t_s": grid - t0}
    irregular = [name for name, (t, _) in zip(names, sigs) if np.max(np.abs(np.diff(t) - dt)) > 0.01 * dt]
    for key, (t, v) in zip(("current_A", "voltage_V", "s3_m"), sigs):
        cols[key] = np.interp(grid, t, v)
    info = dict(re.findall(r"^\s*([A-Za-z_][\w]*)\s*=\s*([^\s<]+)\s*$", _text(comment), re.M))
    info.update(meta or {})
    info["source"] = f"{path.name} ({current_channel}, {voltage_channel})"
    if irregular:
        info["resampled_from"] = ",".join(irregular)
    return Trace(cols, {k: str(v) for k, v in info.items()})


def read_any_trace(path: str | Path, current_channel: str | None = None, voltage_channel: str | None = None,
                   s3_channel: str | None = None, sample_period_s: float | None = None,
                   meta: dict[str, str] | None = None) -> Trace:
    """A trace file: MDF4 (by suffix) with the channel options, else a CSV trace (the options unused)."""
    from estimator.io.traces import read_trace

    if not is_mdf(path):
        return read_trace(path)
    return read_mdf_trace(path, current_channel or "", voltage_channel or "", s3_channel, sample_period_s, meta)


@dataclass
class Injections:
    """What :func:`read_injections` found: the usable injections, and one line (``path: why``) per file
    that could not be read and per trace that cannot be used."""

    injections: list[Injection] = field(default_factory=list)
    unreadable: list[str] = field(default_factory=list)
    unusable: list[str] = field(default_factory=list)


def read_injections(paths: list[Path] | list[str], current_channel: str | None = None, voltage_channel: str | None = None,
                    sample_period_s: float | None = None, meta: dict[str, str] | None = None,
                    serial: str | None = None) -> Injections:
    """Injections from trace files (CSV or MDF4, :func:`read_any_trace`), those of injector ``serial``
    only if given; a file that cannot be read or a trace that cannot be used is listed, not raised."""
    from estimator.io.traces import injection_from_trace, injector_key

    out = Injections()
    for path in paths:
        try:
            tr = read_any_trace(path, current_channel, voltage_channel, None, sample_period_s, meta)
        except (EstimatorError, OSError, ValueError) as exc:
            out.unreadable.append(f"{path}: {exc}")
            continue
        if serial is not None and injector_key(tr.meta) != serial:
            continue
        inj = injection_from_trace(tr)
        problem = inj.problem()
        if problem:
            out.unusable.append(f"{path}: {problem}")
        else:
            out.injections.append(inj)
    return out


def _text(comment: str) -> str:
    """The text of an MDF comment (plain, or the <TX> of its XML form)."""
    m = re.search(r"<TX>(.*?)</TX>", comment, re.S)
    return m.group(1) if m else comment
