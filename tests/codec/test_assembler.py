"""Per-injection validity: every fault rejects that injection with its reason; the next one is fine."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.codec.assembler import Completed, Rejected
from estimator.codec.frame import Frame
from estimator.codec.ingest import Ingest
from estimator.codec.injection_frames import injection_frames
from estimator.codec.records import Codec


@pytest.fixture(scope="module")
def codec() -> Codec:
    return Codec()


def frames(codec, inj=0, cnt=1, n=201, seed=0):
    rng = np.random.default_rng(seed)
    cur = 4.0 + 0.1 * rng.standard_normal(n)
    vol = 50.0 + rng.standard_normal(n)
    return injection_frames(codec, inj, cnt, 0.5e-6, cur, vol, 28.0, 40.0), cur, vol


def run(ing, frs, t0=0.0, dt=1e-4):
    ev = []
    for i, f in enumerate(frs):
        ev += ing.feed(f, t0 + i * dt)
    return ev


def test_good_injection_completes_with_physical_values(codec):
    frs, cur, vol = frames(codec)
    ev = run(Ingest(codec), frs)
    assert len(ev) == 1 and isinstance(ev[0], Completed)
    assert np.max(np.abs(ev[0].current_a - cur)) <= 0.0005 + 1e-12
    assert np.max(np.abs(ev[0].voltage_v - vol)) <= 0.005 + 1e-12
    assert ev[0].header.sample_period_ns == 500 and ev[0].header.sample_count == 201


def _corrupt_sample(f: Frame) -> Frame:
    d = bytearray(f.data)
    d[10] ^= 0x40
    return Frame(f.arbitration_id, bytes(d), f.is_fd)


FAULTS = {
    "drop a block": (lambda fr: fr[:3] + fr[4:], "missing"),
    "duplicate a block": (lambda fr: [*fr[:3], fr[2], *fr[3:]], "duplicate"),
    "swap two blocks": (lambda fr: [*fr[:2], fr[3], fr[2], *fr[4:]], "order"),
    "corrupt a sample": (lambda fr: [*fr[:2], _corrupt_sample(fr[2]), *fr[3:]], "crc"),
    "drop the header": (lambda fr: fr[1:], "missing"),
}


@pytest.mark.parametrize("name", sorted(FAULTS))
def test_each_fault_rejects_once_and_next_injection_is_fine(codec, name):
    mutate, reason = FAULTS[name]
    ing = Ingest(codec)
    bad, _, _ = frames(codec, cnt=1)
    good, _, _ = frames(codec, cnt=2, seed=1)
    ev = run(ing, mutate(bad)) + run(ing, good, t0=1.0)
    rejected = [e for e in ev if isinstance(e, Rejected)]
    completed = [e for e in ev if isinstance(e, Completed)]
    assert [r.reason for r in rejected] == [reason] and rejected[0].counter == 1
    assert len(completed) == 1 and completed[0].header.counter == 2
    assert ing.counters.reasons == {reason: 1}


def test_header_without_trailer_times_out(codec):
    ing = Ingest(codec, timeout_s=0.05)
    frs, _, _ = frames(codec)
    ev = run(ing, frs[:-1])
    assert ev == []
    ev = ing.poll(1.0)
    assert [e.reason for e in ev] == ["timeout"] and ing.counters.rejected_timeout == 1
    assert run(ing, frs[-1:], t0=1.0) == []          # the late trailer is not counted twice
    assert ing.counters.rejected_missing == 0


def test_counter_and_sample_count_mismatch(codec):
    ing = Ingest(codec)
    a, _, _ = frames(codec, cnt=5)
    b, _, _ = frames(codec, cnt=6)
    ev = run(ing, a[:-1] + b[-1:])
    assert [e.reason for e in ev if isinstance(e, Rejected)] == ["counter"]
    data, _, _ = frames(codec, cnt=7, n=201)      # 14 blocks
    fewer, _, _ = frames(codec, cnt=7, n=180)     # a header announcing 12 blocks
    ev = run(ing, [fewer[0], *data[1:]])
    assert [e.reason for e in ev if isinstance(e, Rejected)] == ["invalid"]
    more, _, _ = frames(codec, cnt=8, n=205)      # a header announcing 205 samples, 201 sent
    data, _, _ = frames(codec, cnt=8, n=201)
    ev = run(ing, [more[0], *data[1:]], t0=2.0)
    assert [e.reason for e in ev if isinstance(e, Rejected)] == ["crc"]   # the trailer's CRC covers 201
    assert ing.counters.rejected_missing == 1 and ing.counters.rejected_invalid == 1


def test_nan_samples_rejected_as_invalid(codec):
    cur = np.full(201, 4.0)
    cur[50] = np.nan
    frs = injection_frames(codec, 0, 1, 0.5e-6, cur, np.full(201, 50.0))
    ev = run(Ingest(codec), frs)
    assert [e.reason for e in ev] == ["invalid"]


def test_injectors_are_independent(codec):
    ing = Ingest(codec)
    a, _, _ = frames(codec, inj=0, cnt=1)
    b, _, _ = frames(codec, inj=1, cnt=1, seed=2)
    inter = [f for pair in zip(a, b) for f in pair]
    ev = run(ing, inter)
    assert sorted(e.header.injector_id for e in ev if isinstance(e, Completed)) == [0, 1]
