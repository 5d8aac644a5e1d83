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
    """One published figure: the report it comes from (``bench``, as :func:`bench_of` names it), its
    name, how it is read from one report (a number, or a list whose range is the figure: lots, parts),
    its decimals (negative: rounded to tens, hundreds, ..., with thousands separated), the row of the
    performance page that states it (the start of one table line; None: its prose), whether the
    README's headline table states it too, and whether several runs are stated as the range alone
    (``spread``) rather than the median and the range."""

    bench: str
    name: str
    read: Callable[[Report], float | list[float]]
    digits: int
    row: str | None
    headline: bool = False
    spread: bool = False


def _summary(key: str, scale: float = 1.0) -> Callable[[Report], float]:
    """A key of the report's ``summary`` (times ``scale``: a fraction as a percentage)."""
    return lambda r: scale * r["summary"][key]


def _part(*keys: str) -> Callable[[Report], float]:
    """The figure at ``keys`` in the report's nested sections."""
    def read(r: Report) -> float:
        value: Any = r
        for k in keys:
            value = value[k]
        return float(value)
    return read


def _at_rate(rate: float, read: Callable[[Report], float]) -> Callable[[Report], float]:
    """A figure of the capacity sweep's phase at ``rate`` injections/s."""
    return lambda r: float(read(next(p for p in r["phases"] if p["rate_per_s"] == rate)))


def _count(fraction: str, of: str = "n") -> Callable[[Report], float]:
    """How many a fraction of the summary is of its ``of`` count."""
    return lambda r: round(r["summary"][fraction] * r["summary"][of])


def _ok_within_3_sigma(r: Report) -> float:
    """How many ``ok`` estimates of an accuracy sweep lie within 3σ."""
    s = r["summary"]
    return round(s["ok_within_3_sigma"] * round(s["ok_fraction"] * s["n"]))


def _lots(key: str, figure: str, loop: str = "closed") -> Callable[[Report], list[float]]:
    return lambda r: [lot[loop][key][figure] for lot in r["lots"]]


def _lots_pct(key: str, loop: str) -> Callable[[Report], list[float]]:
    """A fraction of each lot's loop, in percent."""
    return lambda r: [100.0 * lot[loop][key] for lot in r["lots"]]


def _both(r: Report, what: str) -> float:
    """Offline and online together (``refused``, ``false_flags``), of the good parts."""
    return float(r["summary"][f"offline_{what}"] + r["summary"][f"online_{what}"])


def _variant(name: str, key: str) -> Callable[[Report], float]:
    """One variant's figure in a ``selfcal`` report."""
    return lambda r: next(v for v in r["summary"] if v["variant"] == name)[key]


def _series_rows(key: str) -> Callable[[Report], list[float]]:
    """A figure of every series part (not the exact injector) of ``selfcal --online``."""
    return lambda r: [float(row[key]) for row in r["rows"] if not row.get("exact")]


def _lot_rows(key: str) -> Callable[[Report], list[float]]:
    """A figure of every position of the lot's life that has it."""
    return lambda r: [float(row[key]) for row in r["rows"] if row.get(key) is not None]


def _hazards(key: str) -> Callable[[Report], float]:
    """The worst of the state-directory hazards' (the second daemon's row apart)."""
    return lambda r: max(h[key] for h in r["rows"]["state-dir"]["hazards"] if "second_exit" not in h)


def _second(key: str) -> Callable[[Report], float]:
    """The second daemon on a held state directory."""
    return lambda r: next(h[key] for h in r["rows"]["state-dir"]["hazards"] if "second_exit" in h)


def _workers(n: int, key: str) -> Callable[[Report], float]:
    """A figure of the fleet's run on ``n`` workers."""
    return lambda r: next(run[key] for run in r["runs"] if run["workers"] == n)


def _accuracy(sweep: str, row: str, *figures: tuple[str, Callable[[Report], float], int],
              headline: tuple[str, ...] = ()) -> tuple[Figure, ...]:
    return tuple(Figure(f"accuracy --sweep {sweep}", name, read, digits, row, name in headline)
                 for name, read, digits in figures)


def _tracking(scenario: str, row: str, lh_digits: int = 3, nu_digits: int = 3) -> tuple[Figure, ...]:
    """A tracking scenario's row: filtered L_h and N_u RMS, RMS(error/σ) and the outliers counted."""
    bench = f"tracking --scenario {scenario}"
    return (Figure(bench, "rms_lh_um", _summary("rms_lh_um"), lh_digits, row),
            Figure(bench, "rms_nu_pct", _summary("rms_nu_pct"), nu_digits, row),
            Figure(bench, "sigma_ratio_lh", _summary("sigma_ratio_lh"), 2, row,
                   headline=scenario == "spread-injector"),
            Figure(bench, "outliers", _summary("outliers"), 0, row))


def _spreads(loop: str, prefix: str, stroke_row: str, stroke_digits: int, opening_row: str, opening_digits: int,
             p95: bool = True) -> tuple[Figure, ...]:
    """``compensation``'s plateau-stroke and opening-instant spreads across each lot once settled, in
    one loop: the median (a README headline figure for the open and the closed loop) and the 95th
    percentile."""
    out = []
    for what, unit, row, digits in (("stroke", "um", stroke_row, stroke_digits),
                                    ("opening", "us", opening_row, opening_digits)):
        key = f"{what}_spread_{unit}"
        out.append(Figure("compensation", prefix + key, _lots(key, "settled_median", loop), digits, row,
                          headline=loop in ("open", "closed")))
        if p95:
            out.append(Figure("compensation", f"{prefix}{what}_spread_p95_{unit}", _lots(key, "settled_p95", loop),
                              digits, row))
    return tuple(out)


RMSE_LH = ("rmse_lh_um", _summary("rmse_lh_um"), 3)
CRB_LH = ("crb_lh_um", _summary("crb_lh_um"), 3)
FALSE_MISMATCH = ("false_mismatch_pct", _summary("mismatch_fraction", 100), 0)
MISMATCH = ("mismatch_pct", _summary("mismatch_fraction", 100), 0)
OK_FAR = ("ok_off_by_more_than_0p3", _summary("ok_off_by_more_than_0p3"), 0)
Z_RMS = ("rms_error_over_sigma", _summary("rms_error_over_sigma"), 2)
HYSTERESIS_ROW = "| steady / fast-ramp / lh-step / glitch | hysteresis"
LEARNING_ROW = "| four series injectors learning at once"

FIGURES: tuple[Figure, ...] = (
    # single injection
    *_accuracy("random", "| random, exact model | L_h RMSE / CRB", RMSE_LH, CRB_LH, headline=("rmse_lh_um", "crb_lh_um")),
    *_accuracy("random", "| random, exact model | N_u RMSE / CRB", ("rmse_nu_pct", _summary("rmse_nu_pct"), 3),
               ("crb_nu_pct", _summary("crb_nu_pct"), 3), headline=("rmse_nu_pct", "crb_nu_pct")),
    *_accuracy("random", "| random, exact model | opening time RMSE", ("rmse_t_open_us", _summary("rmse_t_open_us"), 2),
               ("crb_t_open_us", _summary("crb_t_open_us"), 2)),
    *_accuracy("random", "| random, exact model | `model_mismatch` false alarms", FALSE_MISMATCH,
               headline=("false_mismatch_pct",)),
    *_accuracy("near-edge", "| near-edge", RMSE_LH, ("ok_pct", _summary("ok_fraction", 100), 0)),
    *_accuracy("high-noise", "| 0.3 V noise", RMSE_LH, CRB_LH, FALSE_MISMATCH, headline=("false_mismatch_pct",)),
    *_accuracy("random (mismatch)", "| hysteresis plant", RMSE_LH, ("max_abs_lh_um", _summary("max_abs_lh_um"), 2)),
    *_accuracy("spread", "| series parts ±10 %", OK_FAR, Z_RMS, MISMATCH, headline=("rms_error_over_sigma",)),
    *_accuracy("spread-chain", "| series parts behind an unmodelled chain", OK_FAR, Z_RMS),
    *_accuracy("chain", "| chain modelled", RMSE_LH, CRB_LH, ("max_abs_nu_pct", _summary("max_abs_nu_pct"), 3)),
    *_accuracy("preload-off", "| header preload force", OK_FAR, ("ok", _count("ok_fraction"), 0),
               ("ok_within_3_sigma", _ok_within_3_sigma, 0), Z_RMS, MISMATCH),
    # the recursive estimator
    *_tracking("steady", "| steady | exact"),
    Figure("tracking --scenario steady", "rms_lh_after_um", _summary("rms_lh_after_um"), 3, "| steady | exact",
           headline=True),
    *_tracking("temperature-ramp", "| temperature-ramp"),
    *_tracking("wear", "| wear"),
    *_tracking("fast-ramp", "| fast-ramp"),
    *_tracking("lh-step", "| lh-step"),
    *_tracking("nu-step", "| nu-step"),
    *_tracking("warm-up", "| warm-up ("),
    *_tracking("glitch", "| glitch ("),
    *(Figure(f"tracking --scenario {s} (mismatch)", "rms_lh_um", _summary("rms_lh_um"), 3, HYSTERESIS_ROW)
      for s in ("steady", "fast-ramp", "lh-step", "glitch")),
    Figure("tracking --scenario glitch (mismatch)", "outliers", _summary("outliers"), 0, HYSTERESIS_ROW),
    *_tracking("spread-injector", "| spread-injector", lh_digits=2, nu_digits=1),
    # learning
    Figure("tracking --scenario lot-life", "lh_max_within_um", _summary("max_lh_err_within_um"), 3,
           "| filtered L_h from injection 40, parts within tolerance", headline=True),
    Figure("tracking --scenario lot-life", "swap_settled_after", _lot_rows("swap_settled_after"), 0,
           "| swapped part: within 0.15 µm again"),
    Figure("tracking --scenario lot-life", "ok_far", _summary("ok_far"), 0, "| `ok` while more than 0.3 µm off"),
    *(Figure("tracking --scenario lot-life", key, _summary(key), 0, "| parts beyond tolerance flagged `out_of_tolerance`")
      for key in ("flagged_beyond", "beyond", "false_flags", "within")),
    Figure("tracking --scenario lot-life", "first_adopted", _lot_rows("first_adopted"), 0, "| first adoption"),
    *(Figure(f"tracking --scenario lot-life --preload {f}{narrow}", key, _summary(key), digits,
             f"| {f} N{', `--narrow-after 12`' if narrow else ''} |")
      for f, narrow in (("28", ""), ("100", ""), ("28", " --narrow-after 12"), ("100", " --narrow-after 12"),
                        ("250", " --narrow-after 12"))
      for key, digits in (("max_lh_err_within_um", 3), ("ok_far", 0), ("flagged_beyond", 0))),
    Figure("bench --scenario series-lot", "max_abs_lh_um", lambda r: r["max_abs_lh_um"], 3,
           "| end-to-end bench, every scenario", headline=True, spread=True),
    Figure("selfcal-refusals", "false_refusals", lambda r: _both(r, "refused"), 0,
           "| false refusals, offline / online", headline=True),
    Figure("selfcal-refusals", "false_flags", lambda r: _both(r, "false_flags"), 0,
           "| false `out_of_tolerance`, offline / online", headline=True),
    Figure("selfcal-refusals", "online_element", _summary("online_element"), 0,
           "| good parts given a hysteresis element (online)"),
    *(Figure("selfcal-refusals", key, _summary(key), 0, "| hysteresis parts learned with an element on their first")
      for key in ("hysteresis_learned", "pi_learned", "hysteresis_without_element")),
    Figure("selfcal-hysteresis", "learned", _summary("learned"), 0, "| hysteresis parts learned with an element ("),
    Figure("selfcal-hysteresis", "pi_learned", _summary("pi_learned"), 0, "| hysteresis parts learned with an element ("),
    Figure("selfcal-hysteresis", "max_lh_from_um", _summary("max_lh_from_um"), 3,
           "| hysteresis parts learned, filtered L_h"),
    Figure("selfcal-hysteresis", "max_opening_from_us", _summary("max_opening_from_us"), 2,
           "| hysteresis parts learned, filtered L_h"),
    Figure("selfcal-hysteresis", "ok_while_off", _summary("ok_while_off"), 0, "| hysteresis parts learned, filtered L_h"),
    *(Figure("selfcal-refusals", key, _summary(key), 0, "| parts beyond tolerance flagged, first window")
      for key in ("beyond_flagged_online", "beyond_flagged_refined")),
    # self-calibration
    *(Figure("selfcal", f"{key}_{variant}", _variant(variant, key), digits, row,
             headline=variant == "plain" and key in ("lh_rms_um", "lh_max_um", "nu_max_pct"))
      for variant, row in (("plain", "| plain |"), ("chain", "| chain (300 kHz")) for key, digits in
      (("adopted", 0), ("lh_rms_um", 3), ("lh_max_um", 3), ("nu_max_pct", 3), ("lh_max_z", 2), ("nu_max_z", 2),
       ("calibration_seconds_median", 1))),
    *(Figure("selfcal", f"{key}_mismatch", _variant("mismatch", key), digits, "| mismatch (chain + hysteresis)")
      for key, digits in (("lh_rms_um", 3), ("lh_max_um", 2), ("nu_max_pct", 1), ("calibration_seconds_median", 1))),
    Figure("selfcal", "lh_max_z", lambda r: max(_variant(v, "lh_max_z")(r) for v in ("plain", "chain")), 1, None,
           headline=True),
    Figure("selfcal-online", "adopted_at", _series_rows("adopted_at"), 0, "| injections until adoption",
           headline=True),
    Figure("selfcal-online", "lh_max_from_40_um", lambda r: max(_series_rows("max_lh_err_from_um")(r)), 3,
           "| filtered L_h error from injection 40 on", headline=True),
    Figure("selfcal-online", "lh_max_z_from_40", lambda r: max(_series_rows("max_lh_z_from")(r)), 2,
           "| filtered L_h error from injection 40 on"),
    *(Figure("selfcal-online", key, _part("speed", key), 2, "| update of a mismatched injector")
      for key in ("median_during_ms", "p99_during_ms", "median_ms")),
    Figure("selfcal-online", "p99_ms", _part("speed", "p99_ms"), 1, "| update of a mismatched injector"),
    # speed
    Figure("speed", "warm_median_ms", lambda r: r["warm_median_ms"], 3, "| warm per-injection update, median",
           headline=True),
    Figure("speed", "warm_p99_ms", lambda r: r["warm_p99_ms"], 2, "| warm per-injection update, p99"),
    Figure("speed", "warm_with_correction_median_ms", lambda r: r["warm_with_correction_median_ms"], 3,
           "| the same through the daemon's processor", headline=True),
    Figure("speed", "correction_added_ms", lambda r: r["correction_added_ms"], 3,
           "| the same through the daemon's processor"),
    Figure("speed", "cold_median_ms", lambda r: r["cold_median_ms"], 2, "| cold start, median", headline=True),
    Figure("speed", "first_call_ms", lambda r: r["first_call_ms"], 0, "| first identification in a process"),
    Figure("speed", "yardstick_us_per_candidate", lambda r: r["yardstick_us_per_candidate"], 1,
           "| the warm update in candidate simulations"),
    Figure("speed", "warm_median_candidates", lambda r: r["warm_median_candidates"], 0,
           "| the warm update in candidate simulations"),
    Figure("speed", "warm_with_correction_median_candidates", lambda r: r["warm_with_correction_median_candidates"],
           0, "| the warm update in candidate simulations"),
    # the daemon
    Figure("daemon", "ingest_frames_per_s", lambda r: r["ingest"]["frames_per_s"], -2, "| ingest", headline=True,
           spread=True),
    Figure("daemon", "daemon_p99_ms", lambda r: r["nominal"]["daemon_latency_p99_ms"], 2,
           "| latency, last frame → EstimateState", headline=True),
    Figure("daemon", "external_p99_ms", lambda r: r["nominal"]["external_latency_p99_ms"], 2,
           "| the same seen from another process"),
    Figure("daemon", "overload_p99_ms", lambda r: r["overload"]["daemon_latency_p99_ms"], 2, "| 2× overload"),
    Figure("daemon --self-calibration", "learning_p99_ms", lambda r: r["nominal"]["daemon_latency_p99_ms"], 2,
           LEARNING_ROW, headline=True),
    *(Figure("daemon --self-calibration", f"{stage}_p99_ms", _part("nominal", "daemon_stage_p99_ms", stage), 2,
             LEARNING_ROW) for stage in ("queue", "assembly", "estimation", "send")),
    Figure("daemon --self-calibration", "adopted_p99_ms", lambda r: r["adopted"]["daemon_latency_p99_ms"], 2,
           "| the same injectors once adopted", headline=True),
    Figure("daemon --self-calibration", "overload_p99_ms", lambda r: r["overload"]["daemon_latency_p99_ms"], 1,
           "| the same, then 400/s"),
    Figure("daemon --self-calibration", "yardstick_us_per_candidate", lambda r: r["yardstick_us_per_candidate"], 1,
           LEARNING_ROW),
    Figure("bench --scenario nominal", "max_abs_lh_um", lambda r: r["max_abs_lh_um"], 3,
           "| end-to-end bench, nominal", headline=True),
    Figure("bench --scenario nominal", "rms_lh_um", lambda r: r["rms_lh_um"], 3, "| end-to-end bench, nominal"),
    Figure("reliability", "hazard_ready_s", _hazards("ready_s"), 1, "| state-directory hazards", spread=True),
    Figure("reliability", "hazard_rss_mb", _hazards("rss_mb"), 0, "| state-directory hazards", spread=True),
    Figure("reliability", "second_exit", _second("second_exit"), 0, "| a second daemon", spread=True),
    Figure("reliability", "second_s", _second("second_s"), 1, "| a second daemon", spread=True),
    *(Figure("reliability", f"{attack}: {key}", _part("rows", attack, key), digits, row, spread=True)
      for attack, row in (("period-flood", "| a stranger's cheap flood"), ("full-flood", "| a stranger's well-formed"),
                          ("sighup-burst", "| 50 SIGHUPs"), ("command-flood", "| 1,000 reset commands"))
      for key, digits in (("legit_estimated", 0), ("legit_p99_ms", 1))),
    Figure("reliability", "period-flood: attacker_counted", _part("rows", "period-flood", "attacker_counted"), 0,
           "| a stranger's cheap flood", spread=True),
    Figure("reliability", "full-flood: attacker_counted", _part("rows", "full-flood", "attacker_counted"), 0,
           "| a stranger's well-formed", spread=True),
    Figure("reliability", "command-flood: commands_applied", _part("rows", "command-flood", "commands_applied"), 0,
           "| 1,000 reset commands", spread=True),
    # the daemon's capacity
    Figure("daemon-capacity", "capacity_per_s", _part("capacity_per_s"), 0, "| capacity", headline=True),
    Figure("daemon-capacity", "yardstick_us_per_candidate", _part("yardstick_us_per_candidate"), 1,
           "| capacity", spread=True),
    Figure("daemon-capacity", "interface_us_per_frame", _part("interface_us_per_frame"), 0,
           "| the bus interface's part"),
    Figure("daemon-capacity", "p99_ms_at_50", _at_rate(50.0, lambda p: p["daemon_p99_ms"]), 2,
           "| daemon p99 at 50 injections/s"),
    Figure("daemon-capacity", "cpu_ms_per_injection_at_100",
           _at_rate(100.0, lambda p: 1e3 * p["cpu_per_s"]["daemon"] / p["offered_per_s"]), 2,
           "| the daemon's CPU per injection"),
    # the XCP slave
    Figure("xcp-bench", "without_client_p99_ms", _part("without_client", "daemon_latency_p99_ms"), 2,
           "| XCP slave on, no client"),
    Figure("xcp-bench", "daq_p99_ms", _part("daq", "daemon_latency_p99_ms"), 2, "| one master, DAQ on the injection"),
    Figure("xcp-bench", "daq_lost", lambda r: float(max(r["daq"]["estimates"] - r["daq"]["daq_packets"], 0)
                                                    + r["slave"]["overruns"]), 0, "| one master, DAQ on the injection"),
    Figure("xcp-bench", "hostile_counted", _part("hostile", "counted"), 0, "| 10,000 hostile datagrams"),
    Figure("xcp-bench", "after_flood_p99_ms", _part("after_flood", "daemon_latency_p99_ms"), 2,
           "| 10,000 hostile datagrams"),
    # drive compensation
    *_spreads("open", "open_", "| plateau-stroke spread, open loop", 2, "| opening-instant spread, open loop", 1),
    *_spreads("closed", "", "| the same, closed loop (each correction", 3, "| the same, closed loop |", 2),
    *_spreads("closed_bus", "bus_", "| closed loop on the bus, stroke", 3, "| closed loop on the bus, opening", 2),
    *(Figure("compensation", f"{prefix}at_limit_pct", _lots_pct("at_limit_settled", loop), 1,
             "| settled injections at a drive limit") for prefix, loop in (("", "closed"), ("bus_", "closed_bus"))),
    Figure("compensation", "valid_not_ok",
           lambda r: float(sum(lot[loop]["valid_not_ok"] for lot in r["lots"] for loop in ("closed", "closed_bus"))),
           0, "| corrections published valid after an estimate that was not"),
    Figure("compensation", "settle_injections",
           lambda r: [p["settle_injections"] for lot in r["lots"] for p in lot["closed"]["injectors"]
                      if p["settle_injections"] is not None], 0,
           "| injections from the model's adoption", headline=True),
    Figure("compensation", "z_rms_stroke", lambda r: r["z_rms_stroke"], 2, "| RMS(error/σ) of the predicted stroke",
           headline=True),
    Figure("compensation", "z_rms_opening", lambda r: r["z_rms_opening"], 2, "| RMS(error/σ) of the predicted stroke",
           headline=True),
    *(Figure("compensation", f"bus_z_rms_{what}", _part(f"bus_z_rms_{what}"), 2,
             "| RMS(error/σ) of the predicted stroke") for what in ("stroke", "opening")),
    # lots
    *(Figure(f"fleet-bench{option}", name, _workers(n, key), digits, row)
      for option, row in (("", "| one trace per injector"), (" --captures", "| one BLF capture"))
      for name, n, key, digits in (("ready_per_s_1w", 1, "work_per_worker_per_s", 0),
                                   ("per_s_1w", 1, "injections_per_s", 0),
                                   ("ready_per_worker_per_s_2w", 2, "work_per_worker_per_s", 0),
                                   ("scaling_ready_2w", 2, "scaling_efficiency_ready", 2),
                                   ("rms_lh_um", 1, "rms_lh_um", 3), ("bad_flagged", 1, "bad_flagged", 0),
                                   ("bad_injectors", 1, "bad_injectors", 0), ("good_flagged", 1, "good_flagged", 0))),
)


def bench_of(report: Report) -> str:
    """The name :data:`FIGURES` knows a report by."""
    name = str(report.get("benchmark", ""))
    if name == "daemon" and report.get("self_calibration"):
        return "daemon --self-calibration"
    if name == "bench":
        return f"bench --scenario {report.get('scenario')}"
    if name == "fleet":
        return "fleet-bench" + (" --captures" if report.get("inputs") == "captures" else "")
    if name in ("accuracy", "tracking"):     # one report per sweep or scenario, on the exact or a mismatched plant
        summary = report.get("summary", {})
        which = summary.get("sweep") if name == "accuracy" else report.get("scenario") or summary.get("scenario")
        option = "--sweep" if name == "accuracy" else "--scenario"
        if report.get("preload_n") is not None:     # the lot's life at one rail pressure
            which += f" --preload {report['preload_n']:g}"
        if report.get("narrow_after"):
            which += f" --narrow-after {report['narrow_after']}"
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
    the runs themselves); the median and the range over several runs; one value where every run
    measured it alike (a seeded accuracy figure beside a timing of the same runs)."""
    if len(values) == 1:
        return number(values[0], digits)
    lo, hi = number(min(values), digits), number(max(values), digits)
    if lo == hi:
        return lo
    if spread:
        return f"{lo}–{hi}"
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
            except (KeyError, TypeError, IndexError, ValueError, StopIteration):   # a report of another version: not this figure
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
    """Write ``output`` with the figures found (those already there and not measured again stay, those
    :data:`FIGURES` no longer names go)."""
    found = publish(directories)
    if not found:
        print(f"no bench report with a headline figure under {', '.join(map(str, directories))}")
        return 1
    try:
        current = json.loads(output.read_text(encoding="utf-8")) if output.exists() else {}
    except ValueError:
        current = {}
    current.update(found)
    known = {f"{f.bench}: {f.name}" for f in FIGURES}
    for name in sorted(set(current) - known):         # a figure no bench publishes any more
        print(f"{name}: no longer published, removed")
        del current[name]
    output.write_text(json.dumps(dict(sorted(current.items())), indent=1, ensure_ascii=False) + "\n",
                      encoding="utf-8")
    for name, fig in found.items():
        print(f"{name:<55} {fig['text']:>24}   ({fig['runs']} run(s))")
    print(f"wrote {output}")
    return 0
