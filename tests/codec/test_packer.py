"""The codec's packer against cantools' strict encoder: the same bytes for every message the daemon
publishes or reads, over values inside, at the edges of and beyond each signal's range, NaN and
None included."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from estimator.codec.packer import packer_for
from estimator.codec.records import REGISTRY, Codec, SampleBlock

CODEC = Codec()
TYPES = [rt for rt in REGISTRY if rt is not SampleBlock]   # sample blocks have their own numpy packer


def _values(rt, rng: np.random.Generator, codec: Codec) -> dict:
    msg = codec.messages[rt]
    out = {}
    for f in dataclasses.fields(rt):
        sname = rt.SIGNALS.get(f.name)
        if sname is None:
            continue
        sig = msg.get_signal_by_name(sname)
        lo = sig.minimum if sig.minimum is not None else 0.0
        hi = sig.maximum if sig.maximum is not None else 1.0
        pick = rng.integers(8)
        if f.type in ("int", int):
            v = int(rng.integers(int(lo), int(hi) + 1)) if pick else int(hi)
        elif pick == 0:
            v = math.nan
        elif pick == 1:
            v = lo - abs(hi - lo) * rng.uniform(0.01, 2.0)    # below the range: saturated
        elif pick == 2:
            v = hi + abs(hi - lo) * rng.uniform(0.01, 2.0)    # above it
        elif pick == 3:
            v = float(rng.choice([lo, hi]))
        else:
            v = float(rng.uniform(lo, hi))
        out[f.name] = v
    return out


@pytest.mark.parametrize("rt", TYPES, ids=lambda rt: rt.__name__)
def test_the_packer_writes_what_cantools_writes(rt):
    assert packer_for(CODEC.messages[rt]) is not None, f"{rt.__name__} falls back to cantools"
    rng = np.random.default_rng(11)
    for _ in range(300):
        rec = rt(**_values(rt, rng, CODEC))
        fast, slow = CODEC.encode(rec), CODEC.encode_with_cantools(rec)
        assert fast == slow, (rec, fast.data.hex(), slow.data.hex())


def test_a_layout_it_does_not_cover_falls_back_to_cantools():
    class Big:     # a big-endian signal, as some DBCs have
        byte_order, is_float, length, start, is_signed = "big_endian", False, 8, 0, False

    class Msg:
        signals, length = [Big()], 8
    assert packer_for(Msg()) is None
