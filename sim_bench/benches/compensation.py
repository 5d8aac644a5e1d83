"""Drive compensation bench: a lot of series injectors driven open loop (the amplifier's standard drive)
and closed loop (each injection driven with the injector's last published drive correction), with
learning on and the estimator's default configuration (``python -m sim_bench compensation``).

The lot (:mod:`sim_bench.hardware.series_life`): parts within the lot's structural spread, idle strokes
1-9 µm with up to 0.5 µm of wear, a warm-up from 15.6 to ≈ 20.6 N/V, the rail pressure wandering
between idle and full load (28-300 N), the lot's amplifier chain, and one part swapped at injection
40. It runs on each amplifier profile (:mod:`sim_bench.hardware.amplifiers`): the estimator is not told which,
it learns each injector's standard drive from the measured current. Each run sees the same parts,
truths and noise in three loops: ``open`` (the standard drive), ``closed`` (each correction computed
for the next injection's preload force, as an ECU that knows its rail pressure asks for it) and
``closed_bus`` (the correction published after each injection, applied at the next injection's
preload force as an amplifier on the bus does, :meth:`~estimator.drive.correction.Correction.at`).
The truth is the plant's: its plateau stroke and its opening instant after the standard drive's start
of charging (the correction's offset plus the plant's own).

Reported per injector and across each lot: the spread (max - min) and SD of the true opening instant
and plateau stroke at each injection, before learning (the first injections) and after (the last
``SETTLED`` of the life), how many injections after the model's adoption the stroke takes to stay on
target (a correction stopped short by its trust region is not on target yet), overshoot (a correction
that claims the target and misses it by more than 2σ), the share of injections at a drive limit and of corrections stopped by their trust
region, corrections marked valid after an estimate that was not ``ok``, parts that went
``model_mismatch`` under their own correction but not under the standard drive; and, over all the lots' parts, whether the predicted σ covers the
achieved error (a learned model's error is a bias, one draw per part: eight parts alone say little
about it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from estimator.drive.correction import Correction, DriveCompensator
from estimator.ident.measurement import Injection
from estimator.ident.status import Learning, Status
from estimator.pipeline.config import EstimatorConfig
from sim_bench.benches.targets import TARGETS, limit
from sim_bench.hardware.amplifiers import PROFILES, amplifier
from sim_bench.hardware.plant import Measurement
from sim_bench.hardware.series_life import Life, LotSpec, draw_lot

if TYPE_CHECKING:
    from estimator.pipeline.processor import Processor, Published

INJECTORS = 8              # a lot: an engine's injectors
LOTS = 1                   # lots per amplifier profile (seeds seed, seed + 1, ...): whether σ covers a part's bias is
                           # judged over all the profiles' and lots' parts
SWAP_AT, SWAPPED = 40, (1,)   # a part swapped early in the life: learned again before the settled injections
NU_RISE = 5.0              # N/V: the warm-up from 15.6 to ≈ 20.6 (± a part's 0.4)
LH_UM = (1.0, 9.0)         # µm: the parts' idle strokes
WEAR_UM = 0.5              # µm: up to this much wear over the life
INJECTIONS = 150           # per injector
SETTLED = 60               # the last injections of the life, where learning is over
SETTLE_UM = 0.15           # |stroke - target| within this (half the lot spread target), or within 2σ of the
                           # predicted stroke, counts as on target
HYSTERESIS_LOT = ((3, 1.0, "prandtl-ishlinskii"), (6, 0.5, "bouc-wen"))   # with ``hysteresis``: parts whose
                           # hysteresis R(N_u) I cannot explain (the learned element's own form, and one it is not)
Z_RMS = (limit("compensation", "z_rms_min"), limit("compensation", "z_rms_max"))   # RMS(error/σ) of the predictions


@dataclass
class Run:
    """One loop's per-injection record, arrays of shape (injectors, injections)."""

    stroke_um: np.ndarray
    opening_us: np.ndarray
    predicted_stroke_um: np.ndarray
    sigma_stroke_um: np.ndarray
    predicted_opening_us: np.ndarray
    sigma_opening_us: np.ndarray
    applied: np.ndarray           # a valid correction drove this injection
    adopted_at: list[int | None]  # injection at which each injector's own model was adopted
    at_limit: np.ndarray | None = None   # the correction that drove this injection was at a limit
    valid_not_ok: int = 0         # corrections published valid (not held) after an estimate that was not ok
    mismatch: np.ndarray | None = None       # the estimate was model_mismatch, after the model's adoption
    trust_limited: np.ndarray | None = None  # the correction that drove this injection stopped at its trust region


def lot_spec(amp: str = "standard", hysteresis: bool = False) -> LotSpec:
    """The compensation bench's lot on the amplifier profile ``amp`` (``hysteresis``: with the parts
    of :data:`HYSTERESIS_LOT`)."""
    return LotSpec(swap_at=SWAP_AT, swapped=SWAPPED, nu_rise=NU_RISE, lh_um=LH_UM, wear_um=WEAR_UM,
                   amplifier=amplifier(amp), hysteresis=HYSTERESIS_LOT if hysteresis else ())


def run_loop(closed: bool, seed: int, injectors: int = INJECTORS, injections: int = INJECTIONS,
             ecu: bool = True, amp: str = "standard", hysteresis: bool = False) -> Run:
    """The lot through ``injections`` injections each, with learning on; ``closed``: drive each
    injection with the injector's last correction, computed for that injection's preload force
    (``ecu``: as an ECU that knows its next rail pressure asks for it) or carried there by the
    correction's own sensitivity (as an amplifier on the bus applies it)."""
    from estimator.pipeline import build_pipeline

    lives = draw_lot(injectors, seed, lot_spec(amp, hysteresis))
    # the daemon's deferred correction, its deferred work never given idle time (as on a worker that is
    # never idle): each injector's table and derivative refresh run just before its next injection
    _, _, processor, _ = build_pipeline(EstimatorConfig(), deferred=True)
    compensator = processor.compensator
    assert compensator is not None    # on by default
    shape = (injectors, injections)
    nan = np.full(shape, np.nan)
    out = Run(nan.copy(), nan.copy(), nan.copy(), nan.copy(), nan.copy(), nan.copy(), np.zeros(shape, bool),
              [None] * injectors, np.zeros(shape, bool), mismatch=np.zeros(shape, bool),
              trust_limited=np.zeros(shape, bool))
    rngs = [np.random.default_rng(life.seed) for life in lives]
    walks = [life.preload_walk(injections + 1, np.random.default_rng(life.seed + 1)) for life in lives]
    last: dict[int, Correction] = {}
    swapped_model: dict[int, object] = {}    # the model in use when a position's part was swapped
    for k in range(injections):
        for i, life in enumerate(lives):
            corr = last.get(i, Correction())
            use = closed and corr.valid
            m, pub, offset = drive_once(processor, life, i, k, injections, rngs[i], walks[i], corr if use else None, ecu)
            out.stroke_um[i, k] = m.stroke_m * 1e6
            out.opening_us[i, k] = offset + m.t_open_s * 1e6
            out.applied[i, k] = use
            assert out.at_limit is not None
            out.at_limit[i, k] = use and corr.at_limit
            assert out.trust_limited is not None and out.mismatch is not None
            out.trust_limited[i, k] = use and corr.trust_limited
            if use:   # σ where the amplifier took the correction, as the table's rows state it there
                out.predicted_stroke_um[i, k] = corr.stroke_um
                out.predicted_opening_us[i, k] = corr.opening_us
                out.sigma_stroke_um[i, k], out.sigma_opening_us[i, k] = corr.sigma_at(walks[i][k])
            last[i] = pub.correction or Correction()
            if last[i].state == "valid" and pub.result.status != Status.OK:
                out.valid_not_ok += 1
            st = processor.tracker.calibration.get(i)
            model = processor.tracker.model_simulator(i, m.dt_s)
            if life.swap_at is not None and k == life.swap_at:   # a new part: its settling counts from its own model
                out.adopted_at[i], swapped_model[i] = None, model
            if out.adopted_at[i] is None and st is not None and st.state in (Learning.ADOPTED, Learning.MONITORING) \
                    and (i not in swapped_model or model is not swapped_model[i]):
                out.adopted_at[i] = k
            if pub.result.status == Status.OK and out.adopted_at[i] is None and st is not None \
                    and st.state == Learning.IDLE and k > 5:
                out.adopted_at[i] = k     # the configured model explains it: nothing to learn
            # estimated with the adopted model (the injection that adopts one was estimated with the last)
            adopted = out.adopted_at[i]
            out.mismatch[i, k] = adopted is not None and k > adopted and pub.result.status == Status.MODEL_MISMATCH
    return out


def drive_once(processor: Processor, life: Life, injector: int, k: int, injections: int,
               rng: np.random.Generator, walk: np.ndarray, corr: Correction | None,
               ecu: bool = True) -> tuple[Measurement, Published, float]:
    """Injection ``k`` of ``injections`` of ``life`` (at the preload force ``walk[k]``, N) driven by
    ``corr`` taken at that force as an amplifier applies it (None: the standard drive), estimated as
    ``injector`` with its correction for ``walk[k + 1]`` (``ecu``: the next preload force is known,
    else this one's). Returns the measurement, what the processor published and the offset applied
    (µs; its opening instant counts from the standard drive's start of charging)."""
    applied = {"offset": 0.0}

    def scale_for(f: float) -> float:
        assert corr is not None
        scale, applied["offset"] = corr.at(f)
        return scale
    m, _truth = life.measure(k, injections, rng, scale_for if corr is not None else None, walk[k])
    inj = Injection(m.current_a, m.voltage_v, m.dt_s, m.f_open_n, injector, k % 256, float("nan"), float(k))
    return m, processor.estimate(inj, walk[k + 1] if ecu else None), applied["offset"]


def spread(values: np.ndarray) -> np.ndarray:
    """Max - min over the lot at each injection (NaN where an injector has no value)."""
    return np.nanmax(values, axis=0) - np.nanmin(values, axis=0)


def summarise(run: Run, target_stroke: float) -> dict:
    """The lot's figures of one run."""
    n = run.stroke_um.shape[1]
    early, late = slice(0, 10), slice(n - SETTLED, n)
    out = {
        "stroke_spread_um": {"first10_median": float(np.median(spread(run.stroke_um)[early])),
                             "settled_median": float(np.median(spread(run.stroke_um)[late])),
                             "settled_p95": float(np.percentile(spread(run.stroke_um)[late], 95))},
        "opening_spread_us": {"first10_median": float(np.median(spread(run.opening_us)[early])),
                              "settled_median": float(np.median(spread(run.opening_us)[late])),
                              "settled_p95": float(np.percentile(spread(run.opening_us)[late], 95))},
        "stroke_sd_um_settled": float(np.median(np.std(run.stroke_um[:, late], axis=0))),
        "opening_sd_us_settled": float(np.median(np.std(run.opening_us[:, late], axis=0))),
        "at_limit_settled": float(np.mean(run.at_limit[:, late])) if run.at_limit is not None else 0.0,
        "valid_not_ok": run.valid_not_ok,
        "trust_limited_settled": float(np.mean(run.trust_limited[:, late])) if run.trust_limited is not None else 0.0,
        "trust_limited_share": float(np.mean(run.trust_limited[run.applied])) if run.trust_limited is not None
        and run.applied.any() else 0.0,
        "mismatch_after_adoption": [int(x) for x in run.mismatch.sum(axis=1)] if run.mismatch is not None else [],
    }
    per = []
    z_all: dict[str, list[np.ndarray]] = {"stroke": [], "opening": []}
    for i in range(run.stroke_um.shape[0]):
        err = run.stroke_um[i] - target_stroke
        adopted = run.adopted_at[i]
        settle = None
        overshoot = 0
        if adopted is not None:
            # a correction its trust region stopped short says so and predicts what it gives (judged by
            # RMS(error/σ)): not yet on target, and no overshoot; one that claims the target and misses
            # it by more than 2σ is
            aimed = ~run.trust_limited[i] if run.trust_limited is not None else np.ones(n, bool)
            ok = (np.abs(err) <= np.maximum(SETTLE_UM, 2 * np.nan_to_num(run.sigma_stroke_um[i]))) & aimed
            for k in range(adopted, n):
                if ok[k:].mean() >= 0.95 and ok[k]:
                    settle = k - adopted
                    break
            if settle is not None:
                s = run.sigma_stroke_um[i, adopted + settle:]
                e = err[adopted + settle:]
                overshoot = int(np.sum((np.abs(e) > 2 * s + SETTLE_UM) & aimed[adopted + settle:]))
        z_s = (run.stroke_um[i] - run.predicted_stroke_um[i]) / run.sigma_stroke_um[i]
        z_s = z_s[late][np.isfinite(z_s[late])]
        z_o = (run.opening_us[i] - run.predicted_opening_us[i]) / run.sigma_opening_us[i]
        z_o = z_o[late][np.isfinite(z_o[late])]
        z_all["stroke"].append(z_s)
        z_all["opening"].append(z_o)
        per.append({"injector": i, "adopted_at": adopted, "settle_injections": settle, "overshoots": overshoot,
                    "stroke_err_um_settled_max": float(np.max(np.abs(err[late]))),
                    "z_rms_stroke": rms(z_s), "z_rms_opening": rms(z_o)})
    out["injectors"] = per
    for what, zs in z_all.items():
        z = np.concatenate(zs)
        out[f"z_rms_{what}"] = rms(z)
        out[f"z_sq_sum_{what}"] = float(np.sum(z ** 2))   # pooled over lots by run()
        out[f"z_count_{what}"] = int(z.size)
    return out


def rms(z: np.ndarray) -> float | None:
    """Root mean square of ``z``, None when empty."""
    return float(np.sqrt(np.mean(z ** 2))) if z.size else None


def run(seed: int = 1, injectors: int = INJECTORS, injections: int = INJECTIONS, lots: int = LOTS,
        amplifiers: tuple[str, ...] = PROFILES, hysteresis: bool = False) -> dict:
    """Open and closed loops on ``lots`` lots per amplifier profile (seeds ``seed``, ``seed + 1``, ...
    across all of them; ``hysteresis``: with the parts of :data:`HYSTERESIS_LOT`); the report."""
    from estimator.ident.simulators import SimulatorPool

    target = DriveCompensator().target_at(SimulatorPool().get(0.5e-6))
    rep: dict = {"benchmark": "compensation", "seed": seed, "lots": [], "injectors": injectors,
                 "injections": injections, "target_stroke_um": target[0], "target_opening_us": target[1],
                 "amplifiers": list(amplifiers), "targets": [t._asdict() for t in TARGETS["compensation"]],
                 "hysteresis": [list(h) for h in HYSTERESIS_LOT if h[0] < injectors] if hysteresis else []}
    n = 0
    for amp in amplifiers:
        for _ in range(lots):
            lot_seed = seed + n
            runs = {"open": run_loop(False, lot_seed, injectors, injections, amp=amp, hysteresis=hysteresis),
                    "closed": run_loop(True, lot_seed, injectors, injections, amp=amp, hysteresis=hysteresis),
                    "closed_bus": run_loop(True, lot_seed, injectors, injections, ecu=False, amp=amp,
                                           hysteresis=hysteresis)}
            lot = {"seed": lot_seed, "amplifier": amp, **{name: summarise(r, target[0]) for name, r in runs.items()}}
            lot["own_mismatch"] = own_mismatch(runs)
            rep["lots"].append(lot)
            if n == 0:
                rep["series"] = {name: {"stroke_um": runs[name].stroke_um.round(4).tolist(),
                                        "opening_us": runs[name].opening_us.round(3).tolist()}
                                 for name in ("open", "closed")}
            n += 1
    rep.update(pooled_z(rep["lots"]))
    rep["failures"] = failures(rep)
    return rep


def own_mismatch(runs: dict[str, Run]) -> dict[str, list[int]]:
    """Per closed loop, the injectors whose estimates went ``model_mismatch`` after their model's adoption
    while the same part, truths and noise driven with the standard drive did not: their own correction
    drove them where their model does not hold."""
    open_ = runs["open"].mismatch
    assert open_ is not None
    out = {}
    for name in ("closed", "closed_bus"):
        m = runs[name].mismatch
        assert m is not None
        out[name] = [i for i in range(m.shape[0]) if m[i].any() and not open_[i].any()]
    return out


def pooled_z(lots: list[dict]) -> dict[str, float | None]:
    """RMS(error/σ) of each closed loop's predicted stroke and opening over all the lots' parts
    (``z_rms_*`` the ECU's loop, ``bus_z_rms_*`` the bus's where the lots ran it). A learned model's
    error is a bias, the same for every injection of the part: one draw per part, so whether σ covers
    it is judged over many parts, not part by part."""
    out: dict[str, float | None] = {}
    for loop, prefix in (("closed", ""), ("closed_bus", "bus_")):
        ran = [lot[loop] for lot in lots if loop in lot]
        if not ran:
            continue
        for what in ("stroke", "opening"):
            count = sum(c[f"z_count_{what}"] for c in ran)
            total = sum(c[f"z_sq_sum_{what}"] for c in ran)
            out[f"{prefix}z_rms_{what}"] = math.sqrt(total / count) if count else None
    return out


def failures(rep: dict) -> list[str]:
    """What makes the bench exit 1: each closed loop (the ECU's and the bus's) on each lot."""
    out = []
    for lot in rep["lots"]:
        for loop in ("closed", "closed_bus"):
            if loop not in lot:
                continue
            c, where = lot[loop], f"lot {lot['seed']} ({lot.get('amplifier', 'standard')}, {loop})"
            for what, unit, digits in (("opening", "us", 2), ("stroke", "um", 3)):
                spread_ = c[f"{what}_spread_{unit}"]
                for stat, key in (("settled_median", f"{what}_spread_{unit}"), ("settled_p95", f"{what}_spread_p95_{unit}")):
                    if spread_[stat] > limit("compensation", key):
                        out.append(f"{where}: {what} spread {stat} {spread_[stat]:.{digits}f}")
            if c.get("at_limit_settled", 0.0) > limit("compensation", "at_limit_share"):
                out.append(f"{where}: {100 * c['at_limit_settled']:.1f} % of the settled injections at a drive limit")
            if c.get("valid_not_ok", 0):
                out.append(f"{where}: {c['valid_not_ok']} corrections valid after an estimate that was not ok")
            for i in lot.get("own_mismatch", {}).get(loop, []):
                out.append(f"{where}: injector {i} went model_mismatch under its own correction "
                           "(not with the standard drive)")
            if loop != "closed":
                continue
            for p in c["injectors"]:
                if p["settle_injections"] is None or p["settle_injections"] > limit("compensation", "settle_injections"):
                    out.append(f"{where}: injector {p['injector']} settled after {p['settle_injections']} injections")
                if p["overshoots"]:
                    out.append(f"{where}: injector {p['injector']}: {p['overshoots']} overshoots beyond 2σ")
    lo, hi = Z_RMS
    for prefix, loop in (("", ""), ("bus_", "the bus loop's ")):
        for what in ("stroke", "opening"):
            key = f"{prefix}z_rms_{what}"
            if prefix and key not in rep:    # the lots did not run the bus's loop
                continue
            z = rep[key]
            if z is None or not (lo <= z <= hi):
                out.append(f"RMS(error/σ) of {loop}predicted {what} over the lots' parts {z}")
    return out


def format_report(rep: dict) -> str:
    """The table."""
    lines = [f"drive compensation, {len(rep['lots'])} lot(s) of {rep['injectors']} series injectors, "
             f"{rep['injections']} injections each, learning on; target stroke {rep['target_stroke_um']:.3f} µm, "
             f"opening {rep['target_opening_us']:.2f} µs" + "".join(
                 f"; injector {i}: a {shape} hysteresis at {gain:g}x" for i, gain, shape in rep.get("hysteresis", [])),
             f"{'':<34} {'stroke spread µm':>30} {'opening spread µs':>30}",
             f"{'lot  amplifier          loop':<34} {'first 10':>10} {'settled':>9} {'p95':>9} {'first 10':>10} "
             f"{'settled':>9} {'p95':>9} {'at limit':>9} {'trust':>7} {'z s / o':>11}"]
    for lot in rep["lots"]:
        for name in ("open", "closed", "closed_bus"):
            s, o = lot[name]["stroke_spread_um"], lot[name]["opening_spread_us"]
            lines.append(f"{lot['seed']:<4} {lot.get('amplifier', 'standard'):<18} {name:<10} "
                         f"{s['first10_median']:>10.3f} {s['settled_median']:>9.3f} {s['settled_p95']:>9.3f} "
                         f"{o['first10_median']:>10.2f} {o['settled_median']:>9.2f} {o['settled_p95']:>9.2f} "
                         f"{100 * lot[name].get('at_limit_settled', 0.0):>8.1f}% "
                         f"{100 * lot[name].get('trust_limited_share', 0.0):>6.1f}% "
                         f"{_z_pair(lot[name]):>11}")
    lines.append("closed: each correction computed for the next injection's preload force (an ECU); closed_bus: "
                 "the correction published after each injection, applied at the next one's preload force (an "
                 "amplifier on the bus); at limit: settled injections driven by a correction at a drive limit; trust: "
                 "corrected injections whose correction stopped where its model had been checked; z s / o: the lot's "
                 "RMS(error/σ) of the predicted stroke and opening (eight draws of a part's bias: judged over "
                 "all the lots' parts, below)")
    for lot in rep["lots"]:
        own = lot.get("own_mismatch", {})
        lines.append(f"lot {lot['seed']}: injectors model_mismatch under their own correction (not with the "
                     f"standard drive): closed {own.get('closed', [])}, closed_bus {own.get('closed_bus', [])}")
    lines.append("closed loop per injector: adopted at / settled after / overshoots / max |stroke error| settled / "
                 "RMS(error/σ) of the predicted stroke, opening")

    for lot in rep["lots"]:
        for p in lot["closed"]["injectors"]:
            lines.append(f"  lot {lot['seed']} injector {p['injector']}: {p['adopted_at']} / {p['settle_injections']} / "
                         f"{p['overshoots']} / {p['stroke_err_um_settled_max']:.3f} µm / {_z_text(p['z_rms_stroke'])}, "
                         f"{_z_text(p['z_rms_opening'])}")
    bus = (f"; bus loop {_z_text(rep['bus_z_rms_stroke'])}, {_z_text(rep['bus_z_rms_opening'])}"
           if "bus_z_rms_stroke" in rep else "")
    lines.append(f"over the lots' parts: RMS(error/σ) of the predicted stroke {_z_text(rep['z_rms_stroke'])}, "
                 f"opening {_z_text(rep['z_rms_opening'])}{bus} (target {Z_RMS[0]}-{Z_RMS[1]})")
    lines.append("PASS" if not rep["failures"] else "FAIL: " + "; ".join(rep["failures"]))
    return "\n".join(lines)


def _z_pair(loop: dict) -> str:
    """A closed loop's RMS(error/σ) of stroke and opening over the lot, as the table shows it ("" for
    the open loop)."""
    zs, zo = loop.get("z_rms_stroke"), loop.get("z_rms_opening")
    if zs is None and zo is None:
        return ""
    return " / ".join(_z_text(z) for z in (zs, zo))


def _z_text(z: float | None) -> str:
    """An RMS(error/σ) as the report prints it ("-": none)."""
    return "-" if z is None else f"{z:.2f}"


def figure(rep: dict, path) -> None:
    """True stroke and opening instant of every injector, open and closed loop, against the target."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), sharex=True)
    for col, name in enumerate(("open", "closed")):
        s = np.array(rep["series"][name]["stroke_um"])
        o = np.array(rep["series"][name]["opening_us"])
        for i in range(s.shape[0]):
            axes[0, col].plot(s[i], lw=0.8)
            axes[1, col].plot(o[i], lw=0.8)
        axes[0, col].axhline(rep["target_stroke_um"], color="k", ls="--", lw=0.8)
        axes[1, col].axhline(rep["target_opening_us"], color="k", ls="--", lw=0.8)
        axes[0, col].set_title(f"{name} loop")
        axes[1, col].set_xlabel("injection")
    axes[0, 0].set_ylabel("true plateau stroke (µm)")
    axes[1, 0].set_ylabel("true opening instant (µs)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

