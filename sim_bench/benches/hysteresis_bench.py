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
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from estimator.ident.learning.selfcal import SelfCalConfig
from estimator.ident.status import Status
from estimator.ident.tracking.tracker import Tracker
from sim_bench.benches.refusal_bench import HYSTERESIS_PARTS, SEED_HYSTERESIS, _life, hysteresis_variant

FROM = 40               # injections before the scored ones
LH_LIMIT_UM, OPENING_LIMIT_US, OK_LIMIT_UM = 0.15, 1.0, 0.3


def part(i: int, injections: int = 70) -> dict[str, Any]:
    """The ``i``-th hysteresis part through the learning tracker; its row."""
    gain, shape = hysteresis_variant(i)
    life = _life(SEED_HYSTERESIS + i, hysteresis=(gain, shape))
    tracker = Tracker(self_calibration=SelfCalConfig())
    lh_err, open_err, ok_off = [], [], []
    t0 = time.perf_counter()
    for inj, m, truth in life.injections(injections):
        r = tracker.update(inj)
        e = r.lh_m * 1e6 - truth["lh_true_um"]
        if r.status == Status.OK and abs(e) > OK_LIMIT_UM:
            ok_off.append(truth["k"])
        if truth["k"] >= FROM:
            lh_err.append(abs(e))
            if np.isfinite(r.t_open_s) and np.isfinite(m.t_open_s):
                open_err.append(abs(r.t_open_s - m.t_open_s) * 1e6)
    own = tracker.own_parameters().get(0)
    st = tracker.calibration.get(0)
    return {"part": i, "seed": SEED_HYSTERESIS + i, "gain": gain, "shape": shape,
            "learned": own is not None, "element": own is not None and own.hysteresis.present,
            "state": st.state if st else "", "message": st.message if st else "",
            "max_lh_from_um": max(lh_err, default=float("nan")),
            "max_opening_from_us": max(open_err, default=float("nan")), "predicted": len(open_err),
            "ok_while_off": ok_off, "seconds": time.perf_counter() - t0}


def run(parts: int = HYSTERESIS_PARTS, injections: int = 70) -> dict[str, Any]:
    """Every part; a JSON-ready report with the verdict."""
    rows = [part(i, injections) for i in range(parts)]
    learned = [r for r in rows if r["element"]]
    pi = [r for r in rows if r["shape"] == "prandtl-ishlinskii"]
    s = {"parts": len(rows), "learned": len(learned), "pi_parts": len(pi), "pi_learned": sum(r["element"] for r in pi),
         "without_element": sum(r["learned"] and not r["element"] for r in rows),
         "max_lh_from_um": max((r["max_lh_from_um"] for r in learned), default=float("nan")),
         "max_opening_from_us": max((r["max_opening_from_us"] for r in learned), default=float("nan")),
         "ok_while_off": sum(len(r["ok_while_off"]) for r in rows)}
    fails = []
    if s["pi_learned"] < s["pi_parts"]:
        fails.append(f"{s['pi_parts'] - s['pi_learned']} Prandtl–Ishlinskii part(s) not learned")
    if s["without_element"]:
        fails.append(f"{s['without_element']} part(s) adopted without a hysteresis element")
    if learned and not s["max_lh_from_um"] <= LH_LIMIT_UM:
        fails.append(f"filtered L_h {s['max_lh_from_um']:.3f} µm off from injection {FROM} (> {LH_LIMIT_UM})")
    if learned and not s["max_opening_from_us"] <= OPENING_LIMIT_US:
        fails.append(f"opening {s['max_opening_from_us']:.2f} µs off from injection {FROM} (> {OPENING_LIMIT_US})")
    if s["ok_while_off"]:
        fails.append(f"{s['ok_while_off']} ok estimate(s) more than {OK_LIMIT_UM} µm off")
    s["failures"], s["passed"] = fails, not fails
    return {"benchmark": "selfcal-hysteresis", "injections": injections, "summary": s, "rows": rows, "passed": not fails}


def format_report(rep: dict[str, Any]) -> str:
    """A line per part and the verdict."""
    s = rep["summary"]
    lines = [f"hysteresis parts learned online ({rep['injections']} injections each, scored from {FROM}): "
             f"{s['learned']} of {s['parts']} with an element (Prandtl–Ishlinskii {s['pi_learned']} of {s['pi_parts']})",
             f"{'part':>4} {'shape':<19} {'gain':>4} {'element':>7} {'state':<11} {'L_h max µm':>10} {'opening max µs':>14} "
             f"{'ok >0.3 µm off':>14}"]
    for r in rep["rows"]:
        lines.append(f"{r['part']:>4} {r['shape']:<19} {r['gain']:>4.1f} {r['element']!s:>7} {r['state']:<11} "
                     f"{r['max_lh_from_um']:>10.3f} {r['max_opening_from_us']:>14.2f} {len(r['ok_while_off']):>14}")
    lines.append("  " + ("PASS" if s["passed"] else "FAIL: " + "; ".join(s["failures"])))
    return "\n".join(lines)
