"""EstimatorCommand policy: off / reset-only / all, priors only within the physical ranges, undefined
codes counted; every refusal is counted in the heartbeat (CommandsRefused, CommandsUnknown)."""

from __future__ import annotations

import pytest

from estimator.codec.ingest import Counters
from estimator.codec.records import Codec, Command, EstimatorCommand, EstimatorStatus
from estimator.ident.config import TrackerConfig
from estimator.ident.tracking.tracker import Tracker, TrackerState
from estimator.pipeline.processor import Processor


def processor(policy: str) -> Processor:
    p = Processor(Codec(), Tracker(TrackerConfig()), Counters(), policy)
    p.tracker.states[1] = TrackerState().with_prior(17.0, 3.0)
    return p


def heartbeat(p: Processor) -> EstimatorStatus:
    return p.codec.decode(p.status_frame(0, 0.0, 1.0))


@pytest.mark.parametrize("policy, reset_applies, prior_applies", [
    ("off", False, False), ("reset-only", True, False), ("all", True, True)])
def test_policy(policy, reset_applies, prior_applies):
    p = processor(policy)
    p.handle([EstimatorCommand(2, Command.SET_PRIOR, 18.0, 4.0)])
    assert (2 in p.tracker.states) == prior_applies
    p.handle([EstimatorCommand(1, Command.RESET)])
    assert (1 not in p.tracker.states) == reset_applies
    hb = heartbeat(p)
    assert hb.commands_refused == (not reset_applies) + (not prior_applies)
    assert p.counters.commands_applied == reset_applies + prior_applies


@pytest.mark.parametrize("nu, lh", [(17.0, 14.9), (17.0, -2.5), (14.0, 3.0), (21.5, 3.0), (32.7, 32.7), (0.0, 0.0)])
def test_priors_outside_the_physical_ranges_are_refused(nu, lh):
    p = processor("all")
    p.handle([EstimatorCommand(2, Command.SET_PRIOR, nu, lh)])
    assert 2 not in p.tracker.states
    assert heartbeat(p).commands_refused == 1


def test_prior_at_the_range_edges_is_taken():
    p = processor("all")
    p.handle([EstimatorCommand(2, Command.SET_PRIOR, 21.0, 10.0), EstimatorCommand(3, Command.SET_PRIOR, 15.0, -2.0)])
    assert {2, 3} <= set(p.tracker.states)


def test_undefined_code_is_counted_in_the_heartbeat():
    """The shipped DBC's 2-bit Command has every code defined (3 is relearn); a site DBC with a wider
    signal can send others: they arrive as they are and are counted, never applied."""
    codec = Codec()
    from estimator.codec.ingest import Ingest
    ing = Ingest(codec)
    p = Processor(codec, Tracker(TrackerConfig()), ing.counters, "all")
    for _ in range(3):
        p.handle([EstimatorCommand(1, 5, 0.0, 0.0)])
    hb = heartbeat(p)
    assert hb.commands_unknown == 3 and hb.commands_refused == 0 and p.counters.commands_applied == 0


def test_counters_roll_at_their_signal_width():
    p = processor("off")
    p.counters.commands_refused = 65536 + 5
    p.counters.accepted = 2 ** 32 + 7
    hb = heartbeat(p)
    assert hb.commands_refused == 5 and hb.accepted == 7


def test_output_frames_are_encoded_when_asked_for_and_equal_the_eager_encoding():
    """A Published injection encodes its frames on first access (rows do not need them), once, and they
    are the frames output_frames gives."""
    import numpy as np

    from estimator.codec.injection_frames import injection_frames
    from estimator.pipeline import build_pipeline
    from estimator.pipeline.processor import output_frames
    from estimator.service.config import DaemonConfig
    from sim_bench.hardware.plant import Plant, PlantConfig

    codec, ingest, processor, clock = build_pipeline(DaemonConfig(self_calibration=None))
    m = Plant(PlantConfig(window_s=100e-6)).measure(17.0, 3e-6, 30.0, np.random.default_rng(1))
    pubs = []
    for k, fr in enumerate(injection_frames(codec, 2, 7, m.dt_s, m.current_a, m.voltage_v)):
        pubs += processor.handle(ingest.feed(fr, clock.on_frame(1.0 + 1e-4 * k)))
    assert len(pubs) == 1
    pub = pubs[0]
    assert "frames" not in vars(pub)                  # not encoded yet
    calls = []
    encode = codec.encode
    codec.encode = lambda rec: calls.append(rec) or encode(rec)
    frames = pub.frames
    assert pub.frames is frames and len(calls) == 4   # encoded once, cached (with the drive correction)
    codec.encode = encode
    assert [f.data for f in frames[:3]] == [f.data for f in output_frames(codec, 2, 7, pub.result)]
    from estimator.codec.records import DriveCorrection, EstimateQuality, EstimateState, ValvePrediction
    assert [f.arbitration_id for f in frames] == [codec.frame_id(r) for r in (EstimateState, EstimateQuality,
                                                                             ValvePrediction, DriveCorrection)]
