"""Command line of the estimator: ``python -m estimator SUBCOMMAND``."""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Callable

from estimator.errors import EstimatorError

log = logging.getLogger("estimator")


def cmd_params(args: argparse.Namespace) -> int:
    """Print the nominal parameters (Tables 1 and 2) and derived quantities."""
    from estimator.model.parameters import load_nominal

    p = load_nominal()
    for group in (p.psa, p.valve):
        print(f"[{type(group).__name__}]")
        for k, v in group.__dict__.items():
            print(f"  {k:<16} = {v:.6g}")
    nu = args.nu
    print(f"derived at N_u = {nu} N/V: C = {p.psa.capacitance_f(nu) * 1e6:.4f} µF, "
          f"R = {p.psa.resistance_ohm(nu):.4f} Ohm, b_p = {p.psa.damping_ns_per_m(nu):.2f} N*s/m")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with all subcommands."""
    p = argparse.ArgumentParser(prog="python -m estimator", description=__doc__)
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("params", help="print the nominal model parameters")
    s.add_argument("--nu", type=float, default=16.39, help="N_u in N/V for the derived values")
    s.set_defaults(func=cmd_params)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.debug else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except (EstimatorError, OSError) as exc:
        if args.debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2
