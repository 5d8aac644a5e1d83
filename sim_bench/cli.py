"""Command line of the simulated injector and the benches: ``python -m sim_bench SUBCOMMAND``."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

import numpy as np

from estimator.cli_support import base_parser, lean_service_imports, run_cli
from estimator.errors import EstimatorError
from estimator.io.traces import read_trace, write_trace
from estimator.model.drive import DRIVES, Drive, named_drive
from estimator.model.parameters import NOMINAL_PRELOAD_N
from sim_bench.benches import tracking_bench
from sim_bench.benches.targets import TARGETS, missed
from sim_bench.hardware import scenarios
from sim_bench.hardware.amplifiers import EXTRA_PROFILES as EXTRA_AMPLIFIERS
from sim_bench.hardware.amplifiers import PROFILES as AMPLIFIER_PROFILES

log = logging.getLogger("sim_bench")
DEFAULT_OUT = Path("bench-results")


def _write_json(path: Path, report: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2, default=float) + "\n")
    print(f"wrote {path}")


def _drive(args: argparse.Namespace) -> Drive | None:
    """``--drive NAME``: a registered drive shape, or None (the scenario's or the standard drive)."""
    return named_drive(args.drive) if args.drive else None


def _add_drive_argument(s: argparse.ArgumentParser, default_text: str) -> None:
    s.add_argument("--drive", choices=tuple(DRIVES), default=None,
                   help=f"amplifier current shape (estimator.model.drive; default: {default_text})")


def _preload_force(text: str) -> float:
    """``--preload N``: a preload force within the lot's range (N)."""
    from sim_bench.hardware.series_life import PRELOAD_RANGE_N

    try:
        f = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a force in N") from None
    lo, hi = PRELOAD_RANGE_N
    if not lo <= f <= hi:
        raise argparse.ArgumentTypeError(f"{f:g} N is outside {lo:g}-{hi:g} N")
    return f


def _injections(text: str) -> int:
    """A count of injections (a whole number, 0 or more)."""
    try:
        k = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if k < 0:
        raise argparse.ArgumentTypeError(f"{k} is negative")
    return k


def _params(args: argparse.Namespace):
    """``--params FILE`` (what ``estimator calibrate --out`` writes) or Tables 1-2."""
    from estimator.model.parameters import load_parameters

    return load_parameters(args.params)


def cmd_simulate(args: argparse.Namespace) -> int:
    """Simulate one injection with the fast simulator and write the trace CSV."""
    from estimator.model.drive import StandardDrive, TableDrive, sample_times
    from estimator.model.fast_sim import FastSimulator

    t_end = args.t_end_us * 1e-6
    if not (0 < t_end <= 5e-3):
        raise EstimatorError(f"--t-end-us {args.t_end_us} must be in (0, 5000] µs")
    if not (-10.0 <= args.lh_um <= 50.0):
        raise EstimatorError(f"--lh-um {args.lh_um} must be within -10..50 µm (the model's range is about -2..10 µm)")
    if not (0.0 <= args.preload_n <= 1000.0):
        raise EstimatorError(f"--preload-n {args.preload_n} must be within 0..1000 N")
    t = sample_times(t_end)
    if args.current and args.drive:
        raise EstimatorError("give either --current FILE or --drive NAME, not both")
    if args.current:
        tr = read_trace(args.current)
        drive: Drive = TableDrive.from_table(tr.column("t_s"), tr.column("current_A"))
    else:
        drive = _drive(args) or StandardDrive()
    current = drive.samples(t_end)
    sim = FastSimulator(_params(args))
    res = sim.simulate(current, args.nu, args.lh_um * 1e-6, args.preload_n, exact=True)
    if not (res.success[0] and np.all(np.isfinite(res.voltage_v[0]))):
        raise EstimatorError(f"simulation failed: {res.message[0]} (N_u={args.nu} N/V, L_h={args.lh_um} µm, "
                             f"F_open={args.preload_n} N)")
    meta = {"nu_n_per_v": args.nu, "lh_um": args.lh_um, "preload_force_n": args.preload_n,
            "sample_period_s": sim.dt_s, "t_contact_us": f"{res.t_contact_s[0] * 1e6:.4f}",
            "t_open_us": f"{res.t_open_s[0] * 1e6:.4f}", "source": "sim_bench simulate (fast simulator)"}
    write_trace(args.out, {"t_s": res.t_s, "current_A": res.current_a, "voltage_V": res.voltage_v[0],
                           "s3_m": res.s3_m[0], "s4_m": res.s4_m[0], "mode": res.mode[0]}, meta)
    print(f"wrote {args.out}: {t.size} samples, contact {res.t_contact_s[0] * 1e6:.2f} µs, "
          f"opening {res.t_open_s[0] * 1e6:.2f} µs, peak voltage {np.nanmax(res.voltage_v):.2f} V")
    return 0


def cmd_speed_sim(args: argparse.Namespace) -> int:
    """Benchmark the fast simulator (candidates per second, batch 1/16/256)."""
    from sim_bench.benches import speed

    report = speed.measure(tuple(args.batch), seconds=args.seconds, drive=_drive(args))
    report["failures"] = missed("speed-sim", {f"candidates_per_s_{r['batch']}": r["candidates_per_s"]
                                              for r in report["results"]})
    print(speed.format_table(report))
    print("PASS" if not report["failures"] else "FAIL: " + "; ".join(report["failures"]))
    _write_json(args.json_out, report)
    return 1 if report["failures"] else 0


def cmd_table3(args: argparse.Namespace) -> int:
    """Reproduce Table 3 (PSA No. 1, "sim" column), then identify ten simulated actuators (section 5.4)."""
    from sim_bench.benches import ident_bench, table3

    if args.fit_drive:
        amp = table3.fit_drive_amplitude()
        print(f"standard drive amplitude for 24.50 µm at N_u=16.39 N/V, L_h=0.6 µm: {amp:.7f} A")
        rows = table3.reproduce(amplitude_a=amp)
    else:
        rows = table3.reproduce()
    print(table3.format_table(rows))
    worst = max(abs(r.diff_um) for r in rows)
    print(f"largest |ours - paper sim| = {worst:.3f} µm (tolerance 0.15 µm)")
    report = {"benchmark": "table3", "paper_psa1": [r.__dict__ for r in rows], "max_abs_diff_um": worst}
    if not args.paper_only:
        print()
        ident = ident_bench.table3(seed=args.seed, mismatch=not args.matched)
        print(ident_bench.format_table3(ident))
        report["identified"] = ident
    if args.json_out:
        _write_json(args.json_out, report)
    return 0 if worst <= 0.15 else 1


def cmd_accuracy(args: argparse.Namespace) -> int:
    """Single-injection accuracy against truth and the Cramér–Rao bound."""
    from sim_bench.benches import ident_bench

    scen = {"matched": [False], "mismatch": [True], "both": [False, True]}[args.scenario]
    sweeps = ["random", "near-edge", "high-noise", "spread", "chain", "preload-off"] if args.sweep == "all" else [args.sweep]
    reports = []
    for sweep in sweeps:
        plants = scen if sweep == "random" else [False]   # the other sweeps have targets of their own
        noise = ident_bench.HIGH_NOISE_V if sweep == "high-noise" else None
        reports += [ident_bench.accuracy(args.n, args.seed, m, args.window_us * 1e-6, sweep=sweep, noise_v=noise)
                    for m in plants]
    print(ident_bench.format_accuracy(reports))
    _write_json(args.json_out, {"benchmark": "accuracy", "reports": reports})
    return 0 if not any(r["summary"]["failures"] for r in reports) else 1


def cmd_tracking(args: argparse.Namespace) -> int:
    """The recursive estimator on drift, steps, glitches and warm-ups; exit 1 if a target is missed."""
    from sim_bench.benches import lot_life, tracking_bench

    if (args.preload is not None or args.narrow_after or args.hysteresis) and args.scenario != "lot-life":
        print("error: --preload, --narrow-after and --hysteresis are options of --scenario lot-life", file=sys.stderr)
        return 2
    if args.scenario == "lot-life":
        life = lot_life.run(args.seed, preload_n=args.preload, narrow_after=args.narrow_after,
                            hysteresis=args.hysteresis)
        print(lot_life.format_report(life))
        _write_json(args.json_out, life)
        return 0 if life["summary"]["passed"] else 1
    lot = lot_life.run(args.seed) if args.scenario == "all" and args.plant != "mismatch" else None
    names = list(tracking_bench.TRACKING) if args.scenario == "all" else [args.scenario]
    runs = []
    if args.plant in ("matched", "both", "default"):
        runs += [(n, False) for n in names]
    if args.plant in ("mismatch", "both"):
        runs += [(n, True) for n in names]
    elif args.plant == "default":
        runs += [(n, True) for n in names if n in tracking_bench.DEFAULT_MISMATCH]
    reports = [tracking_bench.tracking(n, args.seed, m, args.injections, drive=_drive(args)) for n, m in runs]
    print(tracking_bench.format_tracking(reports))
    if lot is not None:
        print(lot_life.format_report(lot))
        reports.append(lot)
    _write_json(args.json_out, {"benchmark": "tracking", "reports": reports})
    return 0 if all(r["summary"]["passed"] for r in reports) else 1


def cmd_speed(args: argparse.Namespace) -> int:
    """Timing of the recursive estimator (warm update, cold start)."""
    from sim_bench.benches import ident_bench

    rep = ident_bench.speed(args.seed, args.injections, drive=_drive(args))
    rep["targets"] = [t._asdict() for t in TARGETS["speed"]]
    rep["failures"] = ident_bench.speed_failures(rep)
    print(ident_bench.format_speed(rep))
    print("PASS" if not rep["failures"] else "FAIL: " + "; ".join(rep["failures"]))
    _write_json(args.json_out, rep)
    return 1 if rep["failures"] else 0


def cmd_calibration_traces(args: argparse.Namespace) -> int:
    """Write traces of an actuator without valve at several temperatures, with s3, for eq. 25."""
    from sim_bench.hardware import calibration_traces

    paths = calibration_traces.write(args.out, args.temps, args.seed, args.noise_v, drive=_drive(args))
    for p in paths:
        print(f"wrote {p}")
    return 0


def cmd_node(args: argparse.Namespace) -> int:
    """The simulated injector node on a bus."""
    import signal
    import threading

    import can

    from estimator.io.captures import to_message
    from estimator.service.bus import open_bus, resolve, spec_from_args
    from estimator.service.sdnotify import SdNotify
    from sim_bench.hardware import scenarios
    from sim_bench.hardware.node import InjectorNode

    try:
        sc = scenarios.get(args.scenario, injectors=args.injectors, rate_hz=args.rate, seconds=args.seconds,
                           drive=_drive(args))
    except KeyError as exc:
        raise EstimatorError(str(exc.args[0])) from None
    if not (1 <= sc.injectors <= 8) or not (0 < sc.rate_hz <= 5000):
        raise EstimatorError(f"--injectors {sc.injectors} must be 1..8 and --rate {sc.rate_hz} within (0, 5000] Hz")
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    spec = resolve(spec_from_args(args))
    with open_bus(spec) as bus:
        def send(frame) -> None:
            try:
                bus.send(to_message(frame), timeout=0.05)
            except can.CanError as exc:
                raise OSError(str(exc)) from None
        node = InjectorNode(send, sc, args.seed)
        notifier = None
        if args.apply_corrections:   # drive each injector with the estimator's DriveCorrection, as an amplifier would
            from estimator.codec.records import Codec, DriveCorrection, DriveCorrectionRow
            from estimator.io.captures import to_frame

            codec = Codec()
            wanted = {codec.messages[DriveCorrection].frame_id, codec.messages[DriveCorrectionRow].frame_id}

            def on_message(msg: can.Message) -> None:
                if msg.arbitration_id in wanted and not msg.is_error_frame:
                    try:
                        rec = codec.decode(to_frame(msg))
                    except EstimatorError:
                        return
                    if isinstance(rec, (DriveCorrection, DriveCorrectionRow)):
                        node.take_correction(rec)
            notifier = can.Notifier(bus, [on_message], timeout=0.05)
        log.info("node: scenario %s, %d injectors at %.1f Hz on %s%s", sc.name, sc.injectors, sc.rate_hz, spec,
                 ", applying the estimator's drive corrections" if notifier else "")
        SdNotify().notify(f"READY=1\nSTATUS=simulating {sc.injectors} injector(s), scenario {sc.name}, on {spec}")
        try:
            node.run(stop, seconds=None if args.count else sc.seconds, count=args.count)
        finally:
            if notifier is not None:
                notifier.stop(timeout=0.5)
    print(node.summary_json(), flush=True)
    return 0


def cmd_compensation(args: argparse.Namespace) -> int:
    """A lot of series injectors, open loop and closed loop with the drive corrections; exit 1 on a miss."""
    from sim_bench.benches import compensation

    if not (2 <= args.injectors <= 8) or args.injections < compensation.SETTLED + 20:
        raise EstimatorError(f"--injectors must be 2..8 and --injections at least {compensation.SETTLED + 20}")
    if not (1 <= args.lots <= 10):
        raise EstimatorError("--lots must be 1..10")
    amps = compensation.PROFILES if args.amplifier == "all" else (args.amplifier,)
    rep = compensation.run(args.seed, args.injectors, args.injections, args.lots, amps, args.hysteresis)
    print(compensation.format_report(rep))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    compensation.figure(rep, args.out)
    print(f"figure: {args.out}")
    _write_json(args.json_out, rep)
    return 1 if rep["failures"] else 0


def cmd_bench(args: argparse.Namespace) -> int:
    """End-to-end bench: daemon + node processes on a real bus, scored against SimTruth."""
    from sim_bench.benches import bench
    from sim_bench.hardware import scenarios

    if args.seconds is not None and not (1.0 <= args.seconds <= 86_400):
        raise EstimatorError(f"--seconds {args.seconds} must be within 1..86400 s")
    names = list(scenarios.SCENARIOS) if args.scenario == "all" else [args.scenario]
    for n in names:
        if n not in scenarios.SCENARIOS:
            raise EstimatorError(f"unknown scenario {n!r}; one of {', '.join(scenarios.SCENARIOS)}, all")
    failed = False
    summary = []
    for n in names:
        s = bench.run_bench(n, args.bus, args.seconds, args.out / n if len(names) > 1 else args.out, args.seed,
                            progress=not args.quiet and sys.stderr.isatty(), plots=not args.no_plots,
                            capture_format=args.capture_format, drive=args.drive)
        print(bench.format_score(s))
        summary.append(s)
        failed |= bool(s["failures"])
    if len(names) > 1:
        _write_json(args.out / "bench-all.json", {"benchmark": "bench", "scores": summary})
    print(f"results in {args.out}")
    return 1 if failed else 0


def cmd_daemon_bench(args: argparse.Namespace) -> int:
    """Daemon benchmarks: ingest rate, latency at a rate, 2x overload."""
    from sim_bench.benches import daemon_bench

    if args.sweep:
        return _daemon_capacity(args)
    if args.rates is not None or args.cpu_share is not None:
        raise EstimatorError("--rates and --cpu-share go with --sweep")
    args.json_out = args.json_out or DEFAULT_OUT / "daemon-bench.json"
    ing = daemon_bench.ingest_rate()
    rep = daemon_bench.run_latency_and_overload(args.out, args.rate, args.seconds, 2.0, args.bus, args.self_calibration)
    failures = daemon_bench.failures(ing, rep)
    print(daemon_bench.format_report(ing, rep))
    print("PASS" if not failures else "FAIL: " + "; ".join(failures))
    _write_json(args.json_out, {"benchmark": "daemon", "ingest": ing, **rep, "failures": failures})
    return 1 if failures else 0


def _daemon_capacity(args: argparse.Namespace) -> int:
    """``daemon-bench --sweep``: the capacity; exit 1 below its target (scaled by the CPU share)."""
    from sim_bench.benches import capacity
    from sim_bench.benches.targets import missed

    rates = tuple(args.rates) if args.rates else capacity.RATES_PER_S
    if any(not (0 < r <= 100_000) for r in rates):
        raise EstimatorError(f"--rates {' '.join(f'{r:g}' for r in rates)}: each must be in 0 ... 100,000 injections/s")
    if args.cpu_share is not None and not 0.01 <= args.cpu_share <= 1.0:
        raise EstimatorError(f"--cpu-share {args.cpu_share:g}: must be in 0.01 ... 1")
    rep = capacity.run(args.out, tuple(sorted(rates)), args.seconds, bus=args.bus, share=args.cpu_share,
                       series=args.self_calibration)
    share = args.cpu_share or 1.0
    failures = missed("daemon-bench --sweep", {"capacity_per_s": rep["capacity_per_s"] / share}) + \
        capacity.failures(rep)
    print(capacity.format_report(rep))
    print("PASS" if not failures else "FAIL: " + "; ".join(failures))
    _write_json(args.json_out or DEFAULT_OUT / "daemon-capacity.json",
                {"benchmark": "daemon-capacity", **rep, "failures": failures})
    return 1 if failures else 0


def cmd_xcp_bench(args: argparse.Namespace) -> int:
    """The daemon with its XCP slave: DAQ at a rate, hostile datagrams; exit 1 on a miss."""
    from sim_bench.benches import xcp_bench

    rep = xcp_bench.run(args.out, args.rate, args.seconds, args.bus)
    print(xcp_bench.format_report(rep))
    print("PASS" if not rep["failures"] else "FAIL: " + "; ".join(rep["failures"]))
    _write_json(args.json_out, rep)
    return 1 if rep["failures"] else 0


def cmd_reliability(args: argparse.Namespace) -> int:
    """The daemon under faults (sample periods, stalls, floods, poisoned state, commands); exit 1 on a loss."""
    from sim_bench.benches import reliability

    try:
        rep = reliability.run_all(args.out, args.bus, tuple(args.only or ()))
    except ValueError as exc:
        print(f"sim_bench reliability: {exc}", file=sys.stderr)
        return 2
    rep["failures"] = reliability.failures(rep)
    print(reliability.format_report(rep))
    print("PASS" if not rep["failures"] else "FAIL: " + "; ".join(rep["failures"]))
    _write_json(args.json_out, rep)
    return 1 if rep["failures"] else 0


def _part_sweep(name: str, parts: int, bench: Any, json_out: Path | None) -> int:
    """A ``selfcal`` sweep over ``parts`` seeded parts (``--refusals``, ``--minima``; ``bench`` its module):
    the report printed and written as JSON; exit 1 if a target is missed."""
    if not 1 <= parts <= 1000:
        raise EstimatorError(f"--{name} {parts}: must be within 1..1000")
    rep = bench.run(parts)
    print(bench.format_report(rep))
    _write_json(json_out or DEFAULT_OUT / f"selfcal-{name}.json", rep)
    return 0 if rep["passed"] else 1


def cmd_selfcal(args: argparse.Namespace) -> int:
    """Series injectors calibrated from their own current and voltage; exit 1 if a target is missed."""
    from sim_bench.benches import selfcal_bench

    if not 1 <= args.injectors <= 100:
        raise EstimatorError(f"--injectors {args.injectors}: must be within 1..100")
    if args.refusals:
        from sim_bench.benches import refusal_bench

        return _part_sweep("refusals", args.refusals, refusal_bench, args.json_out)
    if args.minima:
        from sim_bench.benches import minimum_bench

        return _part_sweep("minima", args.minima, minimum_bench, args.json_out)
    if args.hysteresis:
        from sim_bench.benches import hysteresis_bench

        rep = hysteresis_bench.run(online=args.online)
        print(hysteresis_bench.format_report(rep))
        _write_json(args.json_out or DEFAULT_OUT / f"{rep['benchmark']}.json", rep)
        return 0 if rep["passed"] else 1
    if args.online:
        rep = selfcal_bench.run_online(args.injectors, args.seed)
        print(selfcal_bench.format_online(rep))
        _write_json(args.json_out or DEFAULT_OUT / "selfcal-online.json", rep)
        return 0 if rep["passed"] else 1
    variants = selfcal_bench.VARIANTS if args.variant == "all" else (args.variant,)
    rep = selfcal_bench.run(args.injectors, args.seed, variants)
    print(selfcal_bench.format_report(rep))
    _write_json(args.json_out or DEFAULT_OUT / "selfcal.json", rep)
    return 0 if rep["passed"] else 1


def cmd_fleet_bench(args: argparse.Namespace) -> int:
    """The fleet path on a synthetic lot at 1 and 2 workers: throughput, scaling, accuracy."""
    import os

    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    from sim_bench.benches import fleet_bench

    try:
        rep = fleet_bench.run(args.out, args.injectors, tuple(args.workers), args.seed, args.injections,
                              args.captures)
    except ValueError as exc:    # make_lot's own check of --injectors and --injections, as in `lot`
        raise EstimatorError(str(exc)) from None
    rep["failures"] = [f"{r['workers']} worker(s): {f}" for r in rep["runs"] for f in missed("fleet-bench", r)]
    print(fleet_bench.format_report(rep))
    print("PASS" if not rep["failures"] else "FAIL: " + "; ".join(rep["failures"]))
    _write_json(args.json_out, rep)
    return 1 if rep["failures"] else 0


def cmd_lot(args: argparse.Namespace) -> int:
    """A seeded synthetic production lot (CSV traces with serial numbers, and truth.csv)."""
    from sim_bench.hardware.lot import make_lot

    series = None
    if args.series:
        from sim_bench.hardware.series_life import LotSpec

        if not (0.0 < args.spread <= 0.3 and 0.0 <= args.beyond <= 1.0):
            raise EstimatorError(f"--spread {args.spread} must be in (0, 0.3] and --beyond {args.beyond} in [0, 1]")
        swapped = tuple(range(0, args.injectors, max(1, round(1 / args.swap_share)))) if args.swap_share > 0 else ()
        series = LotSpec(spread=args.spread, beyond_fraction=args.beyond,
                         swap_at=args.swap_at if swapped else None, swapped=swapped)
    try:
        truth = make_lot(args.out, args.injectors, args.injections, args.seed, drive=_drive(args), captures=args.captures,
                         series=series)
    except ValueError as exc:
        raise EstimatorError(str(exc)) from None
    what = f"captures ({args.injectors * args.injections} injections)" if args.captures else \
        f"{args.injectors * args.injections} traces"
    print(f"wrote {what} of {args.injectors} injectors and {truth}")
    return 0


def cmd_publish(args: argparse.Namespace) -> int:
    from sim_bench.benches.published import main as publish_main

    missing = [d for d in args.dirs if not d.is_dir()]
    if missing:
        print(f"error: not a directory: {missing[0]}", file=sys.stderr)
        return 2
    return publish_main(args.dirs, args.out)


def cmd_hub(args: argparse.Namespace) -> int:
    """Serve the loopback CAN hub until interrupted (SIGINT, SIGTERM, SIGHUP stop it and its server)."""
    from sim_bench.hardware.hub import Hub

    with Hub(args.port) as hub:
        print(f"CAN hub: --bus {hub.spec}", flush=True)
        assert hub.proc is not None
        code = hub.proc.wait()   # a signal to us raises KeyboardInterrupt here; the with-block stops the server
    raise EstimatorError(f"the hub server exited by itself with code {code}")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with all subcommands."""
    p, sub = base_parser("python -m sim_bench", __doc__)

    s = sub.add_parser("simulate", help="simulate one injection and write a trace CSV")
    s.add_argument("--current", type=Path, help="CSV with columns t_s,current_A (resampled to 0.5 µs)")
    _add_drive_argument(s, "standard")
    s.add_argument("--nu", type=float, default=16.39, help="coupling factor N_u in N/V (default 16.39)")
    s.add_argument("--lh-um", type=float, default=2.5, help="idle stroke L_h in µm (default 2.5)")
    s.add_argument("--preload-n", type=float, default=NOMINAL_PRELOAD_N,
                   help=f"valve preload F_open in N (default {NOMINAL_PRELOAD_N:g}, Table 2)")
    s.add_argument("--t-end-us", type=float, default=500.0, help="simulated time in µs (default 500)")
    s.add_argument("--out", type=Path, required=True, help="output trace CSV")
    s.add_argument("--params", type=Path, default=None, help="model parameter TOML (default Tables 1-2)")
    s.set_defaults(func=cmd_simulate)

    s = sub.add_parser("speed-sim", help="benchmark the fast simulator")
    s.add_argument("--batch", type=int, nargs="+", default=[1, 16, 256], help="candidate batch sizes to time (default 1 16 256)")
    s.add_argument("--seconds", type=float, default=2.0, help="time per batch size (s)")
    _add_drive_argument(s, "standard")
    s.add_argument("--json-out", type=Path, default=DEFAULT_OUT / "speed-sim.json", help="JSON report (default bench-results/speed-sim.json)")
    s.set_defaults(func=cmd_speed_sim)

    s = sub.add_parser("table3", help="Table 3: the paper's PSA No. 1 reproduced, then ten simulated actuators identified")
    s.add_argument("--fit-drive", action="store_true", help="re-derive the standard drive amplitude first")
    s.add_argument("--paper-only", action="store_true", help="only the PSA No. 1 reproduction")
    s.add_argument("--matched", action="store_true", help="plant without model error (default: with mismatch)")
    s.add_argument("--seed", type=int, default=3, help="seed of the random draws (default 3)")
    s.add_argument("--json-out", type=Path, default=DEFAULT_OUT / "table3.json", help="JSON report (default bench-results/table3.json)")
    s.set_defaults(func=cmd_table3)

    s = sub.add_parser("node", help="the simulated injector node on a CAN bus (any python-can interface)")
    from estimator.service.bus import add_arguments as add_bus_arguments

    add_bus_arguments(s)
    s.add_argument("--scenario", default="nominal", choices=tuple(scenarios.SCENARIOS), help="what the node simulates (default nominal; see the bench's scenarios)")
    s.add_argument("--injectors", type=int, default=None, help="number of injectors (default: the scenario's)")
    s.add_argument("--rate", type=float, default=None, help="injections per second per injector")
    s.add_argument("--seconds", type=float, default=None, help="run time (default: the scenario's)")
    s.add_argument("--count", type=int, default=None, help="stop after this many injections per injector")
    _add_drive_argument(s, "the scenario's")
    s.add_argument("--seed", type=int, default=0, help="seed of the random draws (default 0)")
    s.add_argument("--apply-corrections", action="store_true", help="drive each injector with the estimator's last "
                   "DriveCorrection (0x204) for it, as an amplifier would: the HIL bench in closed loop")
    s.set_defaults(func=cmd_node)

    s = sub.add_parser("compensation", help="drive compensation: a lot of series injectors open and closed loop")
    s.add_argument("--seed", type=int, default=1, help="seed of the first lot (default 1)")
    s.add_argument("--injectors", type=int, default=8, help="injectors in a lot (default 8)")
    s.add_argument("--lots", type=int, default=1, help="lots per amplifier profile, seeds SEED, SEED+1, ... (default 1)")
    s.add_argument("--amplifier", default="all", choices=(*AMPLIFIER_PROFILES, *EXTRA_AMPLIFIERS, "all"),
                   help="the simulated amplifier's standard drive (sim_bench.hardware.amplifiers; default all: "
                   f"{', '.join(AMPLIFIER_PROFILES)})")
    s.add_argument("--injections", type=int, default=150, help="injections per injector (default 150)")
    s.add_argument("--hysteresis", action="store_true",
                   help="two of the lot's parts with a hysteresis R(N_u) I cannot explain (learned with the element)")
    s.add_argument("--out", type=Path, default=DEFAULT_OUT / "compensation.png", help="figure (default bench-results/compensation.png)")
    s.add_argument("--json-out", type=Path, default=DEFAULT_OUT / "compensation.json", help="JSON report (default bench-results/compensation.json)")
    s.set_defaults(func=cmd_compensation)

    s = sub.add_parser("bench", help="end-to-end bench: daemon + node on a real bus, scored")
    s.add_argument("--scenario", default="nominal", choices=(*scenarios.SCENARIOS, "all"), help="scenario, or all of them (default nominal)")
    s.add_argument("--bus", default=None, help="default: socketcan:vcan0 if it exists, else a loopback hub")
    s.add_argument("--seconds", type=float, default=None, help="node run time (default: the scenario's)")
    s.add_argument("--out", type=Path, default=DEFAULT_OUT / "bench", help="directory for the capture, JSON and plots (default bench-results/bench)")
    s.add_argument("--seed", type=int, default=0, help="seed of the random draws (default 0)")
    s.add_argument("--quiet", action="store_true", help="no live progress line (it goes to stderr, on a terminal only)")
    s.add_argument("--no-plots", action="store_true", help="do not draw the PNG figures")
    s.add_argument("--capture-format", choices=("log", "asc", "blf", "csv", "mf4"), default="log",
                   help="format of the bus capture (default log: candump -L)")
    _add_drive_argument(s, "the scenario's")
    s.set_defaults(func=cmd_bench)

    s = sub.add_parser("daemon-bench", help="daemon: ingest rate, latency at 200 injections/s, 2x overload")
    s.add_argument("--rate", type=float, default=200.0, help="injections per second (all injectors)")
    s.add_argument("--self-calibration", action="store_true",
                   help="series injectors (structure ±10 %%, preload cycling) and the daemon's self-calibration on: "
                        "its background calibrations run while the latency is measured")
    s.add_argument("--seconds", type=float, default=10.0, help="seconds per phase (default 10)")
    s.add_argument("--bus", default=None, help="INTERFACE:CHANNEL (default: vcan0 if present, else a loopback hub)")
    s.add_argument("--out", type=Path, default=DEFAULT_OUT / "daemon", help="directory for the figures (default bench-results/daemon)")
    s.add_argument("--json-out", type=Path, default=None,
                   help="JSON report (default bench-results/daemon-bench.json, with --sweep daemon-capacity.json)")
    s.add_argument("--sweep", action="store_true",
                   help="capacity instead: sweep the offered rate (50 to 5,000 injections/s over eight injectors, learning and drive correction on, "
                        "frames replayed by a sender process) and report the highest rate held; with "
                        "--self-calibration the injectors are series parts that learn during the sweep")
    s.add_argument("--rates", type=float, nargs="+", default=None,
                   help="with --sweep: the rates, injections/s (default 50 100 200 500 1000 2000 3000 5000; the sweep "
                        "ends after two rates in a row not held)")
    s.add_argument("--cpu-share", type=float, default=None,
                   help="with --sweep: hold the daemon to this share of one core (cgroup CPU bandwidth; needs "
                        "root), a bench computer 1/share times slower")
    s.set_defaults(func=cmd_daemon_bench)

    s = sub.add_parser("xcp-bench", help="daemon with its XCP slave: DAQ on the injection event at 200 injections/s "
                                         "with a pyxcp master, then 10,000 hostile datagrams")
    s.add_argument("--rate", type=float, default=200.0, help="injections per second (all injectors)")
    s.add_argument("--seconds", type=float, default=10.0, help="seconds per phase (default 10)")
    s.add_argument("--bus", default=None, help="INTERFACE:CHANNEL (default: vcan0 if present, else a loopback hub)")
    s.add_argument("--out", type=Path, default=DEFAULT_OUT / "xcp", help="directory for the logs (default bench-results/xcp)")
    s.add_argument("--json-out", type=Path, default=DEFAULT_OUT / "xcp-bench.json",
                   help="JSON report (default bench-results/xcp-bench.json)")
    s.set_defaults(func=cmd_xcp_bench)

    s = sub.add_parser("fleet-bench", help="fleet on a synthetic lot at 1 and 2 workers: throughput, accuracy")
    s.add_argument("--injectors", type=int, default=1000, help="injectors in the synthetic lot (default 1000)")
    s.add_argument("--injections", type=int, default=1,
                   help="traces per injector (1: every injection a cold start; more: the first cold, the rest warm)")
    s.add_argument("--captures", action="store_true",
                   help="one BLF capture per injector (its injections as bus frames) instead of CSV traces")
    s.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts to run (default 1 2)")
    s.add_argument("--seed", type=int, default=11, help="seed of the random draws (default 11)")
    s.add_argument("--out", type=Path, default=DEFAULT_OUT / "fleet", help="directory for the lot and the results (default bench-results/fleet)")
    s.add_argument("--json-out", type=Path, default=DEFAULT_OUT / "fleet-bench.json", help="JSON report (default bench-results/fleet-bench.json)")
    s.set_defaults(func=cmd_fleet_bench)

    s = sub.add_parser("selfcal", help="series injectors calibrated from 30 of their own injections (current and "
                       "voltage only), then judged on 30 new ones with and without their parameters")
    s.add_argument("--injectors", type=int, default=10, help="series injectors per variant (default 10)")
    s.add_argument("--variant", choices=("all", "plain", "chain", "mismatch"), default="all",
                   help="plain: the series part alone; chain: behind an amplifier chain the calibration is not "
                        "told about; mismatch: the chain plus hysteresis, which no parameter set explains (default all)")
    s.add_argument("--seed", type=int, default=11, help="seed of the first injector (default 11)")
    s.add_argument("--refusals", type=int, default=0, metavar="N",
                   help="the acceptance sweep instead: N good seeded series parts through the offline and online "
                   "calibrations (false refusals, false out_of_tolerance, false hysteresis elements), hysteresis parts (learned "
                   "with an element or refused) and parts "
                   "beyond tolerance (flagged); about 3 s a part")
    s.add_argument("--minima", type=int, default=0, metavar="N",
                   help="instead: N good seeded series parts, each one's first learning window calibrated as the "
                   "learner does and from the part's own parameters too: how often the calibration stops short of "
                   "the deeper minimum (about 8 s a part)")
    s.add_argument("--hysteresis", action="store_true",
                   help="instead: series parts whose hysteresis R(N_u) I cannot explain (two shapes, three sizes) "
                        "through the tracker with learning on: learned with a hysteresis element, L_h and the opening "
                        "from injection 40, no ok while more than 0.3 µm off (about 3 min a part); with --online: "
                        "through the background calibrator, an injection every 0.25 s")
    s.add_argument("--online", action="store_true",
                   help="instead: each injector through the tracker with self-calibration on and the daemon's "
                        "background calibrator, an injection every 0.25 s, and an exact injector (no harm)")
    s.add_argument("--json-out", type=Path, default=None,
                   help="JSON report (default bench-results/selfcal.json, with --online selfcal-online.json)")
    s.set_defaults(func=cmd_selfcal)

    s = sub.add_parser("lot", help="a seeded synthetic production lot (traces with serial numbers + truth)")
    s.add_argument("--injectors", type=int, default=100, help="injectors in the lot (default 100)")
    s.add_argument("--injections", type=int, default=1, help="traces per injector (1 s apart)")
    s.add_argument("--series", action="store_true", help="series parts: every structural parameter within --spread "
                   "of Tables 1-2, one amplifier chain, a warm-up, the rail pressure wandering 28-300 N, wear, "
                   "--beyond of the parts beyond tolerance, --swap-share of them swapped at --swap-at (200 µs sent)")
    s.add_argument("--spread", type=float, default=0.10, help="--series: relative spread of the structure (default 0.10)")
    s.add_argument("--beyond", type=float, default=0.0, help="--series: share of parts beyond tolerance (default 0)")
    s.add_argument("--swap-share", type=float, default=0.0, help="--series: share of injectors whose part is swapped")
    s.add_argument("--swap-at", type=int, default=40, help="--series: the injection at which they are (default 40)")
    s.add_argument("--captures", action="store_true",
                   help="one BLF capture per injector (captures/SERIAL.blf) instead of CSV traces")
    _add_drive_argument(s, "standard")
    s.add_argument("--seed", type=int, default=11, help="seed of the random draws (default 11)")
    s.add_argument("--out", type=Path, required=True, help="output directory (traces/, captures/, truth.csv)")
    s.set_defaults(func=cmd_lot)

    s = sub.add_parser("reliability", help="daemon under faults: sample periods, stalls, floods, state, commands")
    s.add_argument("--bus", default=None, help="default: socketcan:vcan0 if it exists, else a loopback hub")
    s.add_argument("--out", type=Path, default=DEFAULT_OUT / "reliability", help="directory for the daemon's files (default bench-results/reliability)")
    s.add_argument("--json-out", type=Path, default=DEFAULT_OUT / "reliability.json", help="JSON report (default bench-results/reliability.json)")
    s.add_argument("--only", action="append", metavar="ROW",
                   help="run only this fault (repeatable): periods, stall, flood, poisoned-state, commands, state-dir, "
                   "period-flood, full-flood, sighup-burst, command-flood")
    s.set_defaults(func=cmd_reliability)

    s = sub.add_parser("hub", help="serve a loopback CAN hub (python-can-remote) on 127.0.0.1")
    s.add_argument("--port", type=int, default=None, help="TCP port on 127.0.0.1 (default: a free one)")
    s.set_defaults(func=cmd_hub)

    s = sub.add_parser("accuracy", help="single-injection accuracy vs the Cramér–Rao bound")
    s.add_argument("--scenario", choices=("matched", "mismatch", "both"), default="both", help="exact plant, the hysteresis plant, or both (default both)")
    s.add_argument("--sweep", choices=("all", "random", "near-edge", "high-noise", "spread", "spread-chain", "chain",
                                       "preload-off"),
                   default="all",
                   help="random truths over the ranges; N_u near the range edges; 0.3 V voltage noise; series "
                        "parts within ±10 %% (spread; spread-chain behind an unmodelled chain); a modelled chain; "
                        "a header preload force 10-15 %% off the true one (preload-off)")
    s.add_argument("--n", type=int, default=100, help="number of random injectors per sweep (default 100)")
    s.add_argument("--seed", type=int, default=1, help="seed of the random draws (default 1)")
    s.add_argument("--window-us", type=float, default=100.0, help="identification window in µs (default 100)")
    s.add_argument("--json-out", type=Path, default=DEFAULT_OUT / "accuracy.json", help="JSON report (default bench-results/accuracy.json)")
    s.set_defaults(func=cmd_accuracy)

    s = sub.add_parser("tracking", help="recursive estimator on injection sequences")
    s.add_argument("--scenario", choices=("all", *tracking_bench.TRACKING, "lot-life"), default="all",
                   help="scenario, or all of them (default all); lot-life: a lot of series injectors through their "
                   "life with learning on")
    s.add_argument("--plant", choices=("default", "matched", "mismatch", "both"), default="default",
                   help="default: every scenario matched, and " + ", ".join(tracking_bench.DEFAULT_MISMATCH)
                        + " on the hysteresis plant too")
    s.add_argument("--injections", type=int, default=None, help="override the scenario's length")
    s.add_argument("--preload", type=_preload_force, default=None, metavar="N",
                   help="lot-life at this one preload force (N, 28-300) instead of a wandering rail pressure")
    s.add_argument("--narrow-after", type=_injections, default=0, metavar="K",
                   help="lot-life learning with the self-calibration's narrow_after = K (default 0: off)")
    s.add_argument("--hysteresis", action="store_true",
                   help="lot-life with three parts whose hysteresis R(N_u) I cannot explain, learning with the element")
    _add_drive_argument(s, "the scenario's")
    s.add_argument("--seed", type=int, default=2, help="seed of the random draws (default 2)")
    s.add_argument("--json-out", type=Path, default=DEFAULT_OUT / "tracking.json", help="JSON report (default bench-results/tracking.json)")
    s.set_defaults(func=cmd_tracking)

    s = sub.add_parser("speed", help="update time of the recursive estimator")
    s.add_argument("--injections", type=int, default=300, help="warm updates to time (default 300)")
    _add_drive_argument(s, "standard")
    s.add_argument("--seed", type=int, default=4, help="seed of the random draws (default 4)")
    s.add_argument("--json-out", type=Path, default=DEFAULT_OUT / "speed.json", help="JSON report (default bench-results/speed.json)")
    s.set_defaults(func=cmd_speed)

    s = sub.add_parser("publish", help="the headline figures from the benches' JSON reports into the documentation's "
                       "one source (docs/figures.json)")
    s.add_argument("dirs", type=Path, nargs="+", help="directories holding bench reports (the JSON under bench-results), "
                   "one run of a bench each: several runs of a timing give its median and range")
    s.add_argument("--out", type=Path, default=Path("docs") / "figures.json",
                   help="the figures file, updated (default docs/figures.json, from the repository's root)")
    s.set_defaults(func=cmd_publish)

    s = sub.add_parser("calibration-traces", help="traces for eq. 25 (no valve, with s3) at several temperatures")
    s.add_argument("--out", type=Path, required=True, help="output directory")
    s.add_argument("--temps", type=float, nargs="+", default=[0.0, 25.0, 50.0, 75.0, 100.0], help="degC")
    s.add_argument("--noise-v", type=float, default=0.02, help="voltage noise (V, 1 sigma)")
    s.add_argument("--seed", type=int, default=5, help="seed of the random draws (default 5)")
    _add_drive_argument(s, "standard")
    s.set_defaults(func=cmd_calibration_traces)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code. SIGTERM/SIGHUP unwind like Ctrl-C: children are stopped."""
    from sim_bench.hardware.procs import install_stop_signals

    install_stop_signals()
    lean_service_imports(sys.argv[1:] if argv is None else argv, ("node", "hub"))
    return run_cli(build_parser(), argv)
