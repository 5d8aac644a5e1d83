"""The documentation's figures, drawn at each build by the project's own tools (``make docs``), so
that a picture cannot fall behind the code that it shows.

Into ``docs/_generated/`` (not kept in git), each seeded:

- ``identification/voltage_fit.png``, ``identification/cost_contour.png``: one simulated injection
  of the nominal injector identified from a cold start (:func:`estimator.plots.identification.plot_identification`,
  what ``estimator plot`` draws);
- ``learning.png``: three series parts of one lot through the estimator as the daemon runs it
  (learning on by default), the middle one swapped at injection 40
  (:func:`estimator.plots.estimates.plot_estimates`, what ``estimator plot-estimates`` draws);
- ``fleet/lot-lot.png``: a synthetic lot of 40 injectors (three injections each)
  judged on a local Dask cluster of one worker (what ``estimator fleet`` draws);
- ``daemon/latency-histogram.png``: the daemon's latency at 200 and 400 injections/s, 3 s each, the
  daemon and the listener as processes on the loopback hub (what ``sim_bench daemon-bench`` draws).
"""

from __future__ import annotations

import time
from pathlib import Path

from sphinx.application import Sphinx
from sphinx.util import logging

log = logging.getLogger(__name__)
SEED = 2
INJECTIONS = 80
SWAP_AT = 40


def identification(out: Path) -> list[Path]:
    import numpy as np

    from estimator.ident.measurement import Injection
    from estimator.plots.identification import plot_identification
    from sim_bench.hardware.plant import Plant, PlantConfig

    m = Plant(PlantConfig()).measure(17.0, 3e-6, 28.0, np.random.default_rng(SEED))
    return plot_identification(Injection(m.current_a, m.voltage_v, m.dt_s, m.f_open_n), out / "identification")


def learning(out: Path) -> Path:
    import numpy as np

    from estimator.ident.measurement import Injection
    from estimator.pipeline import EstimatorConfig, build_pipeline
    from estimator.plots.estimates import plot_estimates
    from sim_bench.hardware.series_life import LotSpec, draw_lot

    lives = draw_lot(3, SEED, LotSpec(swap_at=SWAP_AT, swapped=(1,)))
    _, _, processor, _ = build_pipeline(EstimatorConfig())
    rows: list[dict] = []
    truth: dict[int, tuple[list[float], list[float], list[float]]] = {i: ([], [], []) for i in range(len(lives))}
    rngs = [np.random.default_rng(life.seed) for life in lives]
    for k in range(INJECTIONS):
        for i, life in enumerate(lives):
            m, t = life.measure(k, INJECTIONS, rngs[i])
            pub = processor.estimate(Injection(m.current_a, m.voltage_v, m.dt_s, m.f_open_n, i, k % 256,
                                               float("nan"), float(k)))
            rows.append(pub.to_row(float(k)))
            for series, v in zip(truth[i], (float(k), t["lh_true_um"], t["nu_true"])):
                series.append(v)
    return plot_estimates(rows, out / "learning.png", truth,
                          title=f"three series parts of one lot, learning on (default); injector 1's part swapped "
                                f"at injection {SWAP_AT}; dashed: truth, x: not ok")


def fleet(out: Path) -> Path:
    import os

    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")   # as `estimator fleet` runs it
    import shutil

    from estimator.fleet.run import run_fleet
    from sim_bench.hardware.lot import make_lot

    lot = out / "fleet" / "lot"
    shutil.rmtree(lot, ignore_errors=True)   # a lot of the same seed, written afresh
    make_lot(lot, 40, 3, seed=SEED)
    res = run_fleet([str(lot)], out / "fleet" / "lot.csv", workers=1)
    return next(Path(f) for f in res.files if str(f).endswith(".png"))


def latency(out: Path) -> Path:
    from sim_bench.benches.daemon_bench import run_latency_and_overload

    report = run_latency_and_overload(out / "daemon", seconds=3.0)
    if not report.get("histogram_png"):
        raise RuntimeError("daemon-bench drew no latency histogram")
    return Path(report["histogram_png"])


def draw(app: Sphinx) -> None:
    import logging as std_logging

    out = Path(app.srcdir) / "_generated"
    t0 = time.perf_counter()
    quiet = [std_logging.getLogger(name) for name in ("estimator", "numexpr", "distributed", "sim_bench")]
    levels = [q.level for q in quiet]
    for q in quiet:
        q.setLevel(std_logging.WARNING)   # the learning's progress lines are not the build's
    try:
        paths = [*identification(out), learning(out), fleet(out), latency(out)]
    finally:
        for q, level in zip(quiet, levels):
            q.setLevel(level)
    log.info("doc figures: %d drawn in %.1f s", len(paths), time.perf_counter() - t0)


def setup(app: Sphinx) -> dict[str, bool]:
    app.connect("builder-inited", draw)
    return {"parallel_read_safe": True}
