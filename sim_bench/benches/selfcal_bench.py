"""Self-calibration benchmark: seeded series injectors learn their own model from their own current
and voltage, and are then judged on injections the calibration never saw.

Each injector draws every structural parameter within ±10 % of Tables 1-2
(:mod:`sim_bench.hardware.series_part`), its own idle stroke (1.5-6 µm) and coupling-factor offset, and makes
60 injections while it warms up (N_u rising by 3.8 N/V) and the rail pressure cycles (preload force
28-300 N, :data:`PRELOADS`); 0.1 V noise, 200 µs sent. Variants:

- ``plain``: the series part alone;
- ``chain``: behind a typical amplifier chain (300 kHz filter on U, I one sample late) the
  calibration is not told about;
- ``mismatch``: the chain plus the hysteresis/series-resistance plant, which no parameter set of the
  model explains: the calibration must say so (and is then not used), the estimates stay honest.

**Offline**: :func:`~estimator.ident.learning.electrical.calibrate_electrical` on the first 30 injections,
the result written as a parameter file and loaded back as a user would (``--params``); each of the
last 30 identified alone (cold start) with it and, for comparison, with the nominal parameters.
Targets (``plain`` and ``chain``): L_h RMS <= 0.1 µm, max <= 0.2 µm, N_u within 0.2 %, each
calibrated parameter within 3 of its reported standard deviations of the truth in >= 95 %;
(``mismatch``): no ``ok`` estimate more than 0.3 µm off.
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from estimator.ident.fit.idle_stroke import identify
from estimator.ident.learning.electrical import calibrate_electrical
from estimator.ident.learning.selfcal import CalibrationStatus, SelfCalConfig
from estimator.ident.measurement import Injection
from estimator.ident.tracking.tracker import Tracker
from estimator.model.fast_sim import FastSimulator
from estimator.model.parameters import NOMINAL_PRELOAD_N, InjectorParameters, load_nominal
from sim_bench.benches.table import Column, keyed, render, verdict
from sim_bench.hardware import series_part
from sim_bench.hardware.plant import Plant, PlantConfig

VARIANTS = ("plain", "chain", "mismatch")
INJECTIONS, CALIBRATE_FIRST = 60, 30
PRELOADS = (NOMINAL_PRELOAD_N, 45.0, 70.0, 100.0, 140.0, 190.0, 250.0, 300.0, 220.0, 120.0)   # N, one rail-pressure cycle
NU_START, NU_RISE, NU_OFFSET = 15.8, 3.8, 0.3      # N/V: warm-up from NU_START (± offset), rising linearly
LH_UM = (1.5, 6.0)
WINDOW_S = 200e-6
LH_RMS_UM, LH_MAX_UM, NU_PCT, Z_PARAM, Z_SHARE = 0.1, 0.2, 0.2, 3.0, 0.95
MISMATCH_LH_MAX_UM = 0.3


def injector_sequence(rng: np.random.Generator) -> tuple[float, list[tuple[float, float]]]:
    """An injector's idle stroke (µm) and its (N_u N/V, preload N) per injection."""
    lh = float(rng.uniform(*LH_UM))
    nu0 = NU_START + float(rng.uniform(-NU_OFFSET, NU_OFFSET))
    return lh, [(nu0 + NU_RISE * k / (INJECTIONS - 1), PRELOADS[k % len(PRELOADS)]) for k in range(INJECTIONS)]


def run_injector(variant: str, seed: int) -> dict:
    """One seeded series injector of ``variant`` through the offline calibration; a JSON-ready row."""
    rng = np.random.default_rng(seed)
    chain = series_part.TYPICAL_CHAIN if variant in ("chain", "mismatch") else series_part.NO_CHAIN
    part = series_part.draw(rng, chain=chain, mismatch=variant == "mismatch")
    plant = Plant(PlantConfig(window_s=WINDOW_S, chain=part.chain, mismatch=part.mismatch), part.params)
    lh, seq = injector_sequence(rng)
    injections, truth = [], []
    for k, (nu, f) in enumerate(seq):
        m = plant.measure(nu, lh * 1e-6, f, rng)
        injections.append(Injection(m.current_a, m.voltage_v, m.dt_s, f, 0, k % 256))
        truth.append(nu)
    t0 = time.perf_counter()
    res = calibrate_electrical(injections[:CALIBRATE_FIRST])
    seconds = time.perf_counter() - t0
    # the way a user carries it: a parameter file. A calibration that does not explain its batch is
    # refused (``calibrate --electrical`` exits 1): the injector keeps the parameters it had
    own_params = load_nominal()
    if res.adequate:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "injector.toml"
            path.write_text(res.params.to_toml(f"electrical calibration of series injector seed {seed}"))
            own_params = InjectorParameters.from_toml(path)
    own, nominal = FastSimulator(own_params), FastSimulator()
    rows_own: list[tuple] = []
    rows_nom: list[tuple] = []
    for inj, nu in zip(injections[CALIBRATE_FIRST:], truth[CALIBRATE_FIRST:]):
        for sim, out in ((own, rows_own), (nominal, rows_nom)):
            e = identify(inj, sim)
            out.append((e.lh_m * 1e6 - lh, 100 * (e.nu_n_per_v / nu - 1), e.sigma_lh_m * 1e6, e.status.value,
                        (e.nu_n_per_v - nu) / e.sigma_nu))
    true_log = np.array([math.log(part.factors[n]) for n in res.names])
    z = (np.log(res.factors) - true_log) / res.sigma_rel
    # the measurement chain's fitted parameters are calibrated parameters too (absolute, µs)
    z_chain = [(getattr(res.params.chain, n) - getattr(part.chain, n)) * 1e6 / sd for n, sd in res.chain_sigma_us.items()]
    z = np.concatenate([z, z_chain])
    lh_err = np.array([r[0] for r in rows_own])
    nu_err = np.array([r[1] for r in rows_own])
    ok = np.array([r[3] == "ok" for r in rows_own])
    row = {"variant": variant, "seed": seed, "describe": part.describe(), "lh_true_um": lh,
           "calibration_seconds": seconds, "rms_before_v": res.rms_before_v, "rms_after_v": res.rms_after_v,
           "adequate": res.adequate, "weak": res.weak, "misfit_z": res.misfit_z,
           "lh_rms_um": float(np.sqrt(np.mean(lh_err ** 2))), "lh_max_um": float(np.max(np.abs(lh_err))),
           "lh_max_ok_um": float(np.max(np.abs(lh_err[ok]))) if ok.any() else 0.0,
           "nu_max_pct": float(np.max(np.abs(nu_err))), "ok": int(ok.sum()), "n": len(rows_own),
           "lh_max_z": float(np.max(np.abs(lh_err / np.array([r[2] for r in rows_own])))),
           "nu_max_z": float(np.max(np.abs([r[4] for r in rows_own]))),
           "statuses": sorted({r[3] for r in rows_own}),
           "lh_max_nominal_um": float(np.max(np.abs([r[0] for r in rows_nom]))),
           "nominal_statuses": sorted({r[3] for r in rows_nom}),
           "param_z": {n: float(v) for n, v in zip(list(res.names) + [f"chain.{c}" for c in res.chain_sigma_us], z)},
           "param_within": int(np.sum(np.abs(z) <= Z_PARAM)), "params": len(z),
           "nu_calibration_sd_pct": float(np.median(100 * res.sigma_nu_n_per_v / np.array(truth[:CALIBRATE_FIRST]))),
           "chain_us": {n: getattr(res.params.chain, n) * 1e6 for n in res.chain_sigma_us},
           "chain_true_us": {n: getattr(part.chain, n) * 1e6 for n in res.chain_sigma_us},
           "chain_sd_us": res.chain_sigma_us}
    row["failures"] = failures(row)
    return row


def failures(row: dict) -> list[str]:
    """What ``row`` misses of its variant's targets."""
    out = []
    if row["variant"] == "mismatch":
        if row["lh_max_ok_um"] > MISMATCH_LH_MAX_UM:
            out.append(f"an ok estimate {row['lh_max_ok_um']:.3f} µm off")
        return out
    if not row["adequate"]:
        out.append(f"calibration refused (residual structure {row['misfit_z']:.0f} sd)")
    if row["lh_rms_um"] > LH_RMS_UM:
        out.append(f"L_h RMS {row['lh_rms_um']:.3f} µm")
    if row["lh_max_um"] > LH_MAX_UM:
        out.append(f"L_h max {row['lh_max_um']:.3f} µm")
    if row["nu_max_pct"] > NU_PCT:
        out.append(f"N_u {row['nu_max_pct']:.3f} %")
    if row["ok"] < row["n"]:
        out.append(f"{row['n'] - row['ok']} not ok ({', '.join(row['statuses'])})")
    return out


def run(injectors: int = 10, seed: int = 11, variants: tuple[str, ...] = VARIANTS) -> dict:
    """Every variant on ``injectors`` seeded injectors (seeds ``seed``, ``seed + 1``, ...)."""
    rows = [run_injector(v, seed + p) for v in variants for p in range(injectors)]
    summary = []
    for v in variants:
        rs = [r for r in rows if r["variant"] == v]
        used = [r for r in rs if r["adequate"]]
        within = sum(r["param_within"] for r in used) / max(1, sum(r["params"] for r in used))
        fails = [f"seed {r['seed']}: " + "; ".join(r["failures"]) for r in rs if r["failures"]]
        if v != "mismatch" and within < Z_SHARE:
            fails.append(f"parameters within {Z_PARAM:g} sigma: {100 * within:.1f} % < {100 * Z_SHARE:.0f} %")
        summary.append({"variant": v, "injectors": len(rs), "param_within_share": within, "adopted": len(used),
                        "lh_rms_um": float(np.sqrt(np.mean([r["lh_rms_um"] ** 2 for r in rs]))),
                        "lh_max_um": max(r["lh_max_um"] for r in rs),
                        "lh_max_ok_um": max(r["lh_max_ok_um"] for r in rs),
                        "nu_max_pct": max(r["nu_max_pct"] for r in rs),
                        "lh_max_z": max(r["lh_max_z"] for r in rs), "nu_max_z": max(r["nu_max_z"] for r in rs),
                        "lh_max_nominal_um": max(r["lh_max_nominal_um"] for r in rs),
                        "ok_share": sum(r["ok"] for r in rs) / max(1, sum(r["n"] for r in rs)),
                        "calibration_seconds_median": float(np.median([r["calibration_seconds"] for r in rs])),
                        "failures": fails, "passed": not fails})
    return {"benchmark": "selfcal", "injectors": injectors, "seed": seed, "summary": summary, "rows": rows,
            "passed": all(s["passed"] for s in summary)}


ROW_COLUMNS = [keyed("variant", "", "<9", "variant"), keyed("seed", "", ">4", "seed"),
               keyed("resid before", "[V]", ">12.3f", "rms_before_v"), keyed("after", "[V]", ">6.3f", "rms_after_v"),
               keyed("Lh nominal max", "[µm]", ">14.3f", "lh_max_nominal_um"),
               keyed("Lh own rms", "[µm]", ">10.3f", "lh_rms_um"), keyed("max", "[µm]", ">6.3f", "lh_max_um"),
               keyed("Nu max", "[%]", ">7.3f", "nu_max_pct"), keyed("(calib sd)", "[%]", ">10.3f", "nu_calibration_sd_pct"),
               keyed("max z Lh", "", ">8.2f", "lh_max_z"), keyed("Nu", "", ">5.2f", "nu_max_z"),
               keyed("ok", "", ">3", "ok"),
               Column("params in 3σ", "", ">12", lambda r: r["param_within"] if r["adequate"] else "refused"), keyed("calib", "[s]", ">6.1f", "calibration_seconds")]
SUMMARY_COLUMNS = [keyed("variant", "", "<9", "variant"), keyed("injectors", "", ">9", "injectors"),
                   keyed("adequate", "", ">8", "adopted"),
                   keyed("Lh rms", "[µm]", ">7.3f", "lh_rms_um"), keyed("max", "[µm]", ">6.3f", "lh_max_um"),
                   keyed("max ok", "[µm]", ">7.3f", "lh_max_ok_um"), keyed("Nu max", "[%]", ">7.3f", "nu_max_pct"),
                   keyed("max z Lh", "", ">8.2f", "lh_max_z"), keyed("Nu", "", ">5.2f", "nu_max_z"),
                   keyed("ok", "[%]", ">6.1f", "ok_share", 100.0),
                   keyed("params in 3σ", "[%]", ">12.1f", "param_within_share", 100.0),
                   keyed("calib median", "[s]", ">12.1f", "calibration_seconds_median")]


def format_report(rep: dict) -> str:
    """Per injector a row, then per variant the summary and its verdict."""
    title = (f"self-calibration - {rep['injectors']} series injectors (±10 %) per variant, {INJECTIONS} injections "
             f"at 28-300 N, calibrated on the first {CALIBRATE_FIRST}, judged on the last {INJECTIONS - CALIBRATE_FIRST}")
    per_row = render(ROW_COLUMNS, rep["rows"], verdict)
    summary = render(SUMMARY_COLUMNS, rep["summary"],
                     lambda s: "PASS" if s["passed"] else "FAIL: " + "; ".join(s["failures"][:3]))
    return "\n".join([title, per_row, "", summary])


# ---- online: the tracker with the daemon's background calibrator ---------------------------------
ONLINE_PACE_S = 0.25          # real seconds between an injector's injections (4 per second)
ONLINE_FROM = 40              # filtered L_h within ONLINE_LH_UM of the truth from this injection on
ONLINE_LH_UM, ONLINE_OK_UM, NO_HARM_SIGMA = 0.15, 0.3, 0.5


def run_online(injectors: int = 10, seed: int = 11, pace_s: float = ONLINE_PACE_S) -> dict:
    """Each series injector (``plain`` variant) through the tracker with self-calibration on and the
    daemon's background calibrator (a low-priority process), its injections ``pace_s`` apart in real
    time; then an exact (nominal) injector with self-calibration on and off. JSON-ready."""
    from estimator.service.calibration_worker import BackgroundCalibrator

    rows: list[dict[str, Any]] = []
    update_s: list[float] = []
    during_s: list[float] = []
    for p in range(injectors + 1):
        exact = p == injectors
        rng = np.random.default_rng(seed + p)
        part = series_part.draw(rng)
        plant = Plant(PlantConfig(window_s=WINDOW_S), None if exact else part.params)
        lh, seq = injector_sequence(rng)
        injections = []
        for k, (nu, f) in enumerate(seq):
            m = plant.measure(nu, lh * 1e-6, f, rng)
            injections.append(Injection(m.current_a, m.voltage_v, m.dt_s, f, 0, k % 256, float("nan"), k * 5.0))
        calibrator = BackgroundCalibrator()
        tracker = Tracker(self_calibration=SelfCalConfig(), calibrator=calibrator)
        reference = Tracker() if exact else None
        tracker.warm_up()     # as the daemon does before it reports ready
        try:
            out: list[dict[str, Any]] = []
            t0 = time.perf_counter()
            for k, inj in enumerate(injections):
                while time.perf_counter() < t0 + k * pace_s:
                    time.sleep(min(0.01, max(0.0, t0 + k * pace_s - time.perf_counter())))
                busy = calibrator.running > 0
                ts = time.perf_counter()
                r = tracker.update(inj)
                dt = time.perf_counter() - ts
                (during_s if busy else update_s).append(dt)
                ref = reference.update(inj) if reference is not None else None
                out.append({"k": k, "lh_err_um": r.lh_m * 1e6 - lh, "sigma_lh_um": r.sigma_lh_m * 1e6,
                            "nu_z": (r.nu_n_per_v - seq[k][0]) / r.sigma_nu,
                            "nu_err_pct": 100 * (r.nu_n_per_v / seq[k][0] - 1), "status": r.status.value,
                            "calibration": tracker.calibration.get(0, CalibrationStatus()).state,
                            "ref_lh_um": ref.lh_m * 1e6 if ref else None,
                            "ref_sigma_lh_um": ref.sigma_lh_m * 1e6 if ref else None})
        finally:
            calibrator.close()
        states = [o["calibration"] for o in out]
        adopted_at = states.index("adopted") if "adopted" in states else None
        late = [o for o in out[ONLINE_FROM:]]
        ok_far = [o["k"] for o in out if o["status"] == "ok" and abs(o["lh_err_um"]) > ONLINE_OK_UM]
        row: dict[str, Any] = {"seed": seed + p, "exact": exact, "lh_true_um": lh, "adopted_at": adopted_at,
               "calibration": tracker.calibration.get(0, CalibrationStatus()).to_dict(),
               "max_lh_err_from_um": float(max(abs(o["lh_err_um"]) for o in late)),
               "max_nu_err_from_pct": float(max(abs(o["nu_err_pct"]) for o in late)),
               "max_lh_z_from": float(max(abs(o["lh_err_um"]) / o["sigma_lh_um"] for o in late)),
               "max_nu_z_from": float(max(abs(o["nu_z"]) for o in late)),
               "ok_far": ok_far, "statuses_from": sorted({o["status"] for o in late})}
        fails = []
        if exact:
            shift = max(abs(o["lh_err_um"] + lh - o["ref_lh_um"]) / o["ref_sigma_lh_um"] for o in out
                        if o["ref_lh_um"] is not None and math.isfinite(o["ref_lh_um"]))
            row["max_shift_sigma"] = float(shift)
            if adopted_at is not None and shift > NO_HARM_SIGMA:
                fails.append(f"adopted a model on an exact injector, estimates moved {shift:.2f} sigma")
        else:
            if row["max_lh_err_from_um"] > ONLINE_LH_UM:
                fails.append(f"L_h {row['max_lh_err_from_um']:.3f} µm off after injection {ONLINE_FROM}")
        if ok_far:
            fails.append(f"ok while more than {ONLINE_OK_UM} µm off at injection(s) {ok_far[:5]}")
        row["failures"] = fails
        rows.append(row)

    def ms(x: list[float], q: float) -> float:
        return float(np.percentile(x, q) * 1e3) if x else float("nan")

    speed = {"updates": len(update_s), "median_ms": ms(update_s, 50), "p99_ms": ms(update_s, 99),
             "updates_during_calibration": len(during_s), "median_during_ms": ms(during_s, 50),
             "p99_during_ms": ms(during_s, 99)}
    return {"benchmark": "selfcal-online", "injectors": injectors, "seed": seed, "pace_s": pace_s,
            "rows": rows, "speed": speed, "passed": all(not r["failures"] for r in rows)}


ONLINE_COLUMNS = [keyed("seed", "", ">4", "seed"), Column("injector", "", "<8", lambda r: "exact" if r["exact"] else "series"),
                  Column("adopted at", "[inj]", ">10", lambda r: "-" if r["adopted_at"] is None else r["adopted_at"]),
                  Column("state", "", "<9", lambda r: r["calibration"]["state"]),
                  keyed(f"max|dLh| from {ONLINE_FROM}", "[µm]", ">15.3f", "max_lh_err_from_um"),
                  keyed("max|dNu|", "[%]", ">8.3f", "max_nu_err_from_pct"),
                  keyed("max z Lh", "", ">8.2f", "max_lh_z_from"), keyed("Nu", "", ">5.2f", "max_nu_z_from")]


def format_online(rep: dict) -> str:
    """Per injector a row, then the update times while calibrations ran."""
    s = rep["speed"]
    title = (f"self-calibration online - {rep['injectors']} series injectors and one exact, an injection every "
             f"{rep['pace_s']:g} s, calibrations in the background process; targets: filtered L_h within "
             f"{ONLINE_LH_UM} µm from injection {ONLINE_FROM}, never ok while > {ONLINE_OK_UM} µm off, "
             f"exact injector unharmed ({NO_HARM_SIGMA} sigma)")
    table = render(ONLINE_COLUMNS, rep["rows"], verdict)
    speed = (f"warm update while a calibration ran: median {s['median_during_ms']:.3f} ms, p99 {s['p99_during_ms']:.3f} ms "
             f"({s['updates_during_calibration']} updates); otherwise median {s['median_ms']:.3f} ms, "
             f"p99 {s['p99_ms']:.3f} ms ({s['updates']} updates, cold starts included)")
    return "\n".join([title, table, speed])
