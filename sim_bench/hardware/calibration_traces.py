"""Calibration traces (eq. 25): an actuator without valve at several temperatures, with s3 measured.

The simulated actuator follows the benches' temperature law (:func:`scenarios.nu_of_temperature`),
and R = R(N_u(T)) from eq. 22 with Table 1's R0a, R0b.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from estimator.io.traces import write_trace
from estimator.model.drive import SAMPLE_PERIOD_S, Drive, StandardDrive, sample_times
from estimator.model.parameters import load_nominal
from estimator.model.psa_lti import simulate_psa
from sim_bench.hardware.scenarios import nu_of_temperature


def write(out_dir: Path, temperatures_c: list[float], seed: int = 5, noise_v: float = 0.02,
          t_end_s: float = 200e-6, drive: Drive | None = None) -> list[Path]:
    """Write one trace CSV per temperature into ``out_dir`` (driven with ``drive``, default the standard
    drive); returns the paths."""
    p = load_nominal()
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    t = sample_times(t_end_s)
    cur = (drive or StandardDrive()).samples(t_end_s)
    paths = []
    for temp in temperatures_c:
        nu = nu_of_temperature(temp)
        u, s3 = simulate_psa(p, nu, p.psa.resistance_ohm(nu), cur, SAMPLE_PERIOD_S)
        u = u + noise_v * rng.standard_normal(u.size)
        path = out_dir / f"calib_{temp:+06.1f}C.csv"
        write_trace(path, {"t_s": t, "current_A": cur, "voltage_V": u, "s3_m": s3},
                    {"temperature_c": temp, "true_nu_n_per_v": nu, "source": "sim_bench calibration-traces"})
        paths.append(path)
    return paths
