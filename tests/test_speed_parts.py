"""What the online-speed work changed, checked for correctness (the timings live in the benchmarks):
the heartbeat's latency range and stage breakdown, the daemon's stage statistics."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.codec.ingest import Counters
from estimator.codec.records import Codec
from estimator.ident.config import TrackerConfig
from estimator.ident.tracker import Tracker
from estimator.service.daemon import STAGES, Stats
from estimator.service.processor import Processor


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


@pytest.mark.parametrize("f_open_n", [35.0, 0.0])
@pytest.mark.parametrize("samples", [201, 981])
def test_grid_voltages_equal_simulate_bit_for_bit(sim, f_open_n, samples):
    """A grid column's shared free run changes nothing: every point's voltage and success are the
    ones its own simulation gives (pre-compressed rows, no-contact rows, failures and a valve that
    opens at once with F_open = 0 included)."""
    from estimator.model.drive import StandardDrive
    rng = np.random.default_rng(samples)
    cur = StandardDrive().samples((samples - 1) * sim.dt_s, sim.dt_s)
    cur = cur * (1.0 + rng.normal(0.0, 0.01, cur.size))
    nu, lh = np.meshgrid(np.linspace(14.9, 21.1, 7), np.r_[np.linspace(-2e-6, 10e-6, 13), 40e-6], indexing="ij")
    nu = np.r_[nu.ravel(), rng.uniform(15.0, 21.0, 20)]
    lh = np.r_[lh.ravel(), rng.uniform(-2e-6, 12e-6, 20)]
    res = sim.simulate(cur, nu, lh, f_open_n)
    u, ok = sim.grid_voltages(cur, nu, lh, f_open_n)
    assert np.array_equal(ok, res.success)
    assert np.array_equal(u, np.where(res.success[:, None], res.voltage_v, np.nan), equal_nan=True)
    assert ok.sum() > nu.size // 2


def test_grid_voltages_check_their_inputs(sim):
    from estimator.errors import ParameterError
    cur = np.linspace(0.0, 10.0, 50)
    with pytest.raises(ParameterError):
        sim.grid_voltages(cur, np.full(4, 40.0), np.full(4, 3e-6), 35.0)     # N_u outside the range
    with pytest.raises(ParameterError):
        sim.grid_voltages(np.r_[cur, np.nan], np.full(4, 17.0), np.full(4, 3e-6), 35.0)
    with pytest.raises(ParameterError):
        sim.grid_voltages(cur, np.full(4, 17.0), np.full(3, 3e-6), 35.0)
