"""Shared test helpers: simulated measurements as the estimator receives them."""

from __future__ import annotations

import numpy as np

from estimator.ident.measurement import Injection
from sim_bench.hardware.plant import Plant, PlantConfig

_PLANTS: dict[tuple, Plant] = {}

# Simulations an update reports, to tell a cold start from a warm update of the clean test traces:
# a warm update 7-16 (one to four compiled cycles), a local-first cold start 29-53 (two Gauss-Newton
# fits, the 16-probe ring of the published one, the valve prediction), the global search 450-700.
WARM_MAX_EVALUATIONS = 20
COLD_MIN_EVALUATIONS = 26


def measured(nu: float, lh_um: float, seed: int, mismatch: bool = False, f_open_n: float = 28.0,
             window_s: float = 150e-6, **kw) -> tuple[Injection, object]:
    """One noisy, quantised injection from the simulated plant, and the plant's Measurement (truth)."""
    key = (mismatch, window_s, tuple(sorted(kw.items())))
    if key not in _PLANTS:
        _PLANTS[key] = Plant(PlantConfig(mismatch=mismatch, window_s=window_s, **kw))
    m = _PLANTS[key].measure(nu, lh_um * 1e-6, f_open_n, np.random.default_rng(seed))
    return Injection(m.current_a, m.voltage_v, m.dt_s, m.f_open_n), m


def injection_messages(injector: int, n: int, seed: int, frame_dt_s: float = 2e-4, gap_s: float = 0.05,
                       t0: float = 1000.0) -> list:
    """python-can messages of ``n`` simulated injections of one injector, timestamped like a bus capture."""
    from estimator.codec.injection_frames import injection_frames
    from estimator.codec.records import Codec
    from estimator.io.captures import to_message

    codec = Codec()
    out, t = [], t0
    for k in range(n):
        inj, _ = measured(17.0, 3.0, seed + k, window_s=100e-6)
        for fr in injection_frames(codec, injector, k, inj.dt_s, inj.current_a, inj.voltage_v):
            t += frame_dt_s
            out.append(to_message(fr, timestamp=t))
        t += gap_s
    return out


def record_codes(monkeypatch, module, name: str) -> list:
    """Wrap ``module.name`` (a function returning something with a ``code``) so that each call's code is
    appended to the list returned; the call's result is passed on unchanged."""
    codes: list = []
    real = getattr(module, name)

    def recording(*args):
        out = real(*args)
        codes.append(out.code)
        return out
    monkeypatch.setattr(module, name, recording)
    return codes
