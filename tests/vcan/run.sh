#!/usr/bin/env bash
# `make test-vcan`: the vcan suite (pytest -m vcan) natively where vcan0 exists, else inside the QEMU VM
# of ../shared/vcan-vm (Debian kernel with vcan; the host's filesystem, venv and can-utils).
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=.venv/bin/python
PYTEST_ARGS=(-m vcan tests/vcan -q -p no:cacheprovider)
if [ -e /sys/class/net/vcan0 ]; then
  exec "$PY" -m pytest "${PYTEST_ARGS[@]}"
fi
VM=../shared/vcan-vm
if [ ! -x "$VM/vmrun.sh" ]; then
  echo "vcan suite skipped: no vcan0 here and no $VM to boot a kernel with vcan"
  exit 0
fi
bash "$VM/setup.sh"
# The VM's CPU model (QEMU TCG) differs from the host's, so numba would recompile every kernel inside the
# ~16x slower guest. Compile them once here for a generic x86-64 CPU; the guest then loads them from the cache.
export NUMBA_CPU_NAME=generic
"$PY" - <<'PYEOF'
from estimator.model.drive import sample_times, standard_drive
from estimator.model.fast_sim import FastSimulator
from estimator.ident.tracking.tracker import Tracker
from sim_bench.hardware.plant import Plant, PlantConfig
import numpy as np
cur = standard_drive(sample_times(100e-6))
FastSimulator().simulate(cur, [16.0, 17.0], [-0.5e-6, 3e-6])
Tracker().warm_up()        # what the daemon runs before READY: cold start, warm updates
Plant(PlantConfig()).warm_up()
from sim_bench.hardware.plant import pi_hysteresis
pi_hysteresis(np.linspace(0, 1e-3, 10))
PYEOF
mkdir -p bench-results
VM_PASSENV="CI NUMBA_CPU_NAME" VM_TIMEOUT=${VM_TIMEOUT:-1200} VM_MEM=${VM_MEM:-2G} \
  "$VM/vmrun.sh" --rw "$PWD" "ip link add dev vcan0 type vcan && ip link set vcan0 mtu 72 up && \
  TMPDIR=/tmp $PY -m pytest ${PYTEST_ARGS[*]} --junitxml=bench-results/vcan-junit.xml"
