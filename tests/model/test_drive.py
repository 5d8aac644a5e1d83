"""The Drive protocol: one definition of the amplifier current used by the plant, the
identifier's valve prediction and every command; a new shape is one class plus its registration."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from estimator.errors import TraceError
from estimator.ident.fit.idle_stroke import predict_valve
from estimator.ident.measurement import Injection
from estimator.io.traces import read_trace
from estimator.model import drive as drv
from estimator.model.drive import (
    SAMPLE_PERIOD_S,
    Drive,
    StandardDrive,
    TableDrive,
    TimeFunction,
    sample_times,
    standard_drive,
)
from estimator.model.fast_sim import PLATEAU_WINDOW_S, FastSimulator
from sim_bench.benches import tracking_bench as tb
from sim_bench.cli import build_parser
from sim_bench.cli import main as sim_main
from sim_bench.hardware import scenarios
from sim_bench.hardware.node import InjectionSource
from sim_bench.hardware.plant import Plant, PlantConfig


@dataclass(frozen=True)
class PilotMain(TimeFunction):
    """A shape the product does not have: a 3 A pilot pulse 0-40 µs, then the standard drive delayed 60 µs."""

    def current(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        pilot = drv.trapezoid(t, 3.0, 0.0, 10e-6, 30e-6, 40e-6)
        return pilot + standard_drive(t - 60e-6) * (t >= 60e-6)


@pytest.fixture
def pilot_main():
    drv.register_drive("pilot-main", PilotMain)
    yield PilotMain()
    del drv.DRIVES["pilot-main"]


def test_every_drive_is_a_drive():
    for d in (StandardDrive(), TableDrive.sampled(np.ones(4), 0.5e-6), PilotMain(),
              PlantConfig().amplifier(StandardDrive(), 0.3)):
        assert isinstance(d, Drive)
    np.testing.assert_array_equal(StandardDrive().samples(100e-6), standard_drive(sample_times(100e-6)))
    with pytest.raises(ValueError, match="twice"):
        drv.register_drive("standard", StandardDrive)
    with pytest.raises(ValueError, match=r"unknown drive 'no-such'.*standard"):
        drv.named_drive("no-such")


def test_a_sampled_current_keeps_its_samples_and_then_holds_zero():
    cur = np.linspace(0.0, 4.0, 201)
    d = TableDrive.sampled(cur, SAMPLE_PERIOD_S)
    got = d.samples(PLATEAU_WINDOW_S[1])
    assert got.size == 981
    np.testing.assert_array_equal(got[:201], cur)
    assert not got[201:].any()
    # on another grid it is the first-order hold the simulators assume
    half = d.samples(50e-6, SAMPLE_PERIOD_S / 2)
    np.testing.assert_allclose(half[1::2], 0.5 * (cur[:100] + cur[1:101]), rtol=1e-12)
    np.testing.assert_array_equal(half[::2], cur[:101])


def test_a_table_with_bad_values_is_a_trace_error():
    with pytest.raises(TraceError, match="strictly increasing"):
        TableDrive.from_table([0.0, 1e-6, 1e-6], [0.0, 1.0, 2.0])
    with pytest.raises(TraceError, match="NaN"):
        TableDrive.from_table([0.0, 1e-6], [0.0, float("nan")])
    with pytest.raises(TraceError, match="equal length"):
        TableDrive.from_table([0.0, 1e-6], [0.0])


def test_the_valve_prediction_runs_the_measured_current_then_zero():
    sim = FastSimulator()
    cur = StandardDrive().samples(100e-6)
    inj = Injection(cur, np.zeros_like(cur), SAMPLE_PERIOD_S)
    tc, to, stroke = predict_valve(sim, inj, 17.0, 3e-6)
    held = np.zeros(981)
    held[:201] = cur
    ref = sim.simulate(held, 17.0, 3e-6, 28.0)
    assert (tc, to) == (float(ref.t_contact_s[0]), float(ref.t_open_s[0]))
    assert stroke == pytest.approx(float(ref.plateau_stroke_m()[0]), rel=1e-12)   # a sum in another order
    # the compiled prediction is simulate's: pre-compressed (L_h <= 0) and without a plateau (NaN stroke)
    for lh_m, samples in ((-1e-6, held), (3e-6, held[:400])):
        ref = sim.simulate(samples, 17.0, lh_m, 28.0)
        got = sim.valve_prediction(samples, 17.0, lh_m, 28.0)
        want = (ref.t_contact_s[0], ref.t_open_s[0], ref.plateau_stroke_m()[0])
        np.testing.assert_allclose(got, want, rtol=1e-12, equal_nan=True)
    assert np.isnan(got[2]) and np.isfinite(got[1])


def test_a_new_drive_shape_reaches_the_plant_the_scenarios_and_the_commands(pilot_main, tmp_path):
    # the plant: the commanded shape plus the amplifier's ripple
    plant = Plant(PlantConfig(drive=pilot_main, ripple_a=0.0))
    m = plant.measure(17.0, 3e-6, 28.0, np.random.default_rng(1))
    assert np.abs(m.current_a - pilot_main.samples(100e-6)).max() < 0.05   # ADC noise and LSB only
    # a scenario run with it (bench node) and a tracking scenario run with it
    sc = scenarios.get("nominal", drive=drv.named_drive("pilot-main"))
    meas, _ = InjectionSource(sc, seed=0).measure(0, 0, 0.0)
    assert abs(meas.current_a[50] - 3.0) < 0.3 and abs(meas.current_a[100]) < 0.3   # pilot at 25 µs, gap at 50 µs
    rep = tb.tracking("steady", injections=3, drive=pilot_main)
    assert len(rep["rows"]) == 3
    # every simulating command offers it
    parser = build_parser()
    for cmd in ("simulate", "node", "bench", "tracking", "speed", "speed-sim", "calibration-traces", "lot"):
        extra = ["--out", "x"] if cmd in ("simulate", "calibration-traces", "lot") else []
        assert parser.parse_args([cmd, "--drive", "pilot-main", *extra]).drive == "pilot-main", cmd
    out = tmp_path / "pm.csv"
    assert sim_main(["simulate", "--drive", "pilot-main", "--t-end-us", "200", "--out", str(out)]) == 0
    np.testing.assert_allclose(read_trace(out).column("current_A"), pilot_main.samples(200e-6), rtol=1e-9, atol=1e-12)


def test_simulate_refuses_a_current_file_and_a_drive_together(tmp_path, capsys):
    rc = sim_main(["simulate", "--drive", "standard", "--current", str(tmp_path / "c.csv"), "--out",
                   str(tmp_path / "o.csv")])
    assert rc != 0 and "either --current FILE or --drive NAME" in capsys.readouterr().err


def test_both_benches_speak_one_scenario_vocabulary():
    bench, track = scenarios.SCENARIOS["warm-up"], tb.TRACKING["warm-up"]
    assert type(scenarios.SCENARIOS) is type(tb.TRACKING) is scenarios.Registry
    rng = np.random.default_rng(0)
    for sc, truth in ((bench, bench.truth(1, 7, 30.0, rng)), (track, track.truth(0, 30, 30.0))):
        assert isinstance(truth, scenarios.Truth) and isinstance(sc.drive, Drive) and sc.description
        assert 15.0 <= truth.nu_n_per_v <= 21.0 and 0 < truth.lh_um < 10.0 and truth.f_open_n >= 28.0
        assert np.isfinite(truth.temperature_c)      # both warm-ups report the fuel temperature
    assert np.isnan(tb.TRACKING["steady"].truth(0, 0, 0.0).temperature_c)
    with pytest.raises(KeyError, match="unknown tracking scenario 'no-such'"):
        tb.TRACKING["no-such"]
    with pytest.raises(ValueError, match="no targets"):
        scenarios.Registry("x", scenarios.BenchTargets).register(tb.TRACKING["steady"])
