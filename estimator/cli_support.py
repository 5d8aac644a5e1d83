"""The entry-point pattern both command lines share: logging set up here, one readable error line."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable

from estimator.errors import EstimatorError


def subcommand(argv: list[str]) -> str | None:
    """The first positional argument (the subcommand), skipping global options and --log-format's value."""
    skip = False
    for a in argv:
        if skip:
            skip = False
        elif a == "--log-format":
            skip = True
        elif not a.startswith("-"):
            return a
    return None


def lean_service_imports(argv: list[str], services: tuple[str, ...]) -> None:
    """For the long-running services (daemon, node, hub): keep python-can from importing asammdf.

    python-can imports asammdf (and with it pandas and pyarrow: +77 MB resident, +0.4 s start-up,
    measured) as soon as it is installed, for its .mf4 logger. The services never read or write MDF4,
    so they run without it; every other command keeps it.
    """
    if subcommand(argv) in services and "asammdf" not in sys.modules:
        sys.modules["asammdf"] = None   # type: ignore[assignment]  # import asammdf -> ImportError


def version_line() -> str:
    """``--version``: this package and the libraries whose versions matter for a bug report."""
    from importlib.metadata import PackageNotFoundError, version

    import estimator

    parts = [f"piezo-injector-estimator {estimator.__version__}"]
    for dist in ("python-can", "cantools", "numpy", "scipy", "numba"):
        try:
            parts.append(f"{dist} {version(dist)}")
        except PackageNotFoundError:
            parts.append(f"{dist} missing")
    return ", ".join(parts) + f" (Python {sys.version.split()[0]})"


def base_parser(prog: str, description: str | None):
    """The parser every command line starts from (--debug, --version, --log-format) and its subparsers."""
    p = argparse.ArgumentParser(prog=prog, description=description,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    p.add_argument("--version", action="version", version=version_line())
    p.add_argument("--log-format", choices=("auto", "text", "journal", "json"), default="auto",
                   help="log lines on stderr: auto (journal priorities <N> under systemd, else text), text, "
                        "journal or json (one object per line)")
    return p, p.add_subparsers(dest="command", required=True)


def run_cli(parser: argparse.ArgumentParser, argv: list[str] | None) -> int:
    """Parse, configure logging (``--debug`` for tracebacks), run ``args.func``; exit code 2 on errors."""
    args = parser.parse_args(argv)
    from estimator.logfmt import configure

    configure(logging.DEBUG if args.debug else logging.INFO, getattr(args, "log_format", "auto"))
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except KeyboardInterrupt:   # Ctrl-C (and, in sim_bench, SIGTERM/SIGHUP): children were stopped on the way out
        print("interrupted", file=sys.stderr)
        return 130
    except (EstimatorError, OSError) as exc:
        if args.debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2
