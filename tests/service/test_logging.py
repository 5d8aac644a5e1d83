"""Log lines for systemd: journald priorities under JOURNAL_STREAM, JSON lines on request."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from ..conftest import REPO


def run_track(tmp_path, *opts, env=None, stderr_path=None):
    missing = str(tmp_path / "missing.csv")
    err = open(stderr_path, "w") if stderr_path else subprocess.PIPE
    r = subprocess.run([sys.executable, "-m", "estimator", *opts, "track", missing], cwd=REPO, env=env,
                       stdout=subprocess.PIPE, stderr=err, text=True, timeout=120)
    return r, (stderr_path.read_text() if stderr_path else r.stderr)


def test_journal_priorities_when_stderr_is_the_journal_stream(tmp_path):
    path = tmp_path / "journal"
    path.write_text("")
    st = os.stat(path)
    env = dict(os.environ, JOURNAL_STREAM=f"{st.st_dev}:{st.st_ino}")
    r, err = run_track(tmp_path, env=env, stderr_path=path)
    assert r.returncode == 1
    warning = [x for x in err.splitlines() if "cannot read trace" in x and not x.startswith("error:")]
    assert warning and all(x.startswith("<4>estimator: ") for x in warning), err
    # the same command on a terminal or file that is not the journal: plain text with a timestamp
    r, err = run_track(tmp_path)
    assert " WARNING estimator: cannot read trace" in err and "<4>" not in err


def test_json_log_lines(tmp_path):
    _r, err = run_track(tmp_path, "--log-format", "json")
    docs = [json.loads(x) for x in err.splitlines() if x.startswith("{")]
    assert docs and docs[0]["level"] == "WARNING" and docs[0]["priority"] == 4 and docs[0]["logger"] == "estimator"
    assert "cannot read trace" in docs[0]["message"] and isinstance(docs[0]["time"], float)


def test_priority_mapping():
    import logging

    from estimator.logfmt import JournalFormatter, priority
    assert [priority(x) for x in (50, 40, 30, 20, 10, 25)] == [2, 3, 4, 6, 7, 6]
    rec = logging.LogRecord("estimator.x", logging.ERROR, __file__, 1, "two\nlines", None, None)
    assert JournalFormatter().format(rec) == "<3>estimator.x: two\n<3>lines"
