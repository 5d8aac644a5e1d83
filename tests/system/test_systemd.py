"""systemd units: verified with systemd-analyze where it is installed; the hardening a deployment needs."""

from __future__ import annotations

import shutil
import subprocess

import pytest

from ..conftest import REPO

UNITS = REPO / "systemd"


def test_estimator_unit_directives():
    text = (UNITS / "injector-estimator@.service").read_text()
    for d in ("Type=notify", "WatchdogSec=", "Restart=on-failure", "DynamicUser=yes", "StateDirectory=",
              "ProtectSystem=strict", "RestrictAddressFamilies=AF_CAN AF_UNIX", "CapabilityBoundingSet=\n",
              "--bus socketcan:%i", "SystemCallFilter=sched_setscheduler\n"):
        assert d in text, d
    assert "MTUBytes=72" in (UNITS / "vcan0.netdev").read_text()


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed here")
def test_units_pass_systemd_analyze_verify(tmp_path):
    for f in UNITS.iterdir():
        if f.suffix in (".service", ".netdev", ".network"):
            # the units name the install location /opt/injector-estimator; point them at this checkout
            (tmp_path / f.name).write_text(f.read_text().replace("/opt/injector-estimator/bin", str(REPO / ".venv" / "bin")))
    names = []
    for template in ("injector-estimator@", "injector-sim@", "vcan@"):
        inst = tmp_path / f"{template}vcan0.service"
        inst.symlink_to(tmp_path / f"{template}.service")
        names.append(str(inst))
    r = subprocess.run(["systemd-analyze", "verify", "--man=no", *names], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "injector" not in r.stderr and "vcan" not in r.stderr, r.stderr


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed here")
@pytest.mark.parametrize("template", ["injector-estimator@", "injector-sim@"])
def test_units_are_hardened_to_an_exposure_of_at_most_2(tmp_path, template):
    unit = tmp_path / f"{template}vcan0.service"
    unit.write_text((UNITS / f"{template}.service").read_text())
    r = subprocess.run(["systemd-analyze", "security", "--offline=yes", "--no-pager", str(unit)], capture_output=True,
                       text=True, timeout=60)
    line = [x for x in r.stdout.splitlines() if "Overall exposure level" in x]
    assert line, r.stdout + r.stderr
    exposure = float(line[0].split(":")[1].split()[0])
    assert exposure <= 2.0, line[0]
    text = unit.read_text()
    for d in ("IPAddressDeny=any", "ProtectProc=invisible", "ProcSubset=pid", "UMask=0077",
              "SystemCallFilter=@system-service", "RestrictAddressFamilies=AF_CAN AF_UNIX", "Type=notify"):
        assert d in text, d
