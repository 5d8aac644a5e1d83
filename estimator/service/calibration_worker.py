"""The daemon's background calibrator: self-calibrations in a process of their own, at low priority.

A batch calibration takes seconds of computing; the injection worker must keep its sub-millisecond
updates meanwhile. :class:`BackgroundCalibrator` runs :func:`~estimator.ident.learning.selfcal.self_calibrate`
in one worker process (started with the calibrator, ``spawn``: the daemon has threads, a forked copy
of them would not be safe), at idle priority (``SCHED_IDLE``; niced where that is not available) so
that the kernel prefers the daemon's own threads, one calibration at a time. When one finishes, a
thread of the executor (not the injection worker) builds the simulator tables for the adopted
parameters; the tracker collects the outcome at its next update with :meth:`poll`, which only takes a
lock and a list.

The worker process also builds the adopted parameters' simulator table (≈ 26 ms of computing that
would hold the daemon's interpreter lock), and the daemon takes it as it is.

A worker process that dies (out of memory, killed) loses that calibration (reported as ``rejected``
with the reason) and is replaced at the next submission.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import numpy as np

from estimator.ident.learning.selfcal import (
    CalibrationOutcome,
    CalibrationStatus,
    CalibrationWindow,
    SelfCalConfig,
    calibrate_and_tabulate,
)
from estimator.ident.status import Learning
from estimator.model.parameters import InjectorParameters

log = logging.getLogger(__name__)
NICE = 10     # added to the worker's niceness: it yields the cores to the daemon's threads


def _run_when_idle() -> bool:
    """Put this process under ``SCHED_IDLE``; whether the platform has it and allowed it."""
    idle = getattr(os, "SCHED_IDLE", None)
    if idle is None:
        return False
    try:
        os.sched_setscheduler(0, idle, os.sched_param(0))
    except OSError:
        return False
    return True


def _lower_priority(increment: int) -> None:
    """In the worker process: lower its priority (best effort), and load the compiled kernels the
    calibration uses, so that the first calibration does not pay for it. On Linux the worker runs
    under ``SCHED_IDLE`` (it gets a core only where nothing else wants it; a niced process still
    takes a share of a busy one); elsewhere, or where that is refused, it is niced by ``increment``."""
    if not _run_when_idle():
        with contextlib.suppress(OSError):   # pragma: no cover - a platform without nice
            os.nice(increment)
    from estimator.model.drive import SAMPLE_PERIOD_S, StandardDrive
    from estimator.model.fast_sim import FastSimulator

    cur = StandardDrive().samples(100e-6, SAMPLE_PERIOD_S)
    FastSimulator().simulate(cur, np.array([17.0, 18.0]), np.array([2e-6, 3e-6]))


def _wake_to_end(pid: int) -> None:
    """Take the worker process ``pid`` out of ``SCHED_IDLE`` so that it can end promptly (best effort).

    A process ends on the CPU: under ``SCHED_IDLE``, on cores other work keeps busy, it got one so
    rarely that its end took 5-8 s, and the daemon, which waits for its children, exited that much
    later. It goes back to the normal policy where it may (root, ``CAP_SYS_NICE``, or an
    ``RLIMIT_NICE`` that allows its nice value, else nice 19); a plain user's daemon, the systemd
    unit's among them, on a saturated machine still waits for it (hence the unit's stop timeout)."""
    idle = getattr(os, "SCHED_IDLE", None)
    try:
        if idle is None or os.sched_getscheduler(pid) != idle:
            return
        os.sched_setscheduler(pid, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, pid, 19)
            os.sched_setscheduler(pid, os.SCHED_OTHER, os.sched_param(0))


class BackgroundCalibrator:
    """Self-calibrations in a low-priority worker process (see the module docstring).

    ``prepare`` (optional) turns adopted parameters into what the tracker swaps in (its simulator
    pool with the tables built); it runs on an executor thread, not on the caller's.
    """

    def __init__(self, prepare: Callable[[InjectorParameters, dict[float, Any]], Any] | None = None,
                 nice: int = NICE) -> None:
        self.prepare = prepare
        self._nice = nice
        self._lock = threading.Lock()
        self._finished = threading.Condition(self._lock)   # notified when a calibration comes back
        self._done: list[CalibrationOutcome] = []
        self._running: set[int] = set()
        self._executor: ProcessPoolExecutor | None = None
        self._closes = 0   # close() calls so far: a calibration submitted before the last one was abandoned
        self._pool().submit(int)   # start the worker process now (at the daemon's start, not in an update)

    def _pool(self) -> ProcessPoolExecutor:
        if self._executor is None:
            self._executor = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                                 initializer=_lower_priority, initargs=(self._nice,))
        return self._executor

    def submit(self, injector_id: int, window: CalibrationWindow, base: InjectorParameters,
               config: SelfCalConfig, current: InjectorParameters | None = None) -> None:
        """Queue a calibration of ``window`` (returns at once)."""
        try:
            fut = self._pool().submit(calibrate_and_tabulate, window, base, config, current)
        except (BrokenProcessPool, RuntimeError) as exc:   # a dead worker: start a new one next time
            self._executor = None
            self._finish_failed(injector_id, f"calibration worker unavailable ({exc})")
            return
        with self._lock:
            self._running.add(injector_id)
        closes = self._closes
        fut.add_done_callback(lambda f: self._finish(injector_id, f, closes))

    def _finish(self, injector_id: int, fut: Future[Any], closes: int) -> None:
        """One calibration back (on an executor thread); ``closes``: :meth:`close` calls when it was
        submitted (one since: abandoned by the stop, not a failure to warn of)."""
        if closes != self._closes:
            self._settle(injector_id, None)
            log.debug("injector %d: the calibration was abandoned when the calibrator closed", injector_id)
            return
        try:
            status, params, tables = fut.result()
        except Exception as exc:
            if isinstance(exc, BrokenProcessPool):
                self._executor = None
            log.warning("injector %d: self-calibration failed: %s", injector_id, exc)
            self._finish_failed(injector_id, f"calibration failed ({type(exc).__name__}: {exc})")
            return
        prepared = None
        if params is not None and self.prepare is not None:
            try:
                prepared = self.prepare(params, tables)
            except Exception as exc:
                log.warning("injector %d: preparing the calibrated model failed: %s", injector_id, exc)
        self._settle(injector_id, CalibrationOutcome(injector_id, status, params, prepared))

    def _finish_failed(self, injector_id: int, message: str) -> None:
        self._settle(injector_id, CalibrationOutcome(injector_id, CalibrationStatus(Learning.REFUSED, message=message),
                                                     None))

    def _settle(self, injector_id: int, outcome: CalibrationOutcome | None) -> None:
        """The injector's calibration is no longer running; its ``outcome`` for :meth:`poll` (None: none,
        abandoned); anyone in :meth:`wait` is woken."""
        with self._lock:
            self._running.discard(injector_id)
            if outcome is not None:
                self._done.append(outcome)
            self._finished.notify_all()

    def poll(self) -> list[CalibrationOutcome]:
        """The calibrations finished since the last call (never blocks on a running one)."""
        with self._lock:
            done, self._done = self._done, []
        return done

    def wait(self, timeout: float) -> bool:
        """Block until no calibration is running (at most ``timeout`` s); True if none is. For
        benches and tests: the daemon's worker never waits, it polls."""
        with self._finished:
            return self._finished.wait_for(lambda: not self._running, timeout)

    @property
    def running(self) -> int:
        """Calibrations submitted and not finished."""
        with self._lock:
            return len(self._running)

    def close(self) -> None:
        """Stop the worker process (a running calibration is abandoned)."""
        ex, self._executor = self._executor, None
        self._closes += 1
        if ex is not None:
            processes = list((getattr(ex, "_processes", None) or {}).values())
            ex.shutdown(wait=False, cancel_futures=True)
            for p in processes:   # do not wait seconds for a running calibration to finish
                if p.is_alive():
                    _wake_to_end(p.pid)
                    p.terminate()
