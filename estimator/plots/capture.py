"""``plot-capture``: N_u, L_h and the valve-opening time over time from a bus capture, one line per
injector, with the truth and a ± band around it where the capture holds SimTruth (bench captures).

Any capture format python-can reads (:func:`estimator.io.captures.read_capture`); times in s
from the first frame; only published estimates (every status that carries an estimate of its injection) are drawn.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from estimator.codec.errors import MalformedFrame
from estimator.codec.records import Codec, EstimateState, SimTruth, ValvePrediction
from estimator.errors import EstimatorError
from estimator.ident.status import ESTIMATED
from estimator.io.captures import read_capture, to_frame


def series(capture: Path) -> dict:
    """{injector: {"t", "nu", "lh", "t_open", "truth_t", "truth_nu", "truth_lh", "truth_open"}} lists."""
    codec = Codec()
    out: dict[int, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    state_t: dict[tuple[int, int], float] = {}
    t0 = None
    for msg in read_capture(capture):
        t0 = msg.timestamp if t0 is None else t0
        t = msg.timestamp - t0
        try:
            rec = codec.decode(to_frame(msg))
        except MalformedFrame:
            continue
        if isinstance(rec, EstimateState) and codec.status_of(rec.status) in ESTIMATED:
            s = out[rec.injector_id]
            s["t"].append(t)
            s["nu"].append(rec.nu_n_per_v)
            s["lh"].append(rec.lh_um)
            state_t[(rec.injector_id, rec.counter)] = t
        elif isinstance(rec, ValvePrediction) and (rec.injector_id, rec.counter) in state_t:
            s = out[rec.injector_id]
            s["open_t"].append(state_t[(rec.injector_id, rec.counter)])
            s["t_open"].append(rec.opening_us)
        elif isinstance(rec, SimTruth):
            s = out[rec.injector_id]
            s["truth_t"].append(t)
            s["truth_nu"].append(rec.nu_n_per_v)
            s["truth_lh"].append(rec.lh_um)
            s["truth_open"].append(rec.opening_us)
    return out


def plot_capture(capture: Path, out: Path, band_lh_um: float = 0.2, band_nu_pct: float = 0.3,
                 band_open_us: float = 1.0) -> Path:
    """Write the figure (PNG) and return its path; bands: ± around the truth (the bench's targets)."""
    from estimator.plots.figures import pyplot, save

    data = series(capture)
    if not data:
        raise EstimatorError(f"{capture}: no estimates in the capture")
    plt = pyplot()
    fig, ax = plt.subplots(3, 1, figsize=(10, 9), sharex=True)
    for inj in sorted(data):
        s = data[inj]
        color = f"C{inj}"
        ax[0].plot(s["t"], s["nu"], ".", ms=3, color=color, label=f"injector {inj}")
        ax[1].plot(s["t"], s["lh"], ".", ms=3, color=color)
        ax[2].plot(s["open_t"], s["t_open"], ".", ms=3, color=color)
        if s["truth_t"]:
            import numpy as np
            tt = np.asarray(s["truth_t"])
            for k, (key, half) in enumerate((("truth_nu", None), ("truth_lh", band_lh_um), ("truth_open", band_open_us))):
                v = np.asarray(s[key])
                h = v * band_nu_pct / 100 if half is None else np.full_like(v, half)
                ax[k].plot(tt, v, "-", lw=0.8, color=color)
                ax[k].fill_between(tt, v - h, v + h, color=color, alpha=0.15, lw=0)
    ax[0].set_ylabel("N_u [N/V]")
    ax[1].set_ylabel("L_h [µm]")
    ax[2].set_ylabel("opening time [µs]")
    ax[2].set_xlabel("time [s]")
    ax[0].legend(loc="best", fontsize=8)
    ax[0].set_title(f"{capture.name}: estimates (dots), truth ± band (lines) where known")
    out.parent.mkdir(parents=True, exist_ok=True)
    return save(fig, out)
