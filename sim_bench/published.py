"""The headline figures as the benches measured them, in one file (``python -m sim_bench publish``).

Each bench writes its report as JSON (``bench-results/<name>.json``). ``publish`` reads the reports
found under the directories it is given, one run of a bench per directory (a timing is published from
several runs, each from a scratch directory), takes each headline figure out of them (:data:`FIGURES`)
and writes ``docs/figures.json``: per figure its value, or the median and the range over the runs,
and the text the documentation states (``0.211 ms (0.210–0.213)``). That file is where a current
figure comes from; the README's headline table and the performance page are checked against it
(``tests/system/test_docs.py``), so a figure measured again and published fails the test until both
say it.
"""

from __future__ import annotations

import json
import statistics
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, NamedTuple

Report = dict[str, Any]


class Figure(NamedTuple):
    """One headline figure: the report it comes from (``bench``: the report's ``benchmark``, with
    `` --self-calibration`` for the daemon's learning run), its name, how it is read from one report
    (a number, or a list whose range is the figure: lots, parts), its decimals (negative: rounded to
    tens, hundreds, ..., with thousands separated), whether several runs are stated as the range
    alone (``spread``) rather than the median and the range, and whether the README's headline table
    states it (the performance page states every one)."""

    bench: str
    name: str
    read: Callable[[Report], float | list[float]]
    digits: int
    headline: bool = True
    spread: bool = False


def _lots(key: str, figure: str, loop: str = "closed") -> Callable[[Report], list[float]]:
    return lambda r: [lot[loop][key][figure] for lot in r["lots"]]


def _both(r: Report, what: str) -> float:
    """Offline and online together (``refused``, ``false_flags``), of the good parts."""
    return float(r["summary"][f"offline_{what}"] + r["summary"][f"online_{what}"])


def _variant(r: Report, name: str) -> dict[str, Any]:
    """One variant's summary of a ``selfcal`` report."""
    return next(v for v in r["summary"] if v["variant"] == name)


def _series_rows(r: Report, key: str) -> list[float]:
    return [float(row[key]) for row in r["rows"] if not row.get("exact")]


FIGURES: tuple[Figure, ...] = (
    Figure("accuracy --sweep random", "rmse_lh_um", lambda r: r["summary"]["rmse_lh_um"], 3),
    Figure("accuracy --sweep random", "crb_lh_um", lambda r: r["summary"]["crb_lh_um"], 3),
    Figure("accuracy --sweep random", "rmse_nu_pct", lambda r: r["summary"]["rmse_nu_pct"], 3),
    Figure("accuracy --sweep random", "crb_nu_pct", lambda r: r["summary"]["crb_nu_pct"], 3),
    Figure("accuracy --sweep random", "false_mismatch_pct", lambda r: 100 * r["summary"]["mismatch_fraction"], 0),
    Figure("accuracy --sweep high-noise", "false_mismatch_pct",
           lambda r: 100 * r["summary"]["mismatch_fraction"], 0),
    Figure("accuracy --sweep spread", "rms_error_over_sigma", lambda r: r["summary"]["rms_error_over_sigma"], 2),
    Figure("speed", "warm_median_ms", lambda r: r["warm_median_ms"], 3),
    Figure("speed", "warm_with_correction_median_ms", lambda r: r["warm_with_correction_median_ms"], 3),
    Figure("speed", "cold_median_ms", lambda r: r["cold_median_ms"], 2),
    Figure("daemon", "daemon_p99_ms", lambda r: r["nominal"]["daemon_latency_p99_ms"], 2),
    Figure("daemon", "ingest_frames_per_s", lambda r: r["ingest"]["frames_per_s"], -2, spread=True),
    Figure("daemon", "external_p99_ms", lambda r: r["nominal"]["external_latency_p99_ms"], 2, headline=False),
    Figure("daemon", "overload_p99_ms", lambda r: r["overload"]["daemon_latency_p99_ms"], 2, headline=False),
    Figure("daemon --self-calibration", "learning_p99_ms", lambda r: r["nominal"]["daemon_latency_p99_ms"], 2),
    Figure("daemon --self-calibration", "adopted_p99_ms", lambda r: r["adopted"]["daemon_latency_p99_ms"], 2),
    Figure("compensation", "open_stroke_spread_um", _lots("stroke_spread_um", "settled_median", "open"), 2),
    Figure("compensation", "open_opening_spread_us", _lots("opening_spread_us", "settled_median", "open"), 1),
    Figure("compensation", "stroke_spread_um", _lots("stroke_spread_um", "settled_median"), 3),
    Figure("compensation", "opening_spread_us", _lots("opening_spread_us", "settled_median"), 2),
    Figure("compensation", "settle_injections",
           lambda r: [p["settle_injections"] for lot in r["lots"] for p in lot["closed"]["injectors"]], 0),
    Figure("compensation", "z_rms_stroke", lambda r: r["z_rms_stroke"], 2),
    Figure("compensation", "z_rms_opening", lambda r: r["z_rms_opening"], 2),
    Figure("selfcal", "lh_rms_um", lambda r: _variant(r, "plain")["lh_rms_um"], 3),
    Figure("selfcal", "lh_max_um", lambda r: _variant(r, "plain")["lh_max_um"], 3),
    Figure("selfcal", "nu_max_pct", lambda r: _variant(r, "plain")["nu_max_pct"], 3),
    Figure("selfcal", "lh_max_z", lambda r: max(_variant(r, v)["lh_max_z"] for v in ("plain", "chain")), 1),
    Figure("selfcal", "lh_max_z_plain", lambda r: _variant(r, "plain")["lh_max_z"], 2, headline=False),
    Figure("selfcal", "lh_max_z_chain", lambda r: _variant(r, "chain")["lh_max_z"], 2, headline=False),
    Figure("selfcal-online", "lh_max_from_40_um", lambda r: max(_series_rows(r, "max_lh_err_from_um")), 3),
    Figure("selfcal-online", "adopted_at", lambda r: _series_rows(r, "adopted_at"), 0),
    Figure("bench --scenario nominal", "max_abs_lh_um", lambda r: r["max_abs_lh_um"], 3),
    Figure("bench --scenario series-lot", "max_abs_lh_um", lambda r: r["max_abs_lh_um"], 3, spread=True),
    Figure("selfcal-refusals", "false_refusals", lambda r: _both(r, "refused"), 0),
    Figure("selfcal-refusals", "false_flags", lambda r: _both(r, "false_flags"), 0),
    Figure("tracking --scenario steady", "rms_lh_after_um", lambda r: r["summary"]["rms_lh_after_um"], 3),
    Figure("tracking --scenario spread-injector", "sigma_ratio_lh", lambda r: r["summary"]["sigma_ratio_lh"], 2),
    Figure("tracking --scenario lot-life", "lh_max_within_um",
           lambda r: r["summary"]["max_lh_err_within_um"], 3),
)


def bench_of(report: Report) -> str:
    """The name :data:`FIGURES` knows a report by."""
    name = str(report.get("benchmark", ""))
    if name == "daemon" and report.get("self_calibration"):
        return "daemon --self-calibration"
    if name == "bench":
        return f"bench --scenario {report.get('scenario')}"
    if name in ("accuracy", "tracking"):     # one report per sweep or scenario, on the exact or a mismatched plant
        summary = report.get("summary", {})
        which = summary.get("sweep") if name == "accuracy" else report.get("scenario") or summary.get("scenario")
        option = "--sweep" if name == "accuracy" else "--scenario"
        return f"{name} {option} {which}" + (" (mismatch)" if summary.get("mismatch") else "")
    return name


def reports_in(directory: Path) -> list[Report]:
    """Every bench report under ``directory`` (a tracking report's scenarios each on its own)."""
    out: list[Report] = []
    for path in sorted(directory.rglob("*.json")):
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if not isinstance(doc, dict):
            continue
        if isinstance(doc.get("score"), dict):            # an end-to-end scenario's report
            out.append({"benchmark": "bench", **doc["score"]})
        elif doc.get("benchmark") in ("tracking", "accuracy") and "reports" in doc:
            out.extend(doc["reports"])
        elif "benchmark" in doc and doc["benchmark"] != "bench":   # bench-all.json repeats its scenarios'
            out.append(doc)
    return out


def number(v: float, digits: int) -> str:
    """``v`` as the documentation writes it: ``digits`` decimals, or (negative) rounded to tens,
    hundreds, ... with thousands separated (``214,700``)."""
    return f"{v:.{digits}f}" if digits >= 0 else f"{round(v, digits):,.0f}"


def text(values: list[float], digits: int, spread: bool = False) -> str:
    """What the documentation states: a value; the range (``spread``: one run's lots or parts, or
    the runs themselves); the median and the range over several runs."""
    if len(values) == 1:
        return number(values[0], digits)
    lo, hi = number(min(values), digits), number(max(values), digits)
    if spread:
        return lo if lo == hi else f"{lo}–{hi}"
    return f"{number(statistics.median(values), digits)} ({lo}–{hi})"


def publish(directories: Iterable[Path]) -> dict[str, dict[str, Any]]:
    """The published figures from the reports under ``directories`` (one run of a bench each)."""
    runs: dict[str, list[Report]] = {}
    for d in directories:
        for rep in reports_in(d):
            runs.setdefault(bench_of(rep), []).append(rep)
    out: dict[str, dict[str, Any]] = {}
    for fig in FIGURES:
        reports = runs.get(fig.bench, [])
        if not reports:
            continue
        read: list[float | list[float]] = []
        for r in reports:
            try:
                read.append(fig.read(r))
            except (KeyError, TypeError, IndexError, ValueError):   # a report of another version: not this figure
                print(f"{fig.bench}: a report without {fig.name}, left out")
        if not read:
            continue
        if len(read) == 1 and isinstance(read[0], list):     # one run: the range over its lots or parts
            vals = [float(v) for v in read[0]]
            shown = text(vals, fig.digits, spread=True)
        else:
            vals = [float(v) for v in read if not isinstance(v, list)]
            shown = text(vals, fig.digits, fig.spread)
        out[f"{fig.bench}: {fig.name}"] = {"text": shown, "runs": len(read),
                                           "values": [round(v, 6) for v in vals]}
    return out


def main(directories: list[Path], output: Path) -> int:
    """Write ``output`` with the figures found (those already there and not measured again stay)."""
    found = publish(directories)
    if not found:
        print(f"no bench report with a headline figure under {', '.join(map(str, directories))}")
        return 1
    try:
        current = json.loads(output.read_text(encoding="utf-8")) if output.exists() else {}
    except ValueError:
        current = {}
    current.update(found)
    output.write_text(json.dumps(dict(sorted(current.items())), indent=1, ensure_ascii=False) + "\n",
                      encoding="utf-8")
    for name, fig in found.items():
        print(f"{name:<55} {fig['text']:>24}   ({fig['runs']} run(s))")
    print(f"wrote {output}")
    return 0
