"""The simulated injector node: frames carry the plant's trace, runs are reproducible, faults at their rates."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.codec.assembler import Completed
from estimator.codec.ingest import Ingest
from estimator.codec.records import Codec, SimTruth
from sim_bench.hardware import scenarios
from sim_bench.hardware.node import InjectorNode, NodeStats, apply_faults


@pytest.fixture(scope="module")
def codec():
    return Codec()


def test_frames_decode_to_the_plant_trace(codec):
    node = InjectorNode(lambda f: None, scenarios.get("nominal"), seed=3, codec=codec)
    ref = InjectorNode(lambda f: None, scenarios.get("nominal"), seed=3, codec=codec)
    frames = node.frames_for(1, 0, 0.0)
    m, _temp = ref.source.measure(1, 0, 0.0)
    ing = Ingest(codec)
    events = [e for f in frames for e in ing.feed(f, 0.0)]
    done = [e for e in events if isinstance(e, Completed)]
    assert len(done) == 1
    c = done[0]
    assert np.max(np.abs(c.current_a - m.current_a)) <= 0.0005 + 1e-12     # 1 mA resolution
    assert np.max(np.abs(c.voltage_v - m.voltage_v)) <= 0.005 + 1e-12      # 10 mV resolution
    assert c.header.sample_period_ns == 500 and c.header.preload_force_n == pytest.approx(m.f_open_n, abs=0.25)
    truth = codec.decode(frames[-1])
    assert isinstance(truth, SimTruth)
    assert truth.nu_n_per_v == pytest.approx(m.nu_n_per_v, abs=0.00025)
    assert truth.lh_um == pytest.approx(m.lh_m * 1e6, abs=0.0005)
    assert truth.opening_us == pytest.approx(m.t_open_s * 1e6, abs=0.005)


def test_runs_are_reproducible_by_seed(codec):
    sc = scenarios.get("faults")
    a = [f.data for k in range(6) for f in InjectorNode(lambda f: None, sc, 5, codec).frames_for(k % 4, 0, 0.1 * k)]
    b = [f.data for k in range(6) for f in InjectorNode(lambda f: None, sc, 5, codec).frames_for(k % 4, 0, 0.1 * k)]
    c = [f.data for k in range(6) for f in InjectorNode(lambda f: None, sc, 6, codec).frames_for(k % 4, 0, 0.1 * k)]
    assert a == b and a != c


def test_faults_injected_at_the_stated_rates(codec):
    sc = scenarios.get("faults")
    node = InjectorNode(lambda f: None, sc, 1, codec)
    frames = node.frames_for(0, 0, 0.0)[:-1] * 700           # about 10,000 frames
    stats = NodeStats()
    rng = np.random.default_rng(9)
    apply_faults(frames, sc, rng, stats)
    n = len(frames)
    for kind, rate in (("drop", sc.faults.drop), ("duplicate", sc.faults.duplicate), ("reorder", sc.faults.reorder)):
        assert abs(stats.faults[kind] / n - rate) < 4 * np.sqrt(rate / n) + 0.001, kind
    n_fd = sum(f.is_fd and len(f.data) == 64 for f in frames)
    assert abs(stats.faults["corrupt"] / n_fd - sc.faults.corrupt) < 4 * np.sqrt(sc.faults.corrupt / n_fd) + 0.001


class _Clock:
    """A monotonic clock the test moves: waiting advances it, sending costs a set time."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class _Stop:
    def __init__(self, clock: _Clock) -> None:
        self.clock = clock

    def is_set(self) -> bool:
        return False

    def wait(self, seconds: float) -> bool:
        self.clock.t += seconds
        return False


def test_scheduler_keeps_absolute_deadlines(codec):
    clock = _Clock()
    sent = []

    def send(frame):
        sent.append(clock.t)
        # the fourth injection's frames take 40 ms in all (longer than the 25 ms period)
        clock.t += 0.040 / 17 if len(sent) in range(3 * 17 + 1, 4 * 17 + 1) else 1e-5

    sc = scenarios.get("nominal", injectors=2, rate_hz=20.0)     # one injection every 25 ms
    node = InjectorNode(send, sc, 0, codec, clock=clock)
    stats = node.run(_Stop(clock), count=6)
    assert stats.injections == 12 and stats.frames == len(sent) == 12 * 17
    starts = np.array(sent[::17])
    due = starts[0] + 0.025 * np.arange(12)
    late = starts - due
    # the injection after the slow one starts late, the rest on their absolute deadlines: the
    # schedule catches up instead of drifting by the overrun
    assert np.all(np.abs(np.delete(late, 4)) < 1e-9), late
    assert 0.014 < late[4] < 0.016
    assert stats.late == 0 and 0.014 < stats.max_lateness_s < 0.016


def test_the_node_drives_an_injector_with_its_published_correction(codec):
    """``--apply-corrections``: a DriveCorrection from the bus scales the injector's plateau current and
    moves its start of charging; SimTruth reports the stroke and the opening instant that gives."""
    from estimator.codec.records import DriveCorrection, SimTruth

    sc = scenarios.get("nominal", injectors=2)

    def truth_of(node, injector):
        return next(codec.decode(f) for f in node.frames_for(injector, 0, 0.0) if codec.decode(f).__class__ is SimTruth)
    plain = truth_of(InjectorNode(lambda f: None, sc, 5, codec), 1)
    node = InjectorNode(lambda f: None, sc, 5, codec)
    node.take_correction(DriveCorrection(1, 0, 1.2, -10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 28.0, 1, 0, 0))
    corrected = truth_of(node, 1)
    assert node.source.applied == 1
    assert corrected.stroke_um > plain.stroke_um + 2.0                   # 20 % more charge in the 100 µs window
    assert corrected.opening_us < plain.opening_us - 10.0               # charged 10 µs earlier, and faster
    node.take_correction(DriveCorrection(1, 0, 1.2, -10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 28.0, 0, 0, 0))   # state none
    assert truth_of(node, 1).stroke_um == pytest.approx(plain.stroke_um, abs=0.5) and node.source.applied == 1


def test_the_correction_table_reaches_the_node_row_by_row(codec):
    """The processor sends two DriveCorrectionTable rows with each injection's correction, in turn; the
    node, once it has every row, applies the correction at any preload force as the estimator's own
    ``Correction.at`` does, and states its σ there as ``Correction.sigma_at`` does (to the wire's
    resolution)."""
    import math

    from estimator.codec.records import DriveCorrection, DriveCorrectionRow
    from estimator.drive.correction import DriveCompensator, DriveTarget
    from estimator.ident.measurement import Injection
    from estimator.pipeline import build_pipeline
    from estimator.pipeline.config import EstimatorConfig
    from sim_bench.hardware.plant import Plant

    _, _, processor, _ = build_pipeline(EstimatorConfig())
    processor.compensator = DriveCompensator(DriveTarget(amplifier_drive="trapezoid"))
    plant, rng = Plant(), np.random.default_rng(8)
    node = InjectorNode(lambda f: None, scenarios.get("nominal", injectors=2), 5, codec)
    rows_seen: list[int] = []
    for k in range(30):
        f = 40.0 + 8.0 * k
        m = plant.measure(17.0, 3e-6, f, rng)
        pub = processor.estimate(Injection(m.current_a, m.voltage_v, m.dt_s, f, 1, k, math.nan, 0.1 * k))
        for frame in pub.frames:
            rec = codec.decode(frame)
            if isinstance(rec, (DriveCorrection, DriveCorrectionRow)):
                node.take_correction(rec)
                if isinstance(rec, DriveCorrectionRow):
                    rows_seen.append(rec.row)
    c = pub.correction
    assert c is not None and c.valid and len(c.table) == len(DriveTarget().table_preloads_n)
    assert len(set(rows_seen)) == len(c.table) and len(rows_seen) <= 2 * 30
    on_node = node.source.corrections[1]
    assert len(on_node.table) == len(c.table)
    for f in (28.0, 33.0, 47.0, 150.0, 300.0):
        mine, theirs = c.at(f), on_node.at(f)
        assert abs(mine[0] - theirs[0]) < 3e-4 and abs(mine[1] - theirs[1]) < 0.05, (f, mine, theirs)
        mine, theirs = c.sigma_at(f), on_node.sigma_at(f)       # the σ each row states, on the wire too
        assert theirs[0] == pytest.approx(mine[0], rel=0.1, abs=2e-3) and theirs[1] == pytest.approx(
            mine[1], rel=0.1, abs=0.02), (f, mine, theirs)
