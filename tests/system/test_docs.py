"""The documentation keeps up with the code: every command, option, configuration key and status is
documented, the README stays short, and neither speaks of how the software was developed."""

from __future__ import annotations

import argparse
import dataclasses
import re
from pathlib import Path

import pytest

from estimator.cli import build_parser as estimator_parser
from estimator.ident.status import Status
from estimator.model.chain import MeasurementChain
from estimator.service.config import DEPRECATED, SECTIONS, DaemonConfig
from sim_bench.cli import build_parser as sim_bench_parser

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
README = ROOT / "README.md"
NUMBER = re.compile(r"\d[\d,]*(?:\.\d+)?")   # a figure as the documentation writes it (214,700; 0.211)


def _user_docs() -> str:
    return "\n".join(p.read_text(encoding="utf-8") for p in [README, *sorted(DOCS.rglob("*.md"))]
                     if "_build" not in p.parts)


def _walk(parser: argparse.ArgumentParser, path: str):
    """(command path, subcommand help or None, option actions) of every (sub)command."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {c.dest: c.help for c in action._choices_actions}
            for name, sub in action.choices.items():
                yield f"{path} {name}", name, helps.get(name), sub
                yield from _walk(sub, f"{path} {name}")


COMMANDS = [*_walk(estimator_parser(), "estimator"), *_walk(sim_bench_parser(), "sim_bench")]


@pytest.mark.parametrize("path,name,help_text,sub", COMMANDS, ids=[c[0] for c in COMMANDS])
def test_every_subcommand_and_option_has_help_and_a_place_in_the_guide(path, name, help_text, sub):
    """The CLI reference is generated from the parsers: what it shows is their help texts."""
    assert help_text, f"{path}: subcommand without help"
    missing = [a.option_strings or a.dest for a in sub._actions
               if not a.help and not isinstance(a, argparse._HelpAction)]
    assert not missing, f"{path}: options without help: {missing}"
    assert re.search(rf"-m (estimator|sim_bench) {re.escape(name)}\b|injector-(estimator|sim) {re.escape(name)}\b",
                     _user_docs()), f"{path} appears nowhere in the README or the user guide"


def test_every_config_key_is_documented():
    """Every daemon key is in the shipped, included estimator.toml and in the allowed-values table;
    every measurement-chain key in the configuration page."""
    toml = (ROOT / "systemd" / "estimator.toml").read_text(encoding="utf-8")
    page = (DOCS / "guide" / "configuration.md").read_text(encoding="utf-8")
    assert "literalinclude:: ../../systemd/estimator.toml" in page or "{literalinclude} ../../systemd/estimator.toml" in page
    from estimator.ident.config import IdentConfig, TrackerConfig
    from estimator.ident.learning.selfcal import SelfCalConfig
    for f in dataclasses.fields(DaemonConfig):
        if f.name in SECTIONS:
            continue
        assert re.search(rf"^#?\s*(\[estimator\.)?{f.name}\b", toml, re.M), f"{f.name} not in systemd/estimator.toml"
        assert f"`{f.name}`" in page, f"{f.name} not in docs/guide/configuration.md"
    for section, cls in (("ident", IdentConfig), ("tracker", TrackerConfig), ("self_calibration", SelfCalConfig)):
        assert f"[estimator.{section}]" in toml and f"`[estimator.{section}]`" in page, section
        for f in dataclasses.fields(cls):
            if f.name != "ident":
                assert f"| `{f.name}` |" in page, f"[estimator.{section}] {f.name} not in docs/guide/configuration.md"
    assert "| `mode` |" in page
    for key in DEPRECATED:
        assert f"`{key}`" in page, f"the deprecated key {key} is not named in docs/guide/configuration.md"
    for f in dataclasses.fields(MeasurementChain):
        assert f.name in page, f"[chain] {f.name} not in docs/guide/configuration.md"


def test_every_status_is_explained():
    page = (DOCS / "how" / "status.md").read_text(encoding="utf-8")
    readme = README.read_text(encoding="utf-8")
    from estimator.codec.records import Codec
    codec = Codec()
    for s in Status:
        assert f"`{s.value}` ({codec.status_code(s)})" in page, f"{s.value} not explained in docs/how/status.md"
        assert f"| {codec.status_code(s)} | `{s.value}` |" in readme, f"{s.value} not in the README's status table"


def test_readme_is_short_and_the_docs_speak_of_the_software():
    assert len(README.read_text(encoding="utf-8").splitlines()) <= 250
    text = _user_docs() + (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    for pattern in (r"\bsessions?\b", r"(?<![\w&])#\d+\b", r"\bissue\s+\d+", r"\bblocked\b"):
        hits = re.findall(rf".{{0,40}}{pattern}.{{0,40}}", text, re.I)
        assert not hits, f"development process in the user documentation: {hits[:3]}"


def test_version_follows_the_changelog():
    import estimator

    first = re.search(r"^## \[(\d+\.\d+\.\d+)\]", (ROOT / "CHANGELOG.md").read_text(encoding="utf-8"), re.M)
    assert first and first.group(1) == estimator.__version__


def _headline_rows() -> list[list[str]]:
    readme = README.read_text(encoding="utf-8")
    sec = readme[readme.index("## Headline figures"):]
    sec = sec[sec.index("| what"):]
    sec = sec[:sec.index("\n\n")]
    return [[c.strip() for c in r.strip().strip("|").split("|")] for r in sec.splitlines()[2:]]


def test_the_readme_headline_figures_are_the_performance_pages():
    """Each figure the README's headline table states is one the performance page states (the page is
    where a figure is replaced when it is measured again): a README left behind fails here."""
    page = set(_numbers((ROOT / "docs" / "performance.md").read_text(encoding="utf-8")))
    rows = _headline_rows()
    assert len(rows) >= 15
    stale = {row[0]: [n for n in _numbers(row[1]) if n not in page] for row in rows}
    assert not {k: v for k, v in stale.items() if v}, stale


def _numbers(text: str) -> list[str]:
    """The numbers in ``text`` as written, thousands separators dropped."""
    return [n.replace(",", "") for n in NUMBER.findall(text)]


def _states(stream: list[str], text: str) -> bool:
    """Whether the numbers of ``text`` appear in ``stream`` one after the other."""
    want = _numbers(text)
    return any(stream[i:i + len(want)] == want for i in range(len(stream) - len(want) + 1))


def _page_rows(row: str, lines: list[str]) -> list[str]:
    return [line for line in lines if line.startswith(row)]


def test_every_published_figure_has_one_row_on_the_performance_page():
    """Each figure :data:`sim_bench.benches.published.FIGURES` knows names the start of one table line of the
    performance page (a row renamed or split leaves its figures unchecked otherwise)."""
    from sim_bench.benches.published import FIGURES

    lines = (DOCS / "performance.md").read_text(encoding="utf-8").splitlines()
    rows = {f.row for f in FIGURES if f.row is not None}
    assert len(rows) >= 50
    assert not {r: n for r in rows if (n := len(_page_rows(r, lines))) != 1}


def test_the_published_figures_are_what_the_readme_and_the_performance_page_state():
    """docs/figures.json is where a current figure comes from (``sim_bench publish`` writes it from the
    benches' JSON reports) and holds every figure the benches publish: the performance page states
    each in its row (a lot's or a part's values each), the README's headline table each one it has a
    row for. Publishing a figure measured again fails here until both say it."""
    import json

    from sim_bench.benches.published import FIGURES, number

    figures = json.loads((DOCS / "figures.json").read_text(encoding="utf-8"))
    known = {f"{f.bench}: {f.name}": f for f in FIGURES}
    assert set(figures) == set(known), (sorted(set(figures) - set(known)), sorted(set(known) - set(figures)))
    page = (DOCS / "performance.md").read_text(encoding="utf-8")
    lines = page.splitlines()
    readme = _numbers(" ".join(row[1] for row in _headline_rows()))
    wrong = []
    for name, fig in figures.items():
        figure = known[name]
        where = _page_rows(figure.row, lines)[0] if figure.row else page
        stated = _numbers(where)
        each_value = fig["runs"] == 1 and len(fig["values"]) > 1      # one run's lots or parts
        if not (_states(stated, fig["text"]) or
                (each_value and all(_numbers(number(v, figure.digits))[0] in stated for v in fig["values"]))):
            wrong.append(f"performance page, {figure.row or 'prose'}: {name} {fig['text']}")
        if figure.headline and not _states(readme, fig["text"]):
            wrong.append(f"README: {name} {fig['text']}")
    assert not wrong, wrong


def test_the_readme_targets_are_the_benches_own():
    """The target the README states for a bench with headline targets is one of that bench's own
    (sim_bench.benches.targets, which the bench exits on and the performance page renders)."""
    from sim_bench.benches.targets import TARGETS

    bench = None
    checked = 0
    for what, _current, target, command in (row[:4] for row in _headline_rows()):
        if command != "same":
            words = command.strip("`").split()
            bench = " ".join(words[3:5]) if {"--self-calibration", "--sweep"} & set(words) \
                else (words[3] if len(words) > 3 else None)
        if bench not in TARGETS:
            continue
        known = {float(t.limit) for t in TARGETS[bench]}
        known |= {float(n) for t in TARGETS[bench] for n in _numbers(t.what)}
        stated = {float(n) for n in _numbers(target)}
        assert stated <= known, (what, bench, sorted(stated - known))
        checked += 1
    assert checked >= 5


def test_publish_takes_the_median_and_range_of_runs_and_a_lots_range_of_one(tmp_path):
    """``sim_bench publish``: five speed runs give the median and the range (one value where all five
    measured alike); one compensation run the
    range over its lots; a tracking report's lot-life scenario counts as that bench; figures not
    measured again stay, one no bench publishes goes; a directory that is not one is refused with one
    line."""
    import json
    import subprocess
    import sys

    for i, warm in enumerate((0.212, 0.210, 0.215, 0.209, 0.211)):
        d = tmp_path / f"run{i}" / "bench-results"
        d.mkdir(parents=True)
        (d / "speed.json").write_text(json.dumps({"benchmark": "speed", "warm_median_ms": warm,
                                                  "warm_with_correction_median_ms": warm + 0.09,
                                                  "cold_median_ms": 1.0 + 1e-9 * i}))
    lots = [{"closed": {"stroke_spread_um": {"settled_median": v}, "opening_spread_us": {"settled_median": 0.2}}}
            for v in (0.1, 0.13, 0.12)]
    (tmp_path / "run0" / "bench-results" / "compensation.json").write_text(json.dumps(
        {"benchmark": "compensation", "lots": lots, "z_rms_stroke": 0.9, "z_rms_opening": 1.2}))
    (tmp_path / "run1" / "bench-results" / "tracking.json").write_text(json.dumps(
        {"benchmark": "tracking", "reports": [{"benchmark": "tracking", "scenario": "lot-life",
                                               "summary": {"max_lh_err_within_um": 0.0751}}]}))
    out = tmp_path / "figures.json"
    out.write_text(json.dumps({"daemon: daemon_p99_ms": {"text": "1.92", "runs": 1, "values": [1.92]},
                               "speed: a figure no bench publishes": {"text": "1", "runs": 1, "values": [1.0]}}))
    cmd = [sys.executable, "-m", "sim_bench", "publish", *(str(tmp_path / f"run{i}") for i in range(5)),
           "--out", str(out)]
    subprocess.run(cmd, check=True, capture_output=True, cwd=ROOT)
    figs = json.loads(out.read_text())
    assert figs["speed: warm_median_ms"]["text"] == "0.211 (0.209–0.215)"
    assert figs["speed: warm_median_ms"]["runs"] == 5
    assert figs["speed: cold_median_ms"]["text"] == "1.00"    # every run alike: stated once
    assert figs["compensation: stroke_spread_um"]["text"] == "0.100–0.130"
    assert figs["tracking --scenario lot-life: lh_max_within_um"]["text"] == "0.075"
    assert figs["daemon: daemon_p99_ms"]["text"] == "1.92"
    assert "speed: a figure no bench publishes" not in figs
    bad = subprocess.run([*cmd[:4], str(tmp_path / "nowhere")], capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1
