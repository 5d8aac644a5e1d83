"""The daemon's latency statistics and the heartbeat that carries them."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.codec.ingest import Counters
from estimator.codec.records import Codec
from estimator.ident.config import TrackerConfig
from estimator.ident.tracking.tracker import Tracker
from estimator.pipeline.processor import Processor
from estimator.service.latency import STAGES, Stats


def test_heartbeat_shows_an_overload_of_seconds_and_the_stages():
    p = Processor(Codec(), Tracker(TrackerConfig()), Counters(), "reset-only")
    stages = {"queue": 4321.5, "assembly": 0.12, "estimation": 2.97, "send": 0.3}
    hb = p.codec.decode(p.status_frame(3, 12_345.67, 10.0, stages))
    assert hb.latency_p99_ms == pytest.approx(12_345.67, abs=0.006)   # was saturated at 655.35 ms
    assert (hb.queue_p99_ms, hb.assembly_p99_ms, hb.estimation_p99_ms, hb.send_p99_ms) == pytest.approx(
        (4321.5, 0.12, 2.97, 0.3), abs=0.006)


def test_stats_p99_per_stage():
    st = Stats()
    for k in range(1000):
        parts = (0.001 * (k == 999), 0.0001, 0.002 + 1e-6 * k, 0.0002)
        st.add(float(k) * 1e-3, sum(parts), parts)
    total, stages = st.p99s_ms()
    assert list(stages) == list(STAGES)
    assert stages["estimation"] == pytest.approx(1e3 * float(np.percentile(0.002 + 1e-6 * np.arange(1000), 99)))
    assert stages["assembly"] == pytest.approx(0.1) and stages["send"] == pytest.approx(0.2)
    assert total > stages["estimation"]
    assert Stats().p99s_ms() == (0.0, dict.fromkeys(STAGES, 0.0))
