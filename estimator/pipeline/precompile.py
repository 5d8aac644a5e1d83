"""Fill numba's cache for these sources on two cores: ``python -m estimator compile``.

A fresh cache (a new checkout, a new version: the cache directory is keyed by the compiled sources,
:mod:`estimator._compiled.cache`) costs the first process that needs the kernels 52-57 s of compiling on
this machine, one function after another. Most of that is LLVM optimising the simulation kernel once
more inside each compiled entry point that calls it; those entry points do not depend on each other.
So this command compiles two halves at once, in this process and in one child: the cold start's
local fits (:func:`warm_cold_start`: Gauss–Newton, the probe ring, the valve prediction) and
everything else (:func:`warm_the_rest`: the free simulation, the warm update, the grid of the global
search). Both write the shared cache (numba writes each entry to a temporary file and renames it into
place); a function both need is compiled by whichever gets there first, or by both. Then
:meth:`Tracker.warm_up` loads every entry point an update uses from the cache and compiles what the
halves missed; a marker file in the cache directory makes a later call return at once.

``make`` runs it before ``demo`` and ``test``; a process that finds the cache empty still compiles
what it needs itself, as before.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from estimator.ident.tracking.tracker import Tracker

import os
import subprocess
import sys
import time
from pathlib import Path

MARKER = ".complete"   # in the numba cache directory: every entry point of Tracker.warm_up is in it


def _tracker() -> Tracker:
    """A tracker with the default configuration and its own simulator pool."""
    from estimator.ident.tracking.tracker import Tracker
    from estimator.pipeline.build import build_pool
    from estimator.pipeline.config import EstimatorConfig

    cfg = EstimatorConfig()
    return Tracker(cfg.tracker_config(), pool=build_pool(cfg))


def warm_cold_start(tracker: Tracker) -> None:
    """Compile the automatic cold start's local fits (plain and robust cost) on ``tracker``'s
    simulator: the Gauss–Newton loop, the forward-difference fit, the probe ring and the valve
    prediction. The trace is a charging voltage's shape (no simulation needed): enough to compile
    against, not to fit well."""
    import numpy as np

    from estimator.ident.coords import UM_PER_M
    from estimator.ident.fit.cold_start import gauss_newton_fit, probe_ring
    from estimator.ident.fit.idle_stroke import _cost_model, predict_valve, search_box
    from estimator.ident.fit.local_fit import local_fit
    from estimator.ident.measurement import Injection
    from estimator.model.drive import SAMPLE_PERIOD_S, StandardDrive

    sim = tracker.simulator(SAMPLE_PERIOD_S)
    cur = np.ascontiguousarray(StandardDrive().samples(100e-6, SAMPLE_PERIOD_S), dtype=float)
    q = np.cumsum(cur)
    inj = Injection(cur, 120.0 * q / q[-1], SAMPLE_PERIOD_S)   # A, V
    config = tracker.config.ident
    box = search_box(config, sim, inj.f_open_n)
    x0 = np.asarray(config.start_point, dtype=float)
    for robust in (False, True):
        model = _cost_model(sim, inj, config, robust)
        fit, _ = gauss_newton_fit(model, x0, box, config)
        fit = local_fit(model, x0, box) if not fit.success else fit
        probe_ring(model, fit, box)
    predict_valve(sim, inj, float(x0[0]), float(x0[1]) / UM_PER_M)


def warm_the_rest() -> None:
    """Compile the free simulation, the warm update and the global search
    (:meth:`Tracker.warm_up` without its local-first cold start), and the drive correction's table carry."""
    _tracker().warm_up(cold_start=False)
    warm_drive()


def warm_drive() -> None:
    """Compile the drive correction's table carry (its simulations are the valve prediction's)."""
    import numpy as np

    from estimator.drive.row_carry import COLUMNS, carry_rows

    carry_rows(np.ones((2, COLUMNS)), 17.0, 4.0, 10.0, 100.0, (0.5, 1.5, -50.0, 50.0))


def cache_dir() -> Path:
    """This installation's numba cache directory (``estimator/__init__`` set it through
    :func:`estimator._compiled.cache.configure` before this module was imported)."""
    return Path(os.environ["NUMBA_CACHE_DIR"])


def precompile(parallel: bool = True, log: Callable[..., Any] = print) -> float:
    """Fill the cache (two halves at once if ``parallel``), check it with :meth:`Tracker.warm_up`,
    mark it complete; returns the seconds taken (0 if it was complete already)."""
    marker = cache_dir() / MARKER
    if marker.exists():
        return 0.0
    t0 = time.perf_counter()
    log(f"compiling the kernels into {marker.parent} (once per version; ~30-60 s)")
    child = None
    if parallel and (os.cpu_count() or 1) > 1:
        child = subprocess.Popen([sys.executable, "-c", "from estimator.pipeline.precompile import warm_the_rest; "
                                  "warm_the_rest()"])
    tracker = _tracker()
    warm_cold_start(tracker)
    if child is not None and child.wait() != 0:
        log(f"the second compiling process exited with {child.returncode}; compiling the rest here")
    tracker.warm_up()   # loads what is cached, compiles what is not
    warm_drive()
    try:
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.write_text("complete\n")
    except OSError as exc:   # a read-only cache: every process loads (or compiles) what it needs
        log(f"cannot mark the cache complete ({exc.strerror or exc}); it is used all the same")
    seconds = time.perf_counter() - t0
    log(f"compiled in {seconds:.1f} s")
    return seconds
