"""One configuration for every entry point: the estimator's (EstimatorConfig), which the daemon's
extends with the bus, state and service keys; offline work builds from it without the service layer."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import fields

import pytest

from estimator.pipeline.config import ConfigError, EstimatorConfig
from estimator.service.config import DaemonConfig

from ..conftest import REPO

ESTIMATOR_TOML = """
[estimator]
commands = "all"
max_sample_periods = 2

[estimator.ident]
window_s = 150e-6

[estimator.self_calibration]
mode = "off"
"""


def test_the_daemons_configuration_is_the_estimators_with_its_own_keys(tmp_path):
    path = tmp_path / "estimator.toml"
    path.write_text(ESTIMATOR_TOML)
    offline = EstimatorConfig.load(path)
    assert offline.commands == "all" and offline.ident.window_s == pytest.approx(150e-6)
    assert offline.self_calibration is None and offline.max_sample_periods == 2
    path.write_text(ESTIMATOR_TOML.replace('commands = "all"', 'commands = "all"\nbus = "virtual:x"\nqueue_frames = 64'))
    daemon = DaemonConfig.load(path)
    assert isinstance(daemon, EstimatorConfig) and daemon.queue_frames == 64
    assert daemon.estimator_config() == offline
    assert type(daemon.estimator_config()) is EstimatorConfig
    own = {f.name for f in fields(DaemonConfig)} - {f.name for f in fields(EstimatorConfig)}
    assert own == {"bus", "bitrate", "data_bitrate", "fd", "bus_options", "state_dir", "queue_frames",
                   "silent_bus_s", "stale_after_ms", "shed_after_ms", "status_period_s", "persist_period_s", "log_level", "xcp"}
    # the estimator's configuration knows no bus
    with pytest.raises(ConfigError, match=r"unknown key.*bus"):
        EstimatorConfig.load(path)


def test_a_bad_estimator_value_is_refused_alike_by_both(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[estimator]\nmax_sample_periods = 0\n")
    for cls in (EstimatorConfig, DaemonConfig):
        with pytest.raises(ConfigError, match="max_sample_periods = 0"):
            cls.load(path)


def test_offline_estimation_does_not_load_the_service_layer():
    """(python-can itself is loaded: cantools imports it.)"""
    code = ("import sys\n"
            "from estimator.pipeline import EstimatorConfig, build_pipeline\n"
            "codec, ingest, processor, clock = build_pipeline(EstimatorConfig())\n"
            "print(sorted(m for m in sys.modules if m.startswith(('estimator.service', 'estimator.fleet'))))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout


def test_replay_takes_the_daemons_file_and_uses_the_estimators_part(tmp_path):
    """An offline command given the daemon's configuration file checks every key (a bad bus key is an
    error) and estimates with the estimator's part."""
    from estimator.cli import offline_config

    path = tmp_path / "daemon.toml"
    path.write_text(ESTIMATOR_TOML.replace('commands = "all"', 'commands = "all"\nbus = "virtual:x"'))
    cfg = offline_config(path)
    assert type(cfg) is EstimatorConfig and cfg.commands == "all"
    path.write_text(ESTIMATOR_TOML.replace('commands = "all"', 'commands = "all"\nqueue_frames = 1'))
    with pytest.raises(ConfigError, match="queue_frames"):
        offline_config(path)
