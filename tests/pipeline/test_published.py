"""One published-estimate record (Published) that the JSON line, the table row and the CAN frames
render: the same estimate in each, in its own units."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.codec.records import Codec, EstimateState, ValvePrediction
from estimator.ident.measurement import Injection
from estimator.pipeline import EstimatorConfig, build_pipeline
from sim_bench.hardware.plant import Plant, PlantConfig


def test_json_row_and_frames_render_one_record():
    codec, _, processor, _ = build_pipeline(EstimatorConfig())
    rng = np.random.default_rng(5)
    plant = Plant(PlantConfig())
    pub = None
    for k in range(5):   # the amplifier's drive is learned from the first four
        m = plant.measure(17.2, 3.1e-6, 28.0, rng)
        pub = processor.estimate(Injection(m.current_a, m.voltage_v, m.dt_s, 28.0, 2, k, float("nan"), 0.01 * k))
    assert pub is not None
    line, row = pub.to_dict(), pub.to_row(0.02)
    states = [codec.decode(f) for f in pub.frames]
    state = next(r for r in states if isinstance(r, EstimateState))
    valve = next(r for r in states if isinstance(r, ValvePrediction))
    assert line["status"] == row["status"] == "ok" and line["injector_id"] == row["injector_id"] == state.injector_id == 2
    assert line["filtered"]["lh_um"] == row["lh_um"] == pytest.approx(state.lh_um, abs=1e-3)
    assert line["filtered"]["t_open_us"] == row["t_open_us"] == pytest.approx(valve.opening_us, abs=0.05)
    assert line["drive_correction"]["scale"] == pytest.approx(row["drive_scale"], abs=1e-5)
    assert line["learning"]["state"] == row["learning"] == "idle"
    assert isinstance(codec, Codec)
