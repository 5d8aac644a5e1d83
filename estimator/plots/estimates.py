"""Estimates over an injector's life, from the rows the estimator writes (``replay --csv``, the
fleet's rows, :func:`~estimator.pipeline.estimates.iter_estimates`): filtered L_h and N_u with their
±2σ bands per injector, the injections that were not ``ok`` marked with their status, and the truth
where it is known (a simulated lot)."""

from __future__ import annotations

import csv
import math
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from estimator.errors import EstimatorError

#: per injector: (x, L_h µm, N_u N/V) of the truth
Truth = Mapping[int, tuple[Sequence[float], Sequence[float], Sequence[float]]]


def read_rows(path: Path) -> list[dict[str, Any]]:
    """The rows of a CSV the estimator wrote (``replay --csv``, ``fleet --out x.csv``)."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise EstimatorError(f"cannot read {path}: {exc}") from None
    if not rows or not {"injector_id", "lh_um", "status"} <= set(rows[0]):
        raise EstimatorError(f"{path}: not the estimator's rows (needs injector_id, lh_um, status columns)")
    return rows


def _number(v: Any) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return math.nan
    return x


def plot_estimates(rows: Iterable[Mapping[str, Any]], out: Path, truth: Truth | None = None,
                   title: str = "") -> Path:
    """Write the figure (PNG) and return its path. The x axis is each injector's injection count."""
    from estimator.plots.figures import pyplot, save

    per: dict[int, list[Mapping[str, Any]]] = defaultdict(list)
    for row in rows:
        per[int(_number(row["injector_id"]))].append(row)
    if not per:
        raise EstimatorError("no estimates to plot")
    plt = pyplot()
    fig, ax = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    for inj in sorted(per):
        rs, color = per[inj], f"C{inj % 10}"
        x = list(range(len(rs)))
        for k, (key, sigma) in enumerate((("lh_um", "sigma_lh_um"), ("nu_n_per_v", "sigma_nu_n_per_v"))):
            v = [_number(r[key]) for r in rs]
            s = [_number(r[sigma]) for r in rs]
            ax[k].plot(x, v, lw=1.0, color=color, label=f"injector {inj}" if k == 0 else None)
            ax[k].fill_between(x, [a - 2 * b for a, b in zip(v, s)], [a + 2 * b for a, b in zip(v, s)],
                               color=color, alpha=0.15, lw=0)
            off = [(i, a) for i, (a, r) in enumerate(zip(v, rs)) if r["status"] not in ("ok",)]
            if off:
                ax[k].plot([i for i, _ in off], [a for _, a in off], "x", ms=4, color=color)
        if truth is not None and inj in truth:
            tx, lh, nu = truth[inj]
            ax[0].plot(tx, lh, "k--", lw=0.8)
            ax[1].plot(tx, nu, "k--", lw=0.8)
    ax[0].set_ylabel("L_h [µm], ±2σ")
    ax[1].set_ylabel("N_u [N/V], ±2σ")
    ax[1].set_xlabel("injection")
    ax[0].legend(loc="best", fontsize=8)
    ax[0].set_title(title or "filtered estimates (lines, ±2σ bands); x: not ok; dashed: truth where known")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    return save(fig, out)
