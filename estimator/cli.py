"""Command line of the estimator: ``python -m estimator SUBCOMMAND``."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from estimator.choices import Norm, Robust
from estimator.cli_support import base_parser, lean_service_imports, run_cli
from estimator.errors import EstimatorError
from estimator.units import MEGA, PER_MICRO, S_PER_US, US_PER_S

if TYPE_CHECKING:
    from estimator.pipeline.config import EstimatorConfig

log = logging.getLogger("estimator")


def _config(args: argparse.Namespace):
    from estimator.ident.config import IdentConfig

    kw = {}
    if getattr(args, "window_us", None) is not None:
        kw["window_s"] = args.window_us * S_PER_US
    if getattr(args, "robust", None):
        kw["robust"] = args.robust
    if getattr(args, "norm", None):
        kw["norm"] = args.norm
    try:
        return IdentConfig(**kw)
    except ValueError as exc:
        raise EstimatorError(str(exc)) from None


def _trace(path: Path, args: argparse.Namespace | None = None):
    """A trace: CSV, or MDF4 (.mf4/.mdf) with the channel options."""
    from estimator.io.mdf import read_any_trace

    meta = {k: str(v) for k, v in (("preload_force_n", getattr(args, "preload_n", None)),
                                   ("temperature_c", getattr(args, "temperature_c", None))) if v is not None}
    period = getattr(args, "sample_period_us", None)
    return read_any_trace(path, getattr(args, "current_channel", None), getattr(args, "voltage_channel", None),
                          getattr(args, "s3_channel", None), period * S_PER_US if period else None, meta)


def _load(path: Path, args: argparse.Namespace | None = None):
    from estimator.io.traces import injection_from_trace

    return injection_from_trace(_trace(path, args))


def _params(args: argparse.Namespace):
    """The model parameters: ``--params FILE`` (what ``calibrate --out`` writes) or Tables 1-2."""
    from estimator.model.parameters import load_parameters

    return load_parameters(getattr(args, "params", None))


def _simulator(args: argparse.Namespace, dt_s: float):
    from estimator.model.fast_sim import FastSimulator

    return FastSimulator(_params(args), dt_s=dt_s)


def cmd_params(args: argparse.Namespace) -> int:
    """Print the nominal parameters (Tables 1 and 2) and derived quantities."""
    from estimator.model.parameters import load_nominal

    p = load_nominal()
    for group in (p.psa, p.valve):
        print(f"[{type(group).__name__}]")
        for k, v in group.__dict__.items():
            print(f"  {k:<16} = {v:.6g}")
    nu = args.nu
    print(f"derived at N_u = {nu} N/V: C = {p.psa.capacitance_f(nu) * PER_MICRO:.4f} µF, "
          f"R = {p.psa.resistance_ohm(nu):.4f} Ohm, b_p = {p.psa.damping_ns_per_m(nu):.2f} N*s/m")
    return 0


def cmd_identify(args: argparse.Namespace) -> int:
    """Identify N_u and L_h of one trace (eq. 28)."""
    from estimator.errors import TraceError
    from estimator.ident.estimate import rejected
    from estimator.ident.fit.idle_stroke import identify

    config = _config(args)
    params = _params(args)
    try:
        inj = _load(args.trace, args)
    except TraceError as exc:
        if "cannot read" in str(exc):
            raise
        est = rejected(str(exc))
    else:
        from estimator.model.fast_sim import FastSimulator

        sim = FastSimulator(params, dt_s=inj.dt_s) if inj.dt_s > 0 else None
        est = identify(inj, sim, config=config)
    d = est.to_dict()
    if args.json:
        print(json.dumps(d))
    else:
        if est.status == "rejected":
            print(f"{args.trace}: rejected: {est.message}")
        else:
            print(f"{args.trace}: N_u = {d['nu_n_per_v']:.4f} ± {d['sigma_nu_n_per_v']:.4f} N/V, "
                  f"L_h = {d['lh_um']:.3f} ± {d['sigma_lh_um']:.3f} µm, cost {d['cost_uvs']:.2f} µV·s, "
                  f"contact {d['t_contact_us']} µs, opening {d['t_open_us']} µs, stroke {d['stroke_um']} µm, "
                  f"status {est.status}{' (robust: model error detected)' if est.robust else ''}")
    return 1 if est.status == "rejected" else 0


def cmd_track(args: argparse.Namespace) -> int:
    """Run the recursive estimator over trace files in order; one JSON line per injection."""
    from estimator.drive.correction import correction_after, estimate_unchecked
    from estimator.errors import TraceError
    from estimator.ident.config import TrackerConfig
    from estimator.ident.estimate import rejected
    from estimator.ident.learning.selfcal import SelfCalConfig
    from estimator.ident.status import Status
    from estimator.pipeline.build import build_compensator, build_tracker
    from estimator.pipeline.config import EstimatorConfig
    from estimator.pipeline.processor import Published

    selfcal = SelfCalConfig() if args.self_calibrate else None
    cfg = EstimatorConfig(params=getattr(args, "params", None), tracker=TrackerConfig(ident=_config(args)),
                          self_calibration=selfcal)
    tracker = build_tracker(cfg)
    compensator = build_compensator(cfg)
    bad = 0
    for path in args.traces:
        try:
            inj = _load(path, args)
        except TraceError as exc:   # unreadable or not a trace: reported in its line, the batch goes on
            bad += 1
            log.warning("%s", exc)
            print(json.dumps({"file": str(path), "injector_id": None, "status": Status.REJECTED.value,
                              "reason": str(exc), "raw": rejected(str(exc)).to_dict()}), flush=True)
            continue
        res = tracker.update(inj) if compensator is None else estimate_unchecked(compensator, tracker, inj)
        # the drive that makes this injector's valve open as the nominal one does
        pub = Published(inj.injector_id, inj.counter, inj.time_s, res,
                        learning=tracker.calibration.get(inj.injector_id) if selfcal is not None else None,
                        correction=correction_after(compensator, tracker, inj, res) if compensator else None)
        print(json.dumps({"file": str(path), **pub.to_dict()}), flush=True)
    if bad:
        print(f"error: {bad} of {len(args.traces)} file(s) could not be read (see their lines)", file=sys.stderr)
    return 1 if bad else 0


def cmd_calibrate_electrical(args: argparse.Namespace) -> int:
    """The injector's structural parameters from current and voltage alone (no displacement)."""
    from estimator.ident.learning.electrical import confirmed_out_of_tolerance
    from estimator.ident.learning.element import calibrate_with_hysteresis_if_needed
    from estimator.io.mdf import read_injections

    meta = {k: str(v) for k, v in (("preload_force_n", args.preload_n), ("temperature_c", args.temperature_c))
            if v is not None}
    found = read_injections(args.traces, args.current_channel, args.voltage_channel,
                            args.sample_period_us * S_PER_US if args.sample_period_us else None, meta, args.serial)
    for line in found.unreadable + found.unusable:   # a corrupt trace is named and skipped, the others calibrate
        print(f"skipped {line}", file=sys.stderr)
    injections, bad = found.injections, len(found.unreadable)
    window_s = (200.0 if args.window_us is None else args.window_us) * S_PER_US
    base = _params(args)
    try:
        res = calibrate_with_hysteresis_if_needed(injections, base, hysteresis=args.hysteresis,
                                                  tolerance=args.tolerance, window_s=window_s)
    except ValueError as exc:
        raise EstimatorError(str(exc)) from None
    header = (f"parameters calibrated electrically (python -m estimator calibrate --electrical) from "
              f"{len(injections)} injections;\nRMS voltage residual {res.rms_before_v * 1e3:.1f} mV before, "
              f"{res.rms_after_v * 1e3:.1f} mV after; SI units.")
    flagged = confirmed_out_of_tolerance(injections, base, res, args.part_tolerance, tolerance=args.tolerance,
                                         window_s=window_s) if res.adequate else []
    if res.adequate:
        toml = res.params.to_toml(header)
        if args.out:
            args.out.write_text(toml)
            print(f"wrote {args.out}")
        else:
            print(toml)
    print(res.report())
    if flagged:
        print(f"out_of_tolerance: {', '.join(flagged)} beyond ±{100 * args.part_tolerance:g} % of the tables by "
              f"more than 3 sigma (a part to reject)")
    if args.json:
        args.json.write_text(json.dumps(res.to_dict() | {"out_of_tolerance": flagged,
                                                         "part_tolerance": args.part_tolerance}, indent=1))
    if not res.adequate:
        print(f"error: calibration refused: {res.refusal or 'the calibrated model does not explain the batch'}; "
              "no parameter file written", file=sys.stderr)
    if bad:
        print(f"error: {bad} of {len(args.traces)} file(s) could not be read (skipped, named above)", file=sys.stderr)
    return 0 if res.adequate and not bad else 1


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Calibrate k_p, k_s, R_b and the temperature laws from traces with s3 (eq. 25)."""
    if args.electrical:
        return cmd_calibrate_electrical(args)
    from estimator.ident.learning.calibration import CalibrationTrace, calibrate, report, to_toml
    from estimator.io.traces import injection_from_trace

    traces = []
    for path in args.traces:
        tr = _trace(path, args)
        temp = tr.meta_float("temperature_c")
        if temp is None:
            raise EstimatorError(f"{path}: calibration traces need '# temperature_c=...'")
        traces.append(CalibrationTrace(injection_from_trace(tr), tr.column("s3_m"), temp))
    try:
        res = calibrate(traces, _params(args), window_s=(170.0 if args.window_us is None else args.window_us) * S_PER_US, gamma_v_per_m=args.gamma)
    except ValueError as exc:
        raise EstimatorError(str(exc)) from None
    toml = to_toml(res, _params(args))
    if args.out:
        args.out.write_text(toml)
        print(f"wrote {args.out}")
    else:
        print(toml)
    print(report(res))
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    """Figures 7/13 (voltage fit and error) and 14 (cost contour) for one trace."""
    from estimator.plots.identification import plot_identification

    config = _config(args)
    if not 3 <= args.grid <= 201:
        raise EstimatorError(f"--grid {args.grid}: the contour needs 3..201 points per axis")
    inj = _load(args.trace, args)
    if inj.problem():
        raise EstimatorError(f"{args.trace}: {inj.problem()}")
    paths = plot_identification(inj, args.out, config, args.grid, _simulator(args, inj.dt_s))
    for p in paths:
        print(f"wrote {p}")
    return 0


def offline_config(path: Path | None, **overrides: Any) -> EstimatorConfig:
    """The estimator's configuration for an offline command: the daemon's file is accepted as it is
    (every key checked), and only the estimator's part is used."""
    from estimator.service.config import DaemonConfig

    return DaemonConfig.load(path, **overrides).estimator_config()


def cmd_run(args: argparse.Namespace) -> int:
    """Run the estimator daemon on a CAN bus."""
    from estimator.service.bus import overrides_from_args
    from estimator.service.config import DaemonConfig
    from estimator.service.launch import run_daemon

    overrides = dict(state_dir=args.state_dir, dbc=args.dbc, params=args.params, **overrides_from_args(args))
    cfg = DaemonConfig.load(args.config, **overrides)
    if not args.debug:
        logging.getLogger().setLevel(cfg.log_level_number)
    loader = (lambda: DaemonConfig.load(args.config, **overrides)) if args.config is not None else None
    return run_daemon(cfg, loader)


def cmd_replay(args: argparse.Namespace) -> int:
    """Replay a capture through the daemon's pipeline, offline."""
    from estimator.pipeline.replay import replay

    cfg = offline_config(args.config, dbc=args.dbc, params=args.params)
    if not args.capture.exists():
        raise EstimatorError(f"capture {args.capture} does not exist")
    # the outputs are closed after the replay (below); "-" is standard output
    out_json = open(args.json, "w") if args.json and str(args.json) != "-" else (sys.stdout if args.json else None)  # noqa: SIM115
    out_csv = open(args.csv, "w", newline="") if args.csv and str(args.csv) != "-" else (  # noqa: SIM115
        sys.stdout if args.csv else None)
    try:
        res = replay(args.capture, cfg, args.out, out_json, out_csv=out_csv)
    except (ValueError, can_errors()) as exc:
        raise EstimatorError(f"cannot replay {args.capture}: {exc}") from None
    finally:
        for f in (out_json, out_csv):
            if f not in (None, sys.stdout):
                f.close()
    c = res.counters
    print(f"replayed {res.frames_in} frames: {res.published} injections estimated; rejected crc {c.rejected_crc}, "
          f"missing {c.rejected_missing}, timeout {c.rejected_timeout}, invalid {c.rejected_invalid}, outlier "
          f"{c.rejected_outlier}; malformed frames {c.frames_malformed}", file=sys.stderr)
    if res.bad_line_count:
        for no, problem in res.bad_lines[:5]:
            print(f"{args.capture}:{no}: skipped, not a frame ({problem})", file=sys.stderr)
        print(f"error: {res.bad_line_count} line(s) of {args.capture} could not be read and were skipped "
              f"(first at line {res.bad_lines[0][0]}); everything else was replayed", file=sys.stderr)
        return 1
    return 0


def can_errors() -> type[Exception]:
    """python-can's base error (imported lazily: only the service layer needs python-can)."""
    import can

    error: type[Exception] = can.CanError
    return error


def cmd_check_dbc(args: argparse.Namespace) -> int:
    """Validate the DBC against the contract."""
    from estimator.codec.database import default_dbc_path
    from estimator.codec.records import Codec, load_database

    path = args.dbc or default_dbc_path()
    db = load_database(path)
    codec = Codec(db)
    attrs = getattr(getattr(db, "dbc", None), "attributes", {})
    rates = "/".join(f"{attrs[k].value / MEGA:g}" for k in ("Baudrate", "BaudrateCANFD") if k in attrs)
    print(f"{path}: ok - {len(db.messages)} messages, CAN FD {rates} Mbit/s, {codec.layout.per_block} samples per "
          f"InjectionSamples frame ({codec.layout.current_scale * 1e3:g} mA, {codec.layout.voltage_scale * 1e3:g} mV)")
    return 0


def cmd_plot_capture(args: argparse.Namespace) -> int:
    """N_u, L_h, opening time over time from a capture, one line per injector."""
    from estimator.plots.capture import plot_capture

    if not args.capture.exists():
        raise EstimatorError(f"capture {args.capture} does not exist")
    try:
        path = plot_capture(args.capture, args.out)
    except ValueError as exc:
        raise EstimatorError(f"cannot read {args.capture}: {exc}") from None
    print(f"wrote {path}")
    return 0


def cmd_plot_estimates(args: argparse.Namespace) -> int:
    """L_h and N_u with their ±2σ bands over each injector's injections, from the estimator's rows."""
    from estimator.plots.estimates import plot_estimates, read_rows

    if not args.rows.exists():
        raise EstimatorError(f"rows {args.rows} do not exist")
    path = plot_estimates(read_rows(args.rows), args.out, title=f"{args.rows.name}: filtered estimates, ±2σ; x: not ok")
    print(f"wrote {path}")
    return 0


def cmd_fleet(args: argparse.Namespace) -> int:
    """Many captures and traces on a Dask cluster: one row per injection, summary, lot report."""
    import os

    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "debug" if args.debug else "warning")
    try:
        from estimator.fleet.run import run_fleet
    except ImportError as exc:
        raise EstimatorError(f"the fleet command needs dask[distributed] and pyarrow: pip install '.[fleet]' ({exc})") \
            from None
    cfg = offline_config(args.config, params=args.params)
    opts = {k: getattr(args, k) for k in ("current_channel", "voltage_channel") if getattr(args, k, None)}
    if args.sample_period_us:
        opts["sample_period_s"] = args.sample_period_us * S_PER_US
    if args.calibrate:
        from estimator.fleet.calibrate import format_report, run_lot_calibration

        if args.out.suffix.lower() in (".parquet", ".csv"):
            raise EstimatorError(f"--out {args.out}: with --calibrate, a directory for the parameter files")
        cal = run_lot_calibration(args.inputs, args.out, args.calibrate, cfg.params, args.tolerance, args.workers,
                                  args.scheduler, opts)
        print(format_report(cal))
        print("\n".join(f"wrote {f}" for f in cal.files))
        return 1 if cal.refused or cal.missing or any(r.get("skipped") for r in cal.rows) else 0
    res = run_fleet(args.inputs, args.out, cfg, args.workers, args.scheduler, opts, progress=sys.stderr.isatty())
    print(format_fleet(res))
    return 1 if res.errors or res.missing else 0


def format_fleet(res) -> str:
    """The report's first line, the lot line and where the files are."""
    from estimator.fleet.run import format_report

    lines = format_report(res).splitlines()
    keep = [lines[0]] + [x for x in lines if x.startswith(("  lot:", "  error:", "matched nothing"))]
    return "\n".join(keep + [f"wrote {f}" for f in res.files])


def cmd_drive_table(args: argparse.Namespace) -> int:
    """The amplifier's standard drive as a current table, from traces recorded at it (scale 1, offset 0)."""
    import numpy as np

    from estimator.drive.standard import from_recordings
    from estimator.errors import TraceError
    from estimator.io.traces import write_trace
    from estimator.model.drive import same_grid

    currents, periods, bad = [], [], 0
    for path in args.traces:
        try:
            inj = _load(path, args)
        except TraceError as exc:   # the batch goes on past a bad file
            bad += 1
            print(f"{path}: {exc}", file=sys.stderr)
            continue
        currents.append(inj.current_a)
        periods.append(inj.dt_s)
    if not currents:
        raise EstimatorError("no trace could be read")
    if not all(same_grid(p, periods[0]) for p in periods):
        raise EstimatorError("the traces have different sample periods; give traces of one amplifier setting")
    try:
        drive, odd = from_recordings(currents, periods[0], args.out.name, args.tolerance)
    except ValueError as exc:
        raise EstimatorError(str(exc)) from None
    for i in odd:
        print(f"{args.traces[i]}: its current disagrees with the others' (left out)", file=sys.stderr)
    t = np.arange(drive.current_a.size) * drive.dt_s
    write_trace(args.out, {"t_s": t, "current_A": drive.current_a},
                {"what": "amplifier standard drive", "recordings": len(currents) - len(odd)})
    print(f"wrote {args.out}: {len(currents) - len(odd)} recording(s), {t[-1] * US_PER_S:.1f} µs, peak "
          f"{float(np.max(np.abs(drive.current_a))):.3f} A; use it as [estimator.drive_correction] "
          f"amplifier_drive = \"{args.out}\"")
    return 1 if bad or odd else 0


def cmd_a2l(args: argparse.Namespace) -> int:
    """Write the A2L of the daemon's XCP slave (what GET_ID serves) for a calibration tool: the slave's
    address from ``[estimator.xcp]`` of ``--config`` (its defaults without one)."""
    from estimator import __version__
    from estimator.codec.records import load_database
    from estimator.service.config import DaemonConfig, XcpConfig
    from estimator.service.xcp.a2l import NAME, a2l_bytes

    xcp = DaemonConfig.load(args.config).xcp or XcpConfig()
    out = args.out or Path(f"{NAME}.a2l")
    data = a2l_bytes(load_database(args.dbc) if args.dbc else load_database(), __version__, (xcp.host, xcp.port),
                     xcp.writes)
    try:
        out.write_bytes(data)
    except OSError as exc:
        raise SystemExit(f"error: cannot write {out}: {exc.strerror or exc}") from None
    print(f"{out}: A2L for the XCP slave ([estimator.xcp]), {len(data)} bytes")
    return 0


def cmd_dbc_path(args: argparse.Namespace) -> int:
    """Print the path of the packaged DBC (for cantools decode/monitor/plot)."""
    from estimator.codec.database import default_dbc_path

    print(default_dbc_path())
    return 0


def cmd_compile(args: argparse.Namespace) -> int:
    """Fill numba's cache for this version on two cores (``make`` runs it before demo and test)."""
    from estimator.pipeline.precompile import precompile

    seconds = precompile(parallel=not args.serial, log=lambda m: print(m, file=sys.stderr))
    if seconds == 0.0 and not args.quiet:
        print("compiled kernels already cached", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with all subcommands."""
    p, sub = base_parser("python -m estimator", __doc__)

    def params_opt(s: argparse.ArgumentParser) -> None:
        s.add_argument("--params", type=Path, default=None,
                       help="model parameter TOML (what 'calibrate --out' writes; default Tables 1-2)")

    def mdf_opts(s: argparse.ArgumentParser, s3: bool = False) -> None:
        g = s.add_argument_group("MDF4 traces (.mf4/.mdf; resampled to a uniform period, see the user guide's trace formats)")
        g.add_argument("--current-channel", help="channel with the amplifier current (A)")
        g.add_argument("--voltage-channel", help="channel with the actuator voltage (V)")
        if s3:
            g.add_argument("--s3-channel", help="channel with the PSA displacement s3 (m), for calibrate")
        g.add_argument("--sample-period-us", type=float, help="resampling period (default: the current channel's "
                       "median interval)")
        g.add_argument("--preload-n", type=float, help="valve preload F_open in N (default: MDF comment "
                       "preload_force_n=, else 28)")
        g.add_argument("--temperature-c", type=float, help="fuel temperature in degC (default: MDF comment)")

    def ident_opts(s: argparse.ArgumentParser) -> None:
        s.add_argument("--window-us", type=float, default=None, help="cost window 0..t1 in µs (default 100)")
        s.add_argument("--robust", choices=Robust.words(), default=None,
                       help="model-error handling (default auto: likelihood-ratio test)")
        s.add_argument("--norm", choices=Norm.words(), default=None, help="search criterion (default l2)")
        params_opt(s)
        mdf_opts(s)

    s = sub.add_parser("params", help="print the nominal model parameters")
    s.add_argument("--nu", type=float, default=16.39, help="N_u in N/V for the derived values")
    s.set_defaults(func=cmd_params)

    s = sub.add_parser("identify", help="identify N_u and L_h from one trace CSV (eq. 28)")
    s.add_argument("trace", type=Path, help="trace: CSV or MDF4 (.mf4, .mdf)")
    s.add_argument("--json", action="store_true", help="print one JSON object")
    ident_opts(s)
    s.set_defaults(func=cmd_identify)

    s = sub.add_parser("track", help="recursive estimator over trace CSVs, one JSON line each")
    s.add_argument("traces", type=Path, nargs="+", help="traces in order: CSV or MDF4")
    s.add_argument("--self-calibrate", action=argparse.BooleanOptionalAction, default=True,
                   help="learning (on by default): an injector the model cannot explain learns its own "
                   "structural parameters from its injections (a window spanning its preload forces; adopted "
                   "when they explain held-out injections better), and is learned again when its model stops "
                   "explaining it; --no-self-calibrate turns it off")
    ident_opts(s)
    s.set_defaults(func=cmd_track)

    s = sub.add_parser("calibrate", help="calibrate the model's parameters: from traces with s3_m (eq. 25), or "
                       "--electrical from current and voltage alone")
    s.add_argument("traces", type=Path, nargs="+", help="traces with the stack displacement at two or more "
                   "temperatures; with --electrical, any injections of one injector (or lot) at several preload forces")
    s.add_argument("--electrical", action="store_true", help="fit the 13 structural parameters and each "
                   "injection's N_u and L_h to the voltage (no displacement channel needed)")
    s.add_argument("--serial", default=None, help="--electrical: only the traces of this injector (metadata "
                   "serial= or injector_key=); default: all traces, one structure shared by all (a lot)")
    s.add_argument("--hysteresis", action="store_true", help="--electrical: where R(N_u)·I cannot explain the "
                   "batch, calibrate it again with a hysteresis element in its place, on two grids of plays that must "
                   "both explain it (their disagreement is written into [calibration])")
    s.add_argument("--tolerance", type=float, default=0.10, help="--electrical: relative standard deviation of "
                   "the prior on each structural parameter (default 0.10)")
    s.add_argument("--part-tolerance", type=float, default=0.10, help="--electrical: the part's datasheet tolerance "
                   "(relative); a parameter beyond it by more than 3 sigma is reported out_of_tolerance (default 0.10)")
    s.add_argument("--json", type=Path, default=None, help="--electrical: write the result (parameters, sigma, "
                   "out_of_tolerance, adequacy) as JSON here")
    s.add_argument("--window-us", type=float, default=None, help="cost window in µs (default 170; --electrical 200)")
    s.add_argument("--gamma", type=float, default=1e6, help="weight of the s3 error in V/m (default 1e6)")
    s.add_argument("--out", type=Path, help="write the TOML here (default: print it)")
    s.add_argument("--params", type=Path, default=None, help="starting parameter TOML (default Tables 1-2)")
    mdf_opts(s, s3=True)
    s.set_defaults(func=cmd_calibrate)

    s = sub.add_parser("run", help="run the estimator daemon on a CAN bus (any python-can interface)")
    from estimator.service.bus import add_arguments as add_bus_arguments

    add_bus_arguments(s)
    s.add_argument("--config", type=Path, help="TOML file with an [estimator] table")
    s.add_argument("--state-dir", type=Path, default=None, help="where per-injector state persists "
                   "(default $STATE_DIRECTORY, else not persisted)")
    s.add_argument("--dbc", type=Path, default=None, help="CAN database (default dbc/injector.dbc)")
    params_opt(s)
    s.set_defaults(func=cmd_run)

    s = sub.add_parser("replay", help="run a capture (.log candump -L, .asc, .blf, .trc, .csv, .mf4) through the pipeline")
    s.add_argument("capture", type=Path, help="capture: .log (candump -L), .asc, .blf, .trc, .csv or .mf4")
    s.add_argument("--out", type=Path, help="write the output frames; format by suffix: .log (candump -L), .asc, .blf, "
                   ".csv, .mf4")
    s.add_argument("--json", type=Path, help="write one JSON line per injection ('-' for stdout)")
    s.add_argument("--csv", type=Path, help="write one CSV row per injection: time, injector, counter, status, "
                   "filtered and raw N_u/L_h, sigmas, prediction ('-' for stdout)")
    s.add_argument("--config", type=Path, help="TOML file with an [estimator] table (the daemon's settings)")
    s.add_argument("--dbc", type=Path, default=None, help="CAN database (default: the packaged dbc/injector.dbc)")
    params_opt(s)
    s.set_defaults(func=cmd_replay)

    s = sub.add_parser("plot-capture", help="PNG: N_u, L_h, opening time over time from a capture, per injector")
    s.add_argument("capture", type=Path, help="any python-can capture (.log, .asc, .blf, .trc, .csv, .mf4)")
    s.add_argument("--out", type=Path, default=Path("capture.png"), help="output PNG (default capture.png)")
    s.set_defaults(func=cmd_plot_capture)

    s = sub.add_parser("plot-estimates", help="PNG: L_h and N_u with ±2σ per injector from the rows replay --csv or "
                       "the fleet wrote")
    s.add_argument("rows", type=Path, help="a CSV of the estimator's rows (replay --csv, fleet --out rows.csv)")
    s.add_argument("--out", type=Path, default=Path("estimates.png"), help="output PNG (default estimates.png)")
    s.set_defaults(func=cmd_plot_estimates)

    s = sub.add_parser("fleet", help="many captures/traces on Dask: one row per injection, summary, lot report")
    s.add_argument("inputs", nargs="+", help="files, directories (recursive) and glob patterns (quote them)")
    s.add_argument("--out", type=Path, required=True, help="RESULTS.parquet or RESULTS.csv (companions beside it); "
                   "with --calibrate a directory")
    s.add_argument("--calibrate", choices=("per-injector", "per-lot"), default=None,
                   help="instead of estimating: electrical calibrations as Dask tasks, per injector (traces grouped by "
                        "serial) or one for the lot; writes each parameter file, calibration.csv and the lot's "
                        "structural spread (structure-spread.txt/.png) into --out")
    s.add_argument("--tolerance", type=float, default=0.10,
                   help="--calibrate: relative standard deviation of each structural parameter's prior (default 0.10)")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, default=None, help="local cluster processes (default: the cores)")
    g.add_argument("--scheduler", default=None, help="attach to a running cluster, tcp://HOST:PORT")
    s.add_argument("--config", type=Path, help="estimator.toml (the same keys as the daemon)")
    params_opt(s)
    mdf_opts(s)
    s.set_defaults(func=cmd_fleet)

    s = sub.add_parser("drive-table", help="the amplifier's standard drive as a current table, from traces recorded "
                       "at it: [estimator.drive_correction] amplifier_drive")
    s.add_argument("traces", type=Path, nargs="+", help="traces (CSV or MDF4) of injections driven with the "
                   "standard drive, from the start of charging, long enough to hold the whole charge")
    s.add_argument("--out", type=Path, required=True, help="the current table to write (CSV t_s, current_A)")
    s.add_argument("--tolerance", type=float, default=0.10,
                   help="relative RMS a recording may differ from the others' median (default 0.10)")
    mdf_opts(s)
    s.set_defaults(func=cmd_drive_table)

    s = sub.add_parser("dbc-path", help="print where the packaged DBC is: cantools monitor $(injector-estimator dbc-path)")
    s.set_defaults(func=cmd_dbc_path)

    s = sub.add_parser("compile", help="compile the kernels into numba's cache now, on two cores (once per version)")
    s.add_argument("--serial", action="store_true", help="in this process only")
    s.add_argument("--quiet", action="store_true", help="say nothing when the cache is complete already")
    s.set_defaults(func=cmd_compile)

    s = sub.add_parser("a2l", help="write the A2L of the daemon's XCP slave (measurements from the DBC, "
                                   "characteristics from the configuration)")
    s.add_argument("--out", type=Path, default=None, help="output file (default ./injector_estimator.a2l)")
    s.add_argument("--dbc", type=Path, default=None, help="CAN database (default: the packaged dbc/injector.dbc)")
    s.add_argument("--config", type=Path, default=None,
                   help="the daemon's configuration: the slave's host and port from [estimator.xcp]")
    s.set_defaults(func=cmd_a2l)

    s = sub.add_parser("check-dbc", help="validate the DBC against the contract")
    s.add_argument("--dbc", type=Path, default=None, help="CAN database (default: the packaged dbc/injector.dbc)")
    s.set_defaults(func=cmd_check_dbc)

    s = sub.add_parser("plot", help="PNG figures: voltage fit and error, cost contour")
    s.add_argument("trace", type=Path, help="trace: CSV or MDF4")
    s.add_argument("--out", type=Path, required=True, help="output directory")
    s.add_argument("--grid", type=int, default=41, help="contour grid points per axis (default 41)")
    ident_opts(s)
    s.set_defaults(func=cmd_plot)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    lean_service_imports(sys.argv[1:] if argv is None else argv, ("run",))
    return run_cli(build_parser(), argv)
