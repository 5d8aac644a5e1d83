"""The CAN contract: DBC loads strictly, every message round-trips, numpy and cantools agree."""

from __future__ import annotations

import math
import random

import cantools
import numpy as np
import pytest

from estimator.codec.database import check_contract
from estimator.codec.errors import ContractError, MalformedFrame
from estimator.codec.frame import Frame
from estimator.codec.records import (
    CONTRACT,
    Codec,
    EstimateQuality,
    EstimateState,
    EstimatorCommand,
    EstimatorStatus,
    InjectionHeader,
    InjectionTrailer,
    SampleBlock,
    SimTruth,
    ValvePrediction,
    load_database,
)
from estimator.codec.samples import samples_crc32

from ..conftest import REPO

DBC = REPO / "dbc" / "injector.dbc"


@pytest.fixture(scope="module")
def codec() -> Codec:
    return Codec()


def test_dbc_loads_strict_and_satisfies_contract():
    db = cantools.database.load_file(str(DBC), strict=True)
    assert check_contract(db, CONTRACT) == []
    assert db.dbc.attributes["BusType"].value == "CAN FD"
    for name in CONTRACT:
        assert "VFrameFormat" in db.get_message_by_name(name).dbc.attributes
    samples = db.get_message_by_name("InjectionSamples")
    assert samples.is_fd and samples.length == 64
    state = db.get_message_by_name("EstimateState")
    assert not state.is_fd and state.length == 8


def test_contract_violations_are_reported(tmp_path):
    text = DBC.read_text().replace("SG_ Crc32 ", "SG_ Crc ")
    bad = tmp_path / "bad.dbc"
    bad.write_text(text)
    with pytest.raises(ContractError, match="InjectionTrailer: signal Crc32 missing"):
        load_database(bad)
    with pytest.raises(ContractError, match="not found"):
        load_database(tmp_path / "none.dbc")


RECORDS = [
    InjectionHeader(3, 200, 500, 201, 28.5, 41.0),
    InjectionTrailer(7, 255, 0xDEADBEEF),
    EstimateState(1, 17, 16.3905, -1.234, 0),
    EstimateQuality(0, 3, 51.2, 0.0123, 0.045, 17, 1),
    ValvePrediction(5, 9, 35.12, 38.66, 22.591),
    ValvePrediction(5, 10, 35.12, float("nan"), float("nan")),
    EstimatorStatus(123456, 1, 2, 3, 4, 5, 6, 7, 12, 1.25, 3600, 9),
    EstimatorCommand(4, 2, 16.5, 2.5),
    SimTruth(2, 77, 18.25, 6.8, 54.49, 56.59, 18.382, 85.0, 150.0),
]


@pytest.mark.parametrize("rec", RECORDS, ids=lambda r: type(r).__name__)
def test_every_message_round_trips(codec, rec):
    frame = codec.encode(rec)
    back = codec.decode(frame)
    assert type(back) is type(rec)
    for k, v in rec.__dict__.items():
        w = getattr(back, k)
        if isinstance(v, float) and math.isnan(v):
            assert math.isnan(w)
        else:
            assert w == pytest.approx(v, abs=1e-3), k


def test_values_saturate_to_the_signal_range(codec):
    back = codec.decode(codec.encode(EstimateQuality(0, 0, 1e9, 1e9, float("nan"), 10**9, 1)))
    assert back.cost_uvs == pytest.approx(6553.5) and back.evaluations == 65535 and back.sigma_lh_um == 0.0


def test_numpy_and_cantools_decode_samples_identically(codec):
    rng = np.random.default_rng(5)
    msg = codec.messages[SampleBlock]
    for _ in range(200):
        cur = rng.integers(-32767, 32768, codec.layout.per_block).astype("<i2")
        vol = rng.integers(-32767, 32768, codec.layout.per_block).astype("<i2")
        inj, cnt, blk = int(rng.integers(0, 8)), int(rng.integers(0, 256)), int(rng.integers(0, 255))
        fr = codec.encode_samples(inj, cnt, blk, cur, vol)
        ref = msg.decode(fr.data, decode_choices=False, scaling=True)
        ours = codec.decode(fr)
        assert (ours.injector_id, ours.counter, ours.block_index) == (ref["InjectorId"], ref["InjectionCounter"],
                                                                      ref["BlockIndex"])
        for k in range(codec.layout.per_block):
            assert ours.current_raw[k] * codec.layout.current_scale == pytest.approx(ref[f"Current_{k}"], abs=1e-9)
            assert ours.voltage_raw[k] * codec.layout.voltage_scale == pytest.approx(ref[f"Voltage_{k}"], abs=1e-9)
        # and the cantools encoder produces the same bytes as the numpy packer
        values = {**{f"Current_{k}": float(cur[k]) * 0.001 for k in range(15)},
                  **{f"Voltage_{k}": float(vol[k]) * 0.01 for k in range(15)},
                  "InjectorId": inj, "InjectionCounter": cnt, "BlockIndex": blk}
        assert bytes(msg.encode(values, strict=True)) == fr.data


def test_malformed_frames_raise(codec):
    good = codec.encode(RECORDS[0])
    with pytest.raises(MalformedFrame, match="bytes"):
        codec.decode(Frame(good.arbitration_id, good.data[:5]))
    samples = codec.encode_samples(0, 0, 0, np.zeros(15, "<i2"), np.zeros(15, "<i2"))
    with pytest.raises(MalformedFrame, match="CAN FD"):
        codec.decode(Frame(samples.arbitration_id, samples.data, is_fd=False))
    assert codec.decode(Frame(0x7FF, b"\0" * 8)) is None


def test_crc_depends_on_every_sample():
    rng = np.random.default_rng(1)
    c = rng.integers(-1000, 1000, 201).astype("<i2")
    v = rng.integers(-1000, 1000, 201).astype("<i2")
    ref = samples_crc32(c, v)
    for k in random.Random(0).sample(range(201), 20):
        c2 = c.copy()
        c2[k] ^= 1
        assert samples_crc32(c2, v) != ref
    assert samples_crc32(v, c) != ref


def test_per_injector_messages_are_multiplexed_for_cantools_monitor():
    """EstimateState, EstimateQuality, ValvePrediction and SimTruth carry InjectorId as multiplexer
    (extended multiplexing over 0-7): cantools monitor keys its rows by it, one row per injector."""
    import cantools
    from cantools.subparsers.__utils__ import format_multiplexed_name

    db = cantools.database.load_file(str(DBC), strict=True)
    for name in ("EstimateState", "EstimateQuality", "ValvePrediction", "SimTruth"):
        msg = db.get_message_by_name(name)
        assert msg.is_multiplexed()
        assert [s.name for s in msg.signals if s.is_multiplexer] == ["InjectorId"]
        assert all(s.multiplexer_ids == list(range(8)) for s in msg.signals if not s.is_multiplexer)
    codec = Codec()
    msg = db.get_message_by_name("EstimateState")
    rows = set()
    for inj in range(4):
        fr = codec.encode(EstimateState(inj, 7, 17.0 + inj, 2.0 + inj, 0))
        decoded = msg.decode(fr.data)
        rows.add(format_multiplexed_name(msg, decoded))
        assert codec.decode(fr) == EstimateState(inj, 7, 17.0 + inj, 2.0 + inj, 0)
    assert rows == {f"EstimateState :: InjectorId={k}" for k in range(4)}
