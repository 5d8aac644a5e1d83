"""Sphinx directives that generate reference pages from the project's own sources of truth.

``dbc-reference``
    Every message and signal of ``dbc/injector.dbc`` (identifier, frame, sender, unit, scale,
    range, value table, comment), read with cantools the way the daemon reads it.
``status-table``
    The estimate statuses: word (JSON, CSV), wire code (``EstimateState.Status``) and the DBC's own
    description of the code.
``bench-targets``
    The benches' headline targets, from :data:`sim_bench.benches.targets.TARGETS` (what each bench exits on).
"""

from __future__ import annotations

import argparse
import re
from typing import Any

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.application import Sphinx
from sphinx.util.docutils import SphinxDirective


def _cell(text: Any) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ") if text not in (None, "") else "–"


def _list_table(title: str, header: list[str], rows: list[list[str]], widths: str = "auto") -> list[str]:
    out = [f".. list-table:: {title}", "   :header-rows: 1", f"   :widths: {widths}", ""]
    for row in [header, *rows]:
        out.append(f"   * - {_cell(row[0])}")
        out.extend(f"     - {_cell(c)}" for c in row[1:])
    return [*out, ""]


def _parse(directive: SphinxDirective, lines: list[str]) -> list[nodes.Node]:
    container = nodes.container()
    directive.state.nested_parse(StringList(lines, source="injector_docs"), directive.content_offset, container)
    return container.children


def _database():
    import cantools

    from estimator.codec.database import default_dbc_path

    return cantools.database.load_file(default_dbc_path(), strict=True)


class DbcReference(SphinxDirective):
    """The CAN contract, one section per message."""

    def run(self) -> list[nodes.Node]:
        db = _database()
        lines: list[str] = []
        for msg in sorted(db.messages, key=lambda m: m.frame_id):
            frame = f"CAN FD, {msg.length} bytes" if msg.is_fd else f"classic, {msg.length} bytes"
            title = f"0x{msg.frame_id:03X} {msg.name}"
            lines += [title, "^" * len(title), "",
                      f"{_cell(msg.comment)}", "",
                      f"*Frame*: {frame}, 11-bit identifier; *sent by*: {', '.join(msg.senders) or '–'}.", ""]
            rows = []
            for sig in msg.signals:
                rng = f"{sig.minimum:g} … {sig.maximum:g}" if sig.minimum is not None and sig.maximum is not None else ""
                codes = "; ".join(f"{int(k)} = {v}" for k, v in (sig.choices or {}).items())
                bits = f"{sig.start}+{sig.length}{'s' if sig.is_signed else 'u'}"
                mux = " (multiplexer)" if sig.is_multiplexer else ""
                rows.append([f"``{sig.name}``{mux}", bits, f"{sig.scale:g}", sig.unit or "", rng,
                             (sig.comment or "") + (f" Values: {codes}." if codes else "")])
            lines += _list_table(f"{msg.name} signals", ["signal", "bits", "scale", "unit", "range", "meaning"],
                                 rows, "22 8 8 8 14 40")
        return _parse(self, lines)


class StatusTable(SphinxDirective):
    """Status words and wire codes, with the DBC's description."""

    def run(self) -> list[nodes.Node]:
        from estimator.codec.records import Codec
        from estimator.ident.status import Status

        codec = Codec(_database())   # the codes are the DBC's value table's, read by the codec
        rows = [[f"``{s.value}``", str(codec.status_code(s))] for s in Status]
        return _parse(self, _list_table("Estimate statuses", ["word (JSON, CSV, the DBC's value table)",
                                                              "code on the bus"], rows, "60 40"))


def _literal_backticks(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The parser with single backticks in help texts made RST literals (python-can's bus options
    quote command lines in Markdown style)."""
    for action in parser._actions:
        if action.help and "`" in action.help:
            text = re.sub(r"(?<!`)`([^`]+)`(?!`)", r"``\1``", action.help)
            action.help = re.sub(r"(?<!`)`(?!`)", r"\\`", text)   # an unpaired one stays a character
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _literal_backticks(sub)
    return parser


def estimator_parser() -> argparse.ArgumentParser:
    """``python -m estimator``'s parser, for sphinx-argparse."""
    from estimator.cli import build_parser

    return _literal_backticks(build_parser())


def sim_bench_parser() -> argparse.ArgumentParser:
    """``python -m sim_bench``'s parser, for sphinx-argparse."""
    from sim_bench.cli import build_parser

    return _literal_backticks(build_parser())


class BenchTargets(SphinxDirective):
    """Every bench's headline targets, as the benches judge them."""

    def run(self) -> list[nodes.Node]:
        from sim_bench.benches.targets import TARGETS

        rows = [[f"``{bench}``", t.what, f"``{t.figure}``", f"{t.op} {t.limit:g} {t.unit}".strip()]
                for bench, targets in TARGETS.items() for t in targets]
        return _parse(self, _list_table("Headline targets (sim_bench/benches/targets.py)", ["bench", "figure", "key", "target"],
                                        rows, "18 52 18 12"))


def setup(app: Sphinx) -> dict[str, Any]:
    app.add_directive("dbc-reference", DbcReference)
    app.add_directive("status-table", StatusTable)
    app.add_directive("bench-targets", BenchTargets)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
