"""Electrical calibration benchmark: seeded series parts calibrated from a batch of their own
injections, then judged on new injections with the nominal and with the calibrated parameters.

Each part draws every structural parameter within ±10 % of Tables 1-2 (:mod:`sim_bench.series_part`);
its batch is six injections at preload forces 28-300 N and N_u 15.5-20 N/V (0.1 V noise, 200 µs sent);
then three new injections at the nominal preload (N_u 16.2, 17.5, 19.8 N/V) are identified from a cold
start. Targets: the calibrated residual within 20 % of the noise level, every new injection ``ok``
with |L_h error| <= 0.2 µm and within 3 sigma.
"""

from __future__ import annotations

import time

import numpy as np

from estimator.ident.electrical import calibrate_electrical
from estimator.ident.idle_stroke import identify
from estimator.ident.measurement import Injection
from estimator.model.fast_sim import FastSimulator
from estimator.model.parameters import NOMINAL_PRELOAD_N
from sim_bench import series_part
from sim_bench.plant import Plant, PlantConfig
from sim_bench.table import keyed, render

LH_UM = 3.0
BATCH = ((28.0, 15.5), (60.0, 17.0), (100.0, 18.5), (150.0, 20.0), (220.0, 16.0), (300.0, 19.5))
CHECK_NU = (16.2, 17.5, 19.8)
NOISE_V = 0.1
LH_TARGET_UM = 0.2


def run(parts: int = 3, seed: int = 3) -> dict:
    """Calibrate ``parts`` seeded series parts (seeds ``seed``, ``seed + 1``, ...); a JSON-ready report."""
    rows = []
    for p in range(parts):
        rng = np.random.default_rng(seed + p)
        part = series_part.draw(rng)
        plant = Plant(PlantConfig(window_s=200e-6), part.params)
        batch = []
        for f, nu in BATCH:
            m = plant.measure(nu, LH_UM * 1e-6, f, rng)
            batch.append(Injection(m.current_a, m.voltage_v, m.dt_s, f))
        t0 = time.perf_counter()
        res = calibrate_electrical(batch)
        seconds = time.perf_counter() - t0
        nominal, own = [], []
        for nu in CHECK_NU:
            m = plant.measure(nu, LH_UM * 1e-6, NOMINAL_PRELOAD_N, rng)
            inj = Injection(m.current_a[:201], m.voltage_v[:201], m.dt_s, NOMINAL_PRELOAD_N)
            nominal.append(identify(inj, FastSimulator(dt_s=m.dt_s)))
            own.append(identify(inj, FastSimulator(res.params, m.dt_s)))
        err_nom = [e.lh_m * 1e6 - LH_UM for e in nominal]
        err_own = [e.lh_m * 1e6 - LH_UM for e in own]
        z_own = [abs(e) / (o.sigma_lh_m * 1e6) for e, o in zip(err_own, own)]
        fails = []
        if res.rms_after_v > 1.2 * NOISE_V:
            fails.append(f"residual {res.rms_after_v:.3f} V above 1.2 x noise")
        if not all(o.status.value == "ok" for o in own):
            fails.append("a new injection not ok with the calibrated parameters: " + ", ".join(o.status.value for o in own))
        if max(map(abs, err_own)) > LH_TARGET_UM or max(z_own) > 3:
            fails.append(f"L_h error {max(map(abs, err_own)):.3f} µm ({max(z_own):.1f} sigma)")
        rows.append({"part": p, "seed": seed + p, "describe": part.describe(), "rms_before_v": res.rms_before_v,
                     "rms_after_v": res.rms_after_v, "max_abs_lh_nominal_um": float(max(map(abs, err_nom))),
                     "nominal_statuses": [e.status.value for e in nominal],
                     "max_abs_lh_calibrated_um": float(max(map(abs, err_own))), "max_z_calibrated": float(max(z_own)),
                     "calibrated_statuses": [e.status.value for e in own], "weak": res.weak,
                     "max_factor_error_pct": float(max(abs(f / part.factors[n] - 1) for n, f in zip(res.names, res.factors)) * 100),
                     "seconds": seconds, "evaluations": res.evaluations, "failures": fails, "passed": not fails})
    return {"benchmark": "electrical-calibration", "parts": parts, "seed": seed, "rows": rows,
            "passed": all(r["passed"] for r in rows)}


COLUMNS = [keyed("part", "seed", ">5", "seed"), keyed("resid before", "[V]", ">12.3f", "rms_before_v"),
           keyed("after", "[V]", ">6.3f", "rms_after_v"), keyed("max|dLh| nominal", "[µm]", ">16.3f", "max_abs_lh_nominal_um"),
           keyed("calibrated", "[µm]", ">10.3f", "max_abs_lh_calibrated_um"), keyed("max z", "", ">6.2f", "max_z_calibrated"),
           keyed("max factor err", "[%]", ">14.2f", "max_factor_error_pct"), keyed("time", "[s]", ">5.1f", "seconds")]


def format_report(rep: dict) -> str:
    """The table: one row per part, its verdict."""
    title = (f"electrical calibration - {rep['parts']} series parts (±10 %), batch of {len(BATCH)} at 28-300 N; "
             f"targets: residual <= 1.2 x {NOISE_V} V, new injections ok within {LH_TARGET_UM} µm and 3 sigma")
    return title + "\n" + render(COLUMNS, rep["rows"], lambda r: "PASS" if r["passed"] else "FAIL: " + "; ".join(r["failures"]))
