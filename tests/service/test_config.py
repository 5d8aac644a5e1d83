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
    ("state_dir = 5", "state_dir"),
    ("dbc = [1]", "dbc"), ("commands = \"maybe\"", "commands"), ("log_level = \"LOUD\"", "log_level"),
    ("sample_periods_ns = [500, -1]", "sample_periods_ns"), ("sample_periods_ns = \"500\"", "sample_periods_ns"),
    ("max_sample_periods = 0", "max_sample_periods"), ("silent_bus_s = nan", "silent_bus_s"),
    ("assembly_timeout_ms = inf", "assembly_timeout_ms"), ("bus = \"\"", "bus"),
    ("max_injectors = 9", "max_injectors"), ("params = 3", "params"),
])
def test_a_bad_value_is_one_error_naming_the_key(tmp_path, line, key):
    with pytest.raises(ConfigError) as e:
        load_text(tmp_path, f"[estimator]\n{line}\n")
    msg = str(e.value)
    assert msg.startswith(f"{key} = ") and "\n" not in msg


@pytest.mark.parametrize("table, line, key", [
    ("ident", "window_s = 1e9", "window_s"), ("ident", "window_s = 0", "window_s"), ("ident", "robust = 1", "robust"),
    ("ident", "robust = \"sometimes\"", "robust"), ("ident", "norm = \"l3\"", "norm"),
    ("ident", "start_point = [1, 2, 3]", "start_point"), ("ident", "cold_start = \"warm\"", "cold_start"),
    ("ident", "wndow_s = 1e-4", "wndow_s"), ("tracker", "q_lh_um = -1", "q_lh_um"),
    ("tracker", "warm_cycles = 0", "warm_cycles"), ("tracker", "gate_chi2 = \"x\"", "gate_chi2"),
    ("self_calibration", "window = 3", "window"), ("self_calibration", "mode = \"yes\"", "mode"),
    ("self_calibration", "mode = true", "mode"),
])
def test_a_bad_value_in_a_sub_table_is_one_error_naming_the_table_and_the_key(tmp_path, table, line, key):
    with pytest.raises(ConfigError) as e:
        load_text(tmp_path, f"[estimator.{table}]\n{line}\n")
    msg = str(e.value)
    assert msg.startswith(f"[estimator.{table}]") and key in msg and "\n" not in msg, msg


def test_the_sub_tables_build_the_settings_objects(tmp_path):
    cfg = load_text(tmp_path, "[estimator]\ncommands = \"all\"\n[estimator.ident]\nwindow_s = 1.2e-4\nrobust = \"on\"\n"
                              "start_point = [17, 3.5]\ntol = [1e-4, 1e-3]\n[estimator.tracker]\nq_lh_um = 0.004\n"
                              "[estimator.self_calibration]\nmode = \"on\"\nwindow = 8\n")
    assert cfg.commands == "all" and cfg.ident.window_s == 1.2e-4 and cfg.ident.robust == "on"
    assert cfg.ident.start_point == (17, 3.5) and cfg.ident.tol == (1e-4, 1e-3) and cfg.tracker.q_lh_um == 0.004
    assert cfg.self_calibration is not None and cfg.self_calibration.window == 8
    assert load_text(tmp_path, "[estimator.self_calibration]\nwindow = 8\n").self_calibration.window == 8   # on by default
    assert load_text(tmp_path, "[estimator.self_calibration]\nmode = \"off\"\n").self_calibration is None
    with pytest.raises(ConfigError, match=r"\[estimator.ident\]"):
        load_text(tmp_path, "[estimator.tracker.ident]\nwindow_s = 1e-4\n")


def test_the_flat_keys_of_earlier_versions_still_load_with_a_warning_naming_their_place(tmp_path, caplog):
    old = load_text(tmp_path, "[estimator]\nwindow_us = 120.0\nrobust = \"on\"\nstart_nu_n_per_v = 16.5\n"
                              "start_lh_um = 2.5\nq_lh_um = 0.004\nself_calibration = \"on\"\n"
                              "self_calibration_window = 8\n")
    new = load_text(tmp_path, "[estimator.ident]\nwindow_s = 1.2e-4\nrobust = \"on\"\nstart_point = [16.5, 2.5]\n"
                              "[estimator.tracker]\nq_lh_um = 0.004\n[estimator.self_calibration]\nmode = \"on\"\n"
                              "window = 8\n")
    assert old == new
    warned = [r.getMessage() for r in caplog.records if "deprecated" in r.getMessage()]
    assert any("window_us in [estimator] is deprecated: use window_s in [estimator.ident]" in m for m in warned)
    assert any("self_calibration_window" in m and "[estimator.self_calibration]" in m for m in warned)
    assert len(warned) == 7
    with pytest.raises(ConfigError, match="window_s"):
        load_text(tmp_path, "[estimator]\nwindow_us = 1e9\n")


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
    """Seeded fuzz: random keys with random values of every type, in [estimator] and in its sub-tables.
    Either a valid configuration (every value of the right type and in range) or one ConfigError line
    that names the key (or its table)."""
    from estimator.ident.config import IdentConfig, TrackerConfig
    from estimator.ident.learning.selfcal import SelfCalConfig
    rng = random.Random(10)
    names = [f.name for f in fields(DaemonConfig)] + ["ident"]
    section_keys = {"ident": [f.name for f in fields(IdentConfig)], "tracker": [f.name for f in fields(TrackerConfig)],
                    "self_calibration": [f.name for f in fields(SelfCalConfig)] + ["mode"]}
    ok = bad = 0
    for _ in range(900):
        kw = {}
        for _ in range(rng.randint(1, 3)):
            name = rng.choice(names)
            if name in section_keys and rng.random() < 0.7:
                kw[name] = {rng.choice(section_keys[name]): rng.choice(VALUES) for _ in range(rng.randint(1, 2))}
                kw[name] = {k: v for k, v in kw[name].items() if v is not None}
            else:
                kw[name] = rng.choice(VALUES)
        kw = {k: v for k, v in kw.items() if v is not None}
        try:
            cfg = DaemonConfig.load(None, **kw)
        except ConfigError as exc:
            bad += 1
            text = str(exc)
            assert "\n" not in text, text
            assert any(text.startswith(k) or text.startswith(f"[estimator.{k}]") for k in kw) or \
                text.startswith("config: "), text
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
