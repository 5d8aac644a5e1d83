"""Per-injector estimator state on disk: atomic (write, fsync, rename), validated on load.

Beside each injector's tracker state the file holds the parameter set its learning adopted for it
(``calibrations``), so that a restarted daemon estimates it with its own model at once, and where
its learning stands (``learning``: the lifecycle state, the refusals and the diagnostics).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import time
from pathlib import Path

from typing import Any

from estimator.errors import EstimatorError
from estimator.ident.selfcal import CalibrationStatus
from estimator.ident.tracker import TrackerState
from estimator.model.parameters import InjectorParameters

log = logging.getLogger(__name__)
FORMAT = "piezo-injector-estimator-state"
VERSION = 1
MAX_BYTES = 1 << 20   # 8 injectors take about 10 kB; anything this large is not ours


def save_states(path: Path, states: dict[int, TrackerState],
                calibrations: dict[int, InjectorParameters] | None = None,
                learning: dict[int, CalibrationStatus] | None = None) -> None:
    """Write all injector states (and the injectors' own parameter sets and learning statuses)
    atomically: a crash leaves the old file or the new one, never a mix."""
    path.parent.mkdir(parents=True, exist_ok=True)
    doc: dict[str, Any] = {"format": FORMAT, "version": VERSION, "saved_at": time.time(),
                           "injectors": {str(k): v.to_dict() for k, v in sorted(states.items())}}
    if calibrations:
        doc["calibrations"] = {str(k): p.to_mapping() for k, p in sorted(calibrations.items())}
    if learning:
        doc["learning"] = {str(k): st.to_dict() for k, st in sorted(learning.items())}
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(doc, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def load_states(path: Path) -> tuple[dict[int, TrackerState], str | None]:
    """States from ``path`` and a problem description (None if fine or absent).

    A corrupt, truncated or foreign file is reported and ignored (the estimator starts cold);
    a single bad injector entry is skipped, the others are kept.
    """
    doc, problem = _read(path)
    if doc is None:
        return {}, problem
    states: dict[int, TrackerState] = {}
    problems = []
    entries = doc.get("injectors") or {}
    if not isinstance(entries, dict):
        return {}, f"state file {path}: 'injectors' is not an object; starting without it"
    for key, value in entries.items():
        try:
            states[_injector(key)] = TrackerState.from_dict(value)
        except (ValueError, TypeError, RecursionError) as exc:
            problems.append(f"injector {key}: {exc}")
    return states, ("; ".join(problems) if problems else None)


def load_calibrations(path: Path) -> tuple[dict[int, InjectorParameters], str | None]:
    """The injectors' own parameter sets from ``path`` and a problem description (None if fine or
    absent); each set is validated like a parameter file, a bad one is skipped."""
    doc, problem = _read(path)
    if doc is None:
        return {}, problem
    entries = doc.get("calibrations") or {}
    if not isinstance(entries, dict):
        return {}, f"state file {path}: 'calibrations' is not an object; ignoring them"
    out: dict[int, InjectorParameters] = {}
    problems = []
    for key, value in entries.items():
        try:
            out[_injector(key)] = InjectorParameters.from_mapping(value)
        except (ValueError, TypeError, RecursionError, EstimatorError) as exc:
            problems.append(f"calibration of injector {key}: {exc}")
    return out, ("; ".join(problems) if problems else None)


def load_learning(path: Path) -> tuple[dict[int, CalibrationStatus], str | None]:
    """The injectors' learning statuses from ``path`` and a problem description (None if fine or
    absent); a bad entry is skipped (that injector's learning starts afresh)."""
    doc, problem = _read(path)
    if doc is None:
        return {}, problem
    entries = doc.get("learning") or {}
    if not isinstance(entries, dict):
        return {}, f"state file {path}: 'learning' is not an object; ignoring it"
    out: dict[int, CalibrationStatus] = {}
    problems = []
    for key, value in entries.items():
        try:
            out[_injector(key)] = CalibrationStatus.from_dict(value)
        except (ValueError, TypeError, RecursionError) as exc:
            problems.append(f"learning of injector {key}: {exc}")
    return out, ("; ".join(problems) if problems else None)


def _injector(key: str) -> int:
    inj = int(key)
    if not 0 <= inj <= 7:
        raise ValueError("injector id out of range")
    return inj


def _read(path: Path) -> tuple[dict | None, str | None]:
    """The state document, or None and why (None, None: no file)."""
    if not path.exists():
        return None, None
    try:
        if path.stat().st_size > MAX_BYTES:
            return None, f"state file {path} is larger than {MAX_BYTES} bytes; ignoring it"
        doc = json.loads(path.read_bytes().decode("utf-8"))
    except (OSError, ValueError, RecursionError) as exc:
        return None, f"state file {path} unreadable ({exc}); starting without it"
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or doc.get("version") != VERSION:
        return None, f"state file {path} is not a {FORMAT} v{VERSION} file; ignoring it"
    return doc, None


def keep_rejected(path: Path) -> Path | None:
    """Copy a state file that was (partly) rejected to ``<name>.rejected`` before it is overwritten,
    so nothing is lost for a post-mortem. Returns the copy's path (None if it could not be made)."""
    dest = path.with_name(path.name + ".rejected")
    try:
        shutil.copyfile(path, dest)
    except OSError:
        return None
    return dest
