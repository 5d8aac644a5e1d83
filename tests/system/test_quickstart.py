"""The README's three quick starts, copied and pasted as a user would: each block runs in bash in a
fresh directory with the environment's ``python`` first on PATH, and must succeed."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def quick_starts() -> dict[str, str]:
    """The shell blocks that follow a ``<!-- quickstart: NAME -->`` marker in the README."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return dict(re.findall(r"<!-- quickstart: ([\w-]+) -->\s*```sh\n(.*?)```", text, re.S))


def test_the_readme_has_the_three_quick_starts():
    assert set(quick_starts()) == {"hil", "calibration", "eol"}


@pytest.mark.slow
@pytest.mark.timeout(400)
@pytest.mark.parametrize("name", ["hil", "calibration", "eol"])
def test_quick_start_runs_as_written(name, tmp_path):
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    script = "set -euo pipefail\n" + quick_starts()[name]
    out = subprocess.run(["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=380)
    assert out.returncode == 0, f"quick start {name} failed:\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    if name == "hil":
        rows = [line for line in out.stdout.splitlines() if "EstimateState" in line]
        assert len(rows) == 4 and all("Status: ok" in r for r in rows), out.stdout[-2000:]
    elif name == "calibration":
        assert '"status": "ok"' in out.stdout and (tmp_path / "figures" / "voltage_fit.png").is_file()
    else:
        assert "flagged" in (tmp_path / "lot-results-report.txt").read_text(encoding="utf-8") or out.stdout
        assert (tmp_path / "lot-results.csv").is_file() and (tmp_path / "inj0.csv").is_file()
