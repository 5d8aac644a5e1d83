"""Fuzz: >= 100,000 bad frames interleaved with valid injections; nothing raises, nothing is lost,
every bad injection is counted exactly once under its reason, every bad frame under its counter."""

from __future__ import annotations

import random
from collections import Counter

import pytest

from estimator.codec.frame import Frame
from estimator.codec.ingest import Ingest
from estimator.codec.injection_frames import injection_frames
from estimator.codec.records import Codec
from estimator.ident.tracking.tracker import Tracker
from estimator.pipeline.processor import Processor

from ..helpers import measured

INPUT_IDS = (0x100, 0x101, 0x102, 0x220)


def _flip(f: Frame, rng: random.Random) -> Frame:
    d = bytearray(f.data)
    i = rng.randrange(3, 63)   # sample pairs only: identification bytes 0-2 intact; byte 63 is spare
    d[i] ^= 1 << rng.randrange(8)
    return Frame(f.arbitration_id, bytes(d), f.is_fd)


def _recount(codec: Codec, f: Frame) -> Frame:
    blk = codec.decode(f)
    return codec.encode_samples(blk.injector_id, (blk.counter + 1) % 256, blk.block_index, blk.current_raw,
                                blk.voltage_raw)


FAULTS = {   # name -> (mutation of the injection's frame list, expected reason, extra malformed frames)
    "drop_block": (lambda fr, r, c: fr[:2] + fr[3:], "missing", 0),
    "duplicate_block": (lambda fr, r, c: [*fr[:3], fr[2], *fr[3:]], "duplicate", 0),
    "swap_blocks": (lambda fr, r, c: [*fr[:2], fr[3], fr[2], *fr[4:]], "order", 0),
    "corrupt_sample": (lambda fr, r, c: [*fr[:4], _flip(fr[4], r), *fr[5:]], "crc", 0),
    "drop_header": (lambda fr, r, c: fr[1:], "missing", 0),
    "truncate_block": (lambda fr, r, c: [*fr[:5], Frame(fr[5].arbitration_id, fr[5].data[:20], True), *fr[6:]],
                       "missing", 1),
    "wrong_counter": (lambda fr, r, c: [*fr[:6], _recount(c, fr[6]), *fr[7:]], "counter", 0),
    "drop_trailer": (lambda fr, r, c: fr[:-1], "missing_or_timeout", 0),
}


@pytest.mark.timeout(600)
def test_fuzz_100k_frames():
    rng = random.Random(1234)
    codec = Codec()
    ingest = Ingest(codec, timeout_s=1e6)            # timeouts only at the final poll
    processor = Processor(codec, Tracker(), ingest.counters)
    injectors = {i: (16.0 + 0.5 * i, 1.0 + 2.0 * i) for i in range(4)}
    streams: dict[int, list[tuple[str, list[Frame]]]] = {i: [] for i in injectors}
    valid = 0
    counter = {i: 0 for i in injectors}
    for k in range(360):
        inj = k % 4
        nu, lh = injectors[inj]
        m_inj, _ = measured(nu, lh, 10_000 + k, window_s=100e-6)
        fr = injection_frames(codec, inj, counter[inj], m_inj.dt_s, m_inj.current_a, m_inj.voltage_v)
        counter[inj] = (counter[inj] + 1) % 256
        if k < 8 or rng.random() < 0.2:
            streams[inj].append(("valid", fr))
            valid += 1
        else:
            name = rng.choice(sorted(FAULTS))
            mutate, _reason, _ = FAULTS[name]
            streams[inj].append((name, mutate(fr, rng, codec)))
    # the injection streams interleaved at random, injections of one injector in order
    queues = {i: [f for _, fr in streams[i] for f in fr] for i in injectors}
    merged: list[Frame] = []
    while any(queues.values()):
        i = rng.choice([i for i in queues if queues[i]])
        merged.append(queues[i].pop(0))
    # noise: unknown identifiers, and known input identifiers with wrong lengths or formats
    n_unknown = n_malformed = 0
    noise: list[Frame] = []
    while len(noise) + len(merged) < 100_500:
        if rng.random() < 0.5:
            aid = rng.choice([a for a in range(0x000, 0x7FF, 7) if a not in INPUT_IDS])
            noise.append(Frame(aid, bytes(rng.randrange(256) for _ in range(rng.choice((0, 3, 8, 12, 64)))),
                               rng.random() < 0.5))
            n_unknown += 1
        else:
            aid = rng.choice(INPUT_IDS)
            good_len = {0x100: 8, 0x101: 64, 0x102: 8, 0x220: 8}[aid]
            length = rng.choice([n for n in (0, 1, 7, 12, 16, 32, 48) if n != good_len])
            noise.append(Frame(aid, bytes(length), aid == 0x101 or rng.random() < 0.5))
            n_malformed += 1
    stream: list[Frame] = []
    positions = sorted(rng.sample(range(len(merged) + len(noise)), len(noise)))
    it_noise, it_merged, pos = iter(noise), iter(merged), set(positions)
    for i in range(len(merged) + len(noise)):
        stream.append(next(it_noise) if i in pos else next(it_merged))
    assert len(stream) >= 100_000

    published = []
    for i, f in enumerate(stream):
        published += processor.handle(ingest.feed(f, i * 1e-6))
    published += processor.handle(ingest.poll(1e9))

    c = ingest.counters
    faults = Counter(name for i in injectors for name, _ in streams[i] if name != "valid")
    assert len(published) == valid
    assert c.accepted + c.rejected_outlier == valid
    assert c.frames_unknown == n_unknown
    assert c.frames_malformed == n_malformed + faults["truncate_block"]
    bad = sum(faults.values())
    assert c.rejected_crc + c.rejected_missing + c.rejected_timeout + c.rejected_invalid == bad
    assert c.reasons.get("crc", 0) == faults["corrupt_sample"]
    assert c.reasons.get("duplicate", 0) == faults["duplicate_block"]
    assert c.reasons.get("order", 0) == faults["swap_blocks"]
    assert c.reasons.get("counter", 0) == faults["wrong_counter"]
    assert c.reasons.get("missing", 0) + c.reasons.get("timeout", 0) == (
        faults["drop_block"] + faults["drop_header"] + faults["truncate_block"] + faults["drop_trailer"])
    # the valid injections were estimated, and the estimates converge to each injector's truth
    last = {p.injector_id: p for p in published}
    for inj, (_nu, lh) in injectors.items():
        assert abs(last[inj].result.lh_m * 1e6 - lh) < 0.3
