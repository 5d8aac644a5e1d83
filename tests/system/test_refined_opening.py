"""A learned model's refinements are what a drive correction's opening instant rests on: the voltage tells
least about the valve's motion, so the second refinement's window must be large enough to pin it down."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.drive.correction import Correction
from estimator.ident.status import Learning
from estimator.pipeline import build_pipeline
from estimator.pipeline.config import EstimatorConfig
from sim_bench.benches import compensation
from sim_bench.hardware.series_life import draw_lot

LIFE = 150          # injections of the bench's life (its wear is spread over them)
RUN = 130           # injections run here: both refinements are done well before the end
JUDGED = 20         # the last injections, whose opening instants are judged


@pytest.mark.slow
def test_a_model_refined_twice_predicts_its_parts_opening_instant_within_a_fifth_of_a_microsecond():
    """Injector 4 of the compensation bench's standard lot (seed 2) driven by its own corrections, as an ECU
    asks for them: refined over 24 injections, its model put its opening instant 0.36 µs later than the
    part opened, at every preload force, with σ 0.2 µs, and set the lot's opening spread to 0.58 µs.
    Refined again over the default second window (60) it is within 0.2 µs."""
    life = draw_lot(compensation.INJECTORS, 2, compensation.lot_spec("standard"))[4]
    _, _, processor, _ = build_pipeline(EstimatorConfig(), deferred=True)
    rng = np.random.default_rng(life.seed)
    walk = life.preload_walk(LIFE + 1, np.random.default_rng(life.seed + 1))
    corr, errors = Correction(), []
    for k in range(RUN):
        m, pub, offset = compensation.drive_once(processor, life, 4, k, LIFE, rng, walk, corr if corr.valid else None)
        if corr.valid and k >= RUN - JUDGED:
            errors.append(offset + m.t_open_s * 1e6 - corr.opening_us)
        corr = pub.correction or Correction()
    assert len(errors) >= JUDGED - 2
    assert abs(float(np.mean(errors))) <= 0.2, f"opening instants {np.mean(errors):+.2f} µs off the predicted"
    status = processor.tracker.calibration.get(4)
    assert status is not None and status.refinements == 2 and status.state == Learning.MONITORING
