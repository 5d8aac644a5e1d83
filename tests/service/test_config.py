"""The daemon's configuration tree: every key type- and range-checked with one line naming it,
seeded fuzz over keys and value types, log_level honoured, params loaded, SIGHUP-style reload."""

from __future__ import annotations

import random
import subprocess
import sys
from dataclasses import fields

import pytest

from estimator.service.config import ConfigError, DaemonConfig

from ..conftest import REPO


def load_text(tmp_path, text: str | bytes) -> DaemonConfig:
    p = tmp_path / "e.toml"
    p.write_bytes(text if isinstance(text, bytes) else text.encode())
    return DaemonConfig.load(p)


@pytest.mark.parametrize("line, key", [
    ("queue_frames = 1.5", "queue_frames"), ("queue_frames = true", "queue_frames"),
    ("window_us = 1e9", "window_us"), ("window_us = 0", "window_us"), ("state_dir = 5", "state_dir"),
    ("dbc = [1]", "dbc"), ("commands = \"maybe\"", "commands"), ("log_level = \"LOUD\"", "log_level"),
    ("sample_periods_ns = [500, -1]", "sample_periods_ns"), ("sample_periods_ns = \"500\"", "sample_periods_ns"),
    ("max_sample_periods = 0", "max_sample_periods"), ("silent_bus_s = nan", "silent_bus_s"),
    ("assembly_timeout_ms = inf", "assembly_timeout_ms"), ("robust = 1", "robust"), ("bus = \"\"", "bus"),
    ("max_injectors = 9", "max_injectors"), ("q_lh_um = -1", "q_lh_um"), ("params = 3", "params"),
])
def test_a_bad_value_is_one_error_naming_the_key(tmp_path, line, key):
    with pytest.raises(ConfigError) as e:
        load_text(tmp_path, f"[estimator]\n{line}\n")
    msg = str(e.value)
    assert msg.startswith(f"{key} = ") and "\n" not in msg


def test_files_that_are_not_configurations(tmp_path):
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_text(tmp_path, "[estimator]\nlog_level = \"INFO\" # caf\xe9\n".encode("latin-1"))
    with pytest.raises(ConfigError, match="must be a table"):
        load_text(tmp_path, "estimator = 5\n")
    with pytest.raises(ConfigError, match="unknown key"):
        load_text(tmp_path, "[estimator]\nqueue_frame = 10\n")
    with pytest.raises(ConfigError, match="unknown key"):
        load_text(tmp_path, "[estimator.extra]\nx = 1\n")
    with pytest.raises(ConfigError):
        load_text(tmp_path, "[estimator\n")
    with pytest.raises(ConfigError, match="does-not-exist"):
        DaemonConfig.load(tmp_path / "does-not-exist.toml")


def test_the_shipped_example_loads_and_lists_every_key():
    cfg = DaemonConfig.load(REPO / "systemd" / "estimator.toml")
    assert cfg == DaemonConfig()                     # the example documents the defaults
    text = (REPO / "systemd" / "estimator.toml").read_text()
    for f in fields(DaemonConfig):
        assert f.name in text, f"systemd/estimator.toml does not document {f.name}"


def test_params_key_loads_what_calibrate_writes(tmp_path):
    good = tmp_path / "p.toml"
    good.write_text((REPO / "estimator" / "model" / "parameters.toml").read_text())
    cfg = load_text(tmp_path, f"[estimator]\nparams = \"{good}\"\n")
    assert cfg.params == good
    bad = tmp_path / "bad.toml"
    bad.write_text("[psa]\nkp_n_per_m = 1\n")
    with pytest.raises(ConfigError, match="params = "):
        load_text(tmp_path, f"[estimator]\nparams = \"{bad}\"\n")


VALUES = [0, 1, -1, 7, 2 ** 40, 0.5, 1e9, -1e-9, float("nan"), float("inf"), True, False, "", "x", "INFO", "all",
          "off", "auto", "socketcan:vcan0", [], [500], [1, 2, 3], ["a"], {}, {"a": 1}, None]


def test_config_fuzz_never_raises_anything_but_a_config_error():
    """Seeded fuzz: random keys with random values of every type. Either a valid configuration
    (every value of the right type and in range) or one ConfigError line that names the key."""
    rng = random.Random(10)
    names = [f.name for f in fields(DaemonConfig)]
    ok = bad = 0
    for _ in range(600):
        kw = {rng.choice(names): rng.choice(VALUES) for _ in range(rng.randint(1, 3))}
        kw = {k: v for k, v in kw.items() if v is not None}
        try:
            cfg = DaemonConfig.load(None, **kw)
        except ConfigError as exc:
            bad += 1
            assert "\n" not in str(exc) and any(str(exc).startswith(k) for k in kw) or "tracker" in str(exc)
            continue
        ok += 1
        assert isinstance(cfg.queue_frames, int) and cfg.queue_frames >= 16
        cfg.tracker_config()
    assert ok > 15 and bad > 300


def test_cli_reports_a_bad_config_in_one_line_and_exits_nonzero(tmp_path):
    p = tmp_path / "e.toml"
    p.write_text("[estimator]\nqueue_frames = 1.5\n")
    r = subprocess.run([sys.executable, "-m", "estimator", "run", "--bus", "virtual:x", "--config", str(p)],
                       cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == ["error: queue_frames = 1.5: must be a whole number in [16, 1000000]"]
