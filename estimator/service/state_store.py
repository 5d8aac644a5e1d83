"""Per-injector estimator state on disk: atomic (write, fsync, rename), validated on load.

Beside each injector's tracker state the file holds the parameter set its learning adopted for it
(``calibrations``), so that a restarted daemon estimates it with its own model at once, and where
its learning stands (``learning``: the lifecycle state, the refusals and the diagnostics); and the
amplifier's standard drive learned for it (``drives``), so that its first injections after a restart
are corrected at once instead of being driven with the standard drive while it is learned again.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
import stat
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from estimator.drive.standard import AmplifierDrive
from estimator.errors import EstimatorError
from estimator.ident.learning.selfcal import CalibrationStatus
from estimator.ident.tracking.tracker import TrackerState
from estimator.model.parameters import InjectorParameters

log = logging.getLogger(__name__)
T = TypeVar("T")
FORMAT = "piezo-injector-estimator-state"
VERSION = 1
MAX_BYTES = 1 << 20   # 8 injectors take about 10 kB, 30 kB more with their learned drives; anything this large is not ours
REJECTED_KEPT = 3     # generations of rejected state files kept (<name>.rejected, .rejected.1, ...)
LOCK_FILE = "estimator.lock"


class StateDirectoryBusy(EstimatorError):
    """Another estimator holds the state directory."""


def lock_state_dir(state_dir: Path) -> int:
    """Hold the state directory for this process (an advisory ``flock`` on ``estimator.lock`` in it,
    released when the process ends); the lock's file descriptor. StateDirectoryBusy names the holder's
    pid when another estimator has it; EstimatorError when the lock file cannot be opened (a link or
    not a regular file is refused)."""
    state_dir.mkdir(parents=True, exist_ok=True)
    path = state_dir / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o600)
    except OSError as exc:
        raise EstimatorError(f"state directory {state_dir}: cannot open its lock file {path.name} ({exc})") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise EstimatorError(f"state directory {state_dir}: {path.name} is not a regular file")
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        holder = os.read(fd, 32).decode("ascii", "replace").strip() or "unknown"
        os.close(fd)
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise StateDirectoryBusy(f"state directory {state_dir} is in use by another estimator "
                                     f"(pid {holder}); one estimator per state directory") from None
        raise EstimatorError(f"state directory {state_dir}: cannot lock it ({exc})") from None
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd


def save_states(path: Path, states: dict[int, TrackerState],
                calibrations: dict[int, InjectorParameters] | None = None,
                learning: dict[int, CalibrationStatus] | None = None,
                drives: dict[int, AmplifierDrive] | None = None) -> None:
    """Write all injector states (and the injectors' own parameter sets, learning statuses and learned
    standard drives) atomically: a crash leaves the old file or the new one, never a mix."""
    path.parent.mkdir(parents=True, exist_ok=True)
    doc: dict[str, Any] = {"format": FORMAT, "version": VERSION, "saved_at": time.time(),
                           "injectors": {str(k): v.to_dict() for k, v in sorted(states.items())}}
    if calibrations:
        doc["calibrations"] = {str(k): p.to_mapping() for k, p in sorted(calibrations.items())}
    if learning:
        doc["learning"] = {str(k): st.to_dict() for k, st in sorted(learning.items())}
    if drives:
        doc["drives"] = {str(k): d.to_dict() for k, d in sorted(drives.items())}
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
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def load_states(path: Path) -> tuple[dict[int, TrackerState], str | None]:
    """States from ``path`` and a problem description (None if fine or absent).

    A corrupt, truncated or foreign file is reported and ignored (the estimator starts cold);
    a single bad injector entry is skipped, the others are kept.
    """
    doc, problem = _read(path)
    if doc is None:
        return {}, problem
    return _states_of(doc, path)


def _entries_of(doc: dict[str, Any], path: Path, key: str, parse: Callable[[Any], T], what: str,
                errors: tuple[type[BaseException], ...] = (ValueError, TypeError, RecursionError)
                ) -> tuple[dict[int, T], str | None]:
    """The per-injector entries under ``key`` of a state document, each parsed by ``parse``; a bad
    entry is skipped and named (``what`` and its injector) in the problem line."""
    entries = doc.get(key) or {}
    if not isinstance(entries, dict):
        return {}, f"state file {path}: '{key}' is not an object; ignoring it"
    out: dict[int, T] = {}
    problems = []
    for k, value in entries.items():
        try:
            out[_injector(k)] = parse(value)
        except errors as exc:
            problems.append(f"{what}injector {k}: {exc}")
    return out, ("; ".join(problems) if problems else None)


def _states_of(doc: dict[str, Any], path: Path) -> tuple[dict[int, TrackerState], str | None]:
    return _entries_of(doc, path, "injectors", TrackerState.from_dict, "")


def load_calibrations(path: Path) -> tuple[dict[int, InjectorParameters], str | None]:
    """The injectors' own parameter sets from ``path`` and a problem description (None if fine or
    absent); each set is validated like a parameter file, a bad one is skipped."""
    doc, problem = _read(path)
    if doc is None:
        return {}, problem
    return _calibrations_of(doc, path)


def _calibrations_of(doc: dict[str, Any], path: Path) -> tuple[dict[int, InjectorParameters], str | None]:
    return _entries_of(doc, path, "calibrations", InjectorParameters.from_mapping, "calibration of ",
                       (ValueError, TypeError, RecursionError, EstimatorError))


def load_learning(path: Path) -> tuple[dict[int, CalibrationStatus], str | None]:
    """The injectors' learning statuses from ``path`` and a problem description (None if fine or
    absent); a bad entry is skipped (that injector's learning starts afresh)."""
    doc, problem = _read(path)
    if doc is None:
        return {}, problem
    return _learning_of(doc, path)


def _learning_of(doc: dict[str, Any], path: Path) -> tuple[dict[int, CalibrationStatus], str | None]:
    return _entries_of(doc, path, "learning", CalibrationStatus.from_dict, "learning of ")


def load_all(path: Path) -> tuple[dict[int, TrackerState], dict[int, InjectorParameters],
                                  dict[int, CalibrationStatus], dict[int, AmplifierDrive], list[str]]:
    """States, own parameter sets, learning statuses and learned standard drives from one read of
    ``path``, and the problems (one line each: the file's, or each bad entry's)."""
    doc, problem = _read(path)
    if doc is None:
        return {}, {}, {}, {}, [problem] if problem else []
    (states, p1), (cals, p2), (learning, p3) = _states_of(doc, path), _calibrations_of(doc, path), _learning_of(doc, path)
    drives, p4 = _entries_of(doc, path, "drives", AmplifierDrive.from_dict, "standard drive of ")
    return states, cals, learning, drives, [p for p in (p1, p2, p3, p4) if p]


def _injector(key: str) -> int:
    inj = int(key)
    if not 0 <= inj <= 7:
        raise ValueError("injector id out of range")
    return inj


def read_regular(path: Path, max_bytes: int = MAX_BYTES) -> bytes:
    """The bytes of ``path`` as a careful daemon reads a file it does not trust: a link is not followed,
    a FIFO or device is not waited on (opened non-blocking, then refused as not a regular file), and
    at most ``max_bytes`` are read. FileNotFoundError if absent; OSError naming the refusal else."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise OSError(errno.ELOOP, "a symbolic link (not followed)") from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise OSError(errno.EINVAL, "not a regular file")
        if st.st_size > max_bytes:
            raise OSError(errno.EFBIG, f"larger than {max_bytes} bytes")
        chunks, left = [], max_bytes + 1
        while left > 0:
            b = os.read(fd, min(left, 1 << 16))
            if not b:
                break
            chunks.append(b)
            left -= len(b)
        data = b"".join(chunks)
        if len(data) > max_bytes:
            raise OSError(errno.EFBIG, f"larger than {max_bytes} bytes")
        return data
    finally:
        os.close(fd)


def _read(path: Path) -> tuple[dict[str, Any] | None, str | None]:
    """The state document, or None and why (None, None: no file)."""
    try:
        doc = json.loads(read_regular(path).decode("utf-8"))
    except FileNotFoundError:
        return None, None
    except (OSError, ValueError, RecursionError) as exc:
        return None, f"state file {path} unreadable ({exc}); starting without it"
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or doc.get("version") != VERSION:
        return None, f"state file {path} is not a {FORMAT} v{VERSION} file; ignoring it"
    return doc, None


def keep_rejected(path: Path) -> Path | None:
    """Keep a state file that was (partly) rejected as ``<name>.rejected`` for a post-mortem, by
    renaming it (never copying: a huge or special file costs nothing, and a rename within the directory
    writes nowhere else); earlier ones move to ``.rejected.1`` ... and the oldest beyond
    :data:`REJECTED_KEPT` goes. Returns the kept path (None if nothing could be kept)."""
    base = path.with_name(path.name + ".rejected")
    names = [base] + [base.with_name(f"{base.name}.{k}") for k in range(1, REJECTED_KEPT)]
    try:
        for older, newer in zip(reversed(names[1:]), reversed(names[:-1])):
            if os.path.lexists(newer):
                os.replace(newer, older)
        os.replace(path, base)
    except OSError as exc:
        log.warning("state file %s: could not keep it as %s (%s)", path, base.name, exc)
        return None
    return base
