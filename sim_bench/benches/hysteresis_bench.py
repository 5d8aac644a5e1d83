"""Parts whose hysteresis R(N_u)·I cannot explain, learned online: ``python -m sim_bench selfcal --hysteresis``.

Each part is a seeded series part (±10 %) on the mismatch plant: a Prandtl–Ishlinskii or a Bouc–Wen
hysteresis of the charge (the second is a form no sum of the estimator's plays is built from) at half,
once and twice its size, and a 0.2 Ω series resistance (:func:`refusal_bench.hysteresis_variant`).
Each runs through the tracker with learning on (``hysteresis = true``, the default), as the
daemon does, for ``injections`` injections
with the rail pressure wandering, and is scored from injection 40 on (the issue of learning: the
first window, its adoption, the refinement): the largest error of the filtered L_h, the valve's
predicted opening instant against the plant's, and any ``ok`` estimate more than 0.3 µm off.
Targets: every Prandtl–Ishlinskii part learned with a hysteresis element, L_h within 0.15 µm and the
opening within 1 µs from injection 40 for every part learned, no ``ok`` while more than 0.3 µm off
for any part, and no part adopted without an element.

``online`` (``selfcal --hysteresis --online``): the same parts with the daemon's background calibrator
(a process at idle priority) and an injection every ``ONLINE_PACE_S`` real seconds, up to
``ONLINE_INJECTIONS``: the element's calibrations take seconds to minutes there, so each part is
scored from ``ONLINE_SETTLE`` injections after its element's adoption (when it has one), with the
same targets, and the worker's update times while a calibration runs are reported.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from estimator.ident.learning.selfcal import SelfCalConfig
from estimator.ident.status import Status
from estimator.ident.tracking.tracker import Tracker
from estimator.service.calibration_worker import BackgroundCalibrator
from sim_bench.benches.refusal_bench import HYSTERESIS_PARTS, SEED_HYSTERESIS, hysteresis_variant, part_life

FROM = 40               # injections before the scored ones
ONLINE_PACE_S, ONLINE_INJECTIONS, ONLINE_SETTLE = 0.25, 400, 30
LH_LIMIT_UM, OPENING_LIMIT_US, OK_LIMIT_UM = 0.15, 1.0, 0.3


def part(i: int, injections: int = 70, online: bool = False) -> dict[str, Any]:
    """The ``i``-th hysteresis part through the learning tracker (``online``: with the background
    calibrator, paced in real time); its row."""
    gain, shape = hysteresis_variant(i)
    life = part_life(SEED_HYSTERESIS + i, hysteresis=(gain, shape))
    calibrator = BackgroundCalibrator() if online else None
    tracker = Tracker(self_calibration=SelfCalConfig(), calibrator=calibrator)
    trace, busy_ms = [], []
    t0 = time.perf_counter()
    try:
        for inj, m, truth in life.injections(injections):
            while online and time.perf_counter() < t0 + truth["k"] * ONLINE_PACE_S:
                time.sleep(0.005)
            busy = calibrator is not None and calibrator.running > 0
            ts = time.perf_counter()
            r = tracker.update(inj)
            if busy:
                busy_ms.append((time.perf_counter() - ts) * 1e3)
            own = tracker.own_parameters().get(0)
            opening = abs(r.t_open_s - m.t_open_s) * 1e6 if np.isfinite(r.t_open_s) and np.isfinite(m.t_open_s) else None
            trace.append((truth["k"], r.lh_m * 1e6 - truth["lh_true_um"], r.status == Status.OK, opening,
                          own is not None and own.hysteresis.present))
    finally:
        if calibrator is not None:
            calibrator.close()
    adopted = next((k for k, *_rest, element in trace if element), None)
    start = FROM if not online else (adopted + ONLINE_SETTLE if adopted is not None else len(trace))
    st = tracker.calibration.get(0)
    return {"part": i, "seed": SEED_HYSTERESIS + i, "gain": gain, "shape": shape,
            "learned": tracker.own_parameters().get(0) is not None, "element": bool(trace and trace[-1][4]),
            "element_adopted_at": adopted, "scored_from": start,
            "state": st.state if st else "", "message": st.message if st else "",
            "max_lh_from_um": max((abs(e) for k, e, *_ in trace if k >= start), default=float("nan")),
            "max_opening_from_us": max((o for k, _e, _ok, o, _el in trace if k >= start and o is not None),
                                       default=float("nan")),
            "ok_while_off": [k for k, e, ok, *_ in trace if ok and abs(e) > OK_LIMIT_UM],
            "p99_update_during_calibration_ms": float(np.percentile(busy_ms, 99)) if busy_ms else None,
            "seconds": time.perf_counter() - t0}


def run(parts: int = HYSTERESIS_PARTS, injections: int = 70, online: bool = False) -> dict[str, Any]:
    """Every part (``online``: through the background calibrator, paced); a JSON-ready report with
    the verdict."""
    injections = ONLINE_INJECTIONS if online else injections
    rows = [part(i, injections, online) for i in range(parts)]
    learned = [r for r in rows if r["element"]]
    pi = [r for r in rows if r["shape"] == "prandtl-ishlinskii"]
    s = {"parts": len(rows), "learned": len(learned), "pi_parts": len(pi), "pi_learned": sum(r["element"] for r in pi),
         "without_element": sum(r["learned"] and not r["element"] for r in rows),
         "max_lh_from_um": max((r["max_lh_from_um"] for r in learned), default=float("nan")),
         "max_opening_from_us": max((r["max_opening_from_us"] for r in learned), default=float("nan")),
         "ok_while_off": sum(len(r["ok_while_off"]) for r in rows)}
    fails = []
    since = f"{ONLINE_SETTLE} injections after the adoption" if online else f"injection {FROM}"
    if s["pi_learned"] < s["pi_parts"]:
        fails.append(f"{s['pi_parts'] - s['pi_learned']} Prandtl–Ishlinskii part(s) not learned")
    if s["without_element"]:
        fails.append(f"{s['without_element']} part(s) adopted without a hysteresis element")
    if learned and not s["max_lh_from_um"] <= LH_LIMIT_UM:
        fails.append(f"filtered L_h {s['max_lh_from_um']:.3f} µm off from {since} (> {LH_LIMIT_UM})")
    if learned and not s["max_opening_from_us"] <= OPENING_LIMIT_US:
        fails.append(f"opening {s['max_opening_from_us']:.2f} µs off from {since} (> {OPENING_LIMIT_US})")
    if s["ok_while_off"]:
        fails.append(f"{s['ok_while_off']} ok estimate(s) more than {OK_LIMIT_UM} µm off")
    s["failures"], s["passed"] = fails, not fails
    name = "selfcal-hysteresis-online" if online else "selfcal-hysteresis"
    return {"benchmark": name, "injections": injections, "online": online, "summary": s, "rows": rows,
            "passed": not fails}


def format_report(rep: dict[str, Any]) -> str:
    """A line per part and the verdict."""
    s = rep["summary"]
    scored = (f"an injection every {ONLINE_PACE_S:g} s, the background calibrator, scored from {ONLINE_SETTLE} after "
              "the element's adoption" if rep.get("online") else f"scored from {FROM}")
    lines = [f"hysteresis parts learned online ({rep['injections']} injections each, {scored}): "
             f"{s['learned']} of {s['parts']} with an element (Prandtl–Ishlinskii {s['pi_learned']} of {s['pi_parts']})",
             f"{'part':>4} {'shape':<19} {'gain':>4} {'element':>7} {'at':>4} {'state':<11} {'L_h max µm':>10} "
             f"{'opening max µs':>14} {'ok >0.3 µm off':>14} {'p99 busy ms':>11}"]
    for r in rep["rows"]:
        at = "-" if r.get("element_adopted_at") is None else r["element_adopted_at"]
        busy = r.get("p99_update_during_calibration_ms")
        lines.append(f"{r['part']:>4} {r['shape']:<19} {r['gain']:>4.1f} {r['element']!s:>7} {at:>4} {r['state']:<11} "
                     f"{r['max_lh_from_um']:>10.3f} {r['max_opening_from_us']:>14.2f} {len(r['ok_while_off']):>14} "
                     f"{'-' if busy is None else format(busy, '.2f'):>11}")
    lines.append("  " + ("PASS" if s["passed"] else "FAIL: " + "; ".join(s["failures"])))
    return "\n".join(lines)
