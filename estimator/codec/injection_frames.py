"""The amplifier's side of the contract: one injection's samples as header, sample blocks, trailer."""

from __future__ import annotations

import numpy as np

from estimator.codec.frame import Frame
from estimator.codec.records import Codec, InjectionHeader, InjectionTrailer
from estimator.codec.samples import samples_crc32
from estimator.model.parameters import NOMINAL_PRELOAD_N


def injection_frames(codec: Codec, injector_id: int, counter: int, sample_period_s: float, current_a: np.ndarray,
                     voltage_v: np.ndarray, preload_force_n: float = NOMINAL_PRELOAD_N,
                     fuel_temperature_c: float = 40.0) -> list[Frame]:
    """Header, ceil(N/per_block) sample blocks and trailer (with the CRC over the raw samples)."""
    cur_raw, vol_raw = codec.layout.to_raw(current_a, voltage_v)
    n = cur_raw.size
    period_ns = int(round(sample_period_s * 1e9))
    # NaN: not measured (the codec sends the DBC's "not measured" value)
    frames = [codec.encode(InjectionHeader(injector_id, counter, period_ns, n, preload_force_n, fuel_temperature_c))]
    per = codec.layout.per_block
    for b in range(-(-n // per)):
        sl = slice(b * per, min((b + 1) * per, n))
        frames.append(codec.encode_samples(injector_id, counter, b, cur_raw[sl], vol_raw[sl]))
    frames.append(codec.encode(InjectionTrailer(injector_id, counter, samples_crc32(cur_raw, vol_raw))))
    return frames
