"""The amplifier's own standard drive (estimator.drive.standard): learned from the measured current of
the first injections, checked on every later one, read from a current table; the correction computed
with it, not with the built-in trapezoid."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from estimator.drive.correction import DriveCompensator, DriveTarget, respond
from estimator.drive.standard import AmplifierDrive, DriveLearner, from_recordings
from estimator.ident.simulators import SimulatorPool
from estimator.model.chain import MeasurementChain
from estimator.model.drive import SAMPLE_PERIOD_S, StandardDrive, named_drive
from sim_bench.hardware.amplifiers import EXTRA_PROFILES, PROFILES, amplifier
from sim_bench.hardware.plant import Plant, PlantConfig

COV = np.diag([0.01 ** 2, 0.05 ** 2])
WINDOW_S = 200e-6     # holds the whole charge


def _plant(name: str) -> Plant:
    amp = amplifier(name)
    return Plant(PlantConfig(window_s=WINDOW_S, drive=amp.standard, ripple_a=amp.ripple_a,
                             ripple_period_s=amp.ripple_period_s))


@pytest.fixture(scope="module")
def sim():
    return SimulatorPool().get(SAMPLE_PERIOD_S)


def test_the_correction_is_computed_with_the_drive_the_amplifier_delivers(sim):
    """On an amplifier with a shorter, higher plateau of the same charge, the correction waits for the
    drive learned from the first four injections, then predicts the opening instant the true drive
    gives; the trapezoid would put it a microsecond off with a σ of a tenth of that."""
    plant, rng = _plant("short-high"), np.random.default_rng(3)
    comp = DriveCompensator()
    for k in range(6):
        m = plant.measure(18.0, 4e-6, 120.0, rng)
        c = comp.update(0, True, sim, 18.0, 4.0, COV, 120.0, sim, current_a=m.current_a, dt_s=m.dt_s)
        assert c.valid == (k >= 3), (k, c.reason)
        if k < 3:
            assert "learning the amplifier's standard drive" in c.reason
    true = AmplifierDrive(amplifier("short-high").standard.samples(700e-6, SAMPLE_PERIOD_S), SAMPLE_PERIOD_S,
                          "true", measured=False)
    stroke, opening = respond(sim, c.scale, 18.0, 4.0, 120.0, true)
    assert abs(stroke - c.stroke_um) < 0.05 and abs(c.offset_us + opening - c.opening_us) < 0.15
    _, trapezoid_opening = respond(sim, c.scale, 18.0, 4.0, 120.0)
    assert abs(c.offset_us + trapezoid_opening - c.opening_us) > 1.0
    assert comp.drive_of(0) is not None and comp.drive_of(0).source == "learned"


@pytest.mark.parametrize("name", PROFILES + EXTRA_PROFILES)
def test_every_amplifier_profile_puts_the_trapezoids_charge_in_another_shape(name):
    """Each profile charges the actuator as the trapezoid does (the comparison between amplifiers is one
    of shape, not of charge), is a drive by name, and only the trapezoid itself has the trapezoid's shape."""
    t = np.arange(0.0, 400e-6, SAMPLE_PERIOD_S)
    std = StandardDrive().current(t)
    cur = amplifier(name).standard.current(t)
    assert np.sum(cur) == pytest.approx(np.sum(std), rel=0.01)
    assert np.array_equal(named_drive(name).current(t), cur)
    shape = AmplifierDrive(std, SAMPLE_PERIOD_S, "trapezoid").check(cur, SAMPLE_PERIOD_S)
    assert shape.agrees == (name == "standard"), shape


def test_a_current_the_standard_drive_does_not_explain_holds_the_correction(sim):
    plant, rng = _plant("standard"), np.random.default_rng(4)
    comp = DriveCompensator(DriveTarget(amplifier_drive="trapezoid"))
    m = plant.measure(18.0, 4e-6, 120.0, rng)
    good = comp.update(0, True, sim, 18.0, 4.0, COV, 120.0, sim, current_a=m.current_a, dt_s=m.dt_s)
    assert good.valid and not good.held and abs(good.drive_scale - 1.0) < 0.02   # ripple within tolerance
    other = _plant("short-high").measure(18.0, 4e-6, 120.0, rng)
    held = comp.update(0, True, sim, 18.0, 4.0, COV, 140.0, sim, current_a=other.current_a, dt_s=other.dt_s)
    assert held.held and held.scale == good.scale and "disagrees with the amplifier's standard drive" in held.reason
    assert comp.drive_disagreements == 1


def test_learning_starts_again_from_a_shape_unlike_the_ones_before():
    rng = np.random.default_rng(5)
    std, short = _plant("standard"), _plant("short-high")
    learner = DriveLearner(needed=3)
    assert learner.add(std.measure(17.0, 3e-6, 60.0, rng).current_a, SAMPLE_PERIOD_S)
    assert learner.add(std.measure(17.0, 3e-6, 60.0, rng).current_a, SAMPLE_PERIOD_S) and learner.count == 2
    assert not learner.add(short.measure(17.0, 3e-6, 60.0, rng).current_a, SAMPLE_PERIOD_S)
    assert learner.count == 1 and learner.drive is None
    assert not learner.add(np.full(401, math.nan), SAMPLE_PERIOD_S) and learner.count == 1


def test_a_measured_drive_has_the_models_measurement_chain_undone():
    """A current recorded through the amplifier's channel (its skew) drives a model that knows the chain
    as the actuator's current; the designed trapezoid is used as it is."""
    chain = MeasurementChain(i_skew_s=0.5e-6)
    true = AmplifierDrive.trapezoid()
    seen, _ = chain.apply(true.current_a, np.zeros_like(true.current_a), SAMPLE_PERIOD_S)
    measured = AmplifierDrive(seen, SAMPLE_PERIOD_S, "learned")
    back = measured.actuator_samples(SAMPLE_PERIOD_S, 490e-6, chain)
    assert np.max(np.abs(back[:-2] - true.samples(SAMPLE_PERIOD_S, 490e-6)[:-2])) < 1e-9
    assert np.max(np.abs(measured.samples(SAMPLE_PERIOD_S, 490e-6) - back)) > 0.01
    assert true.actuator_samples(SAMPLE_PERIOD_S, 490e-6, chain) is true.samples(SAMPLE_PERIOD_S, 490e-6)


def test_recordings_make_one_drive_without_the_odd_one():
    rng = np.random.default_rng(6)
    std = _plant("standard")
    cur = [std.measure(17.0, 3e-6, 60.0, rng).current_a for _ in range(3)]
    cur.append(_plant("short-high").measure(17.0, 3e-6, 60.0, rng).current_a)
    drive, odd = from_recordings(cur, SAMPLE_PERIOD_S, "amp.csv")
    assert odd == [3] and drive.check(cur[0], SAMPLE_PERIOD_S).agrees
    with pytest.raises(ValueError):
        from_recordings([cur[0], cur[3]], SAMPLE_PERIOD_S, "x")   # not one drive
    for bad in (lambda: AmplifierDrive(np.zeros(10), SAMPLE_PERIOD_S, "x"),
                lambda: AmplifierDrive(np.ones(10), -1.0, "x"),
                lambda: AmplifierDrive.from_table(np.array([0.0, 1.0]), np.array([1.0, 1.0]), "x")):
        with pytest.raises(ValueError):
            bad()


def test_a_current_table_is_the_configured_drive(tmp_path):
    """``amplifier_drive`` naming a table written by ``estimator drive-table``: the compensator takes it;
    a file that is not one is refused when the configuration is read."""
    from estimator.cli import main
    from estimator.pipeline.build import build_compensator
    from estimator.pipeline.config import ConfigError, EstimatorConfig
    from sim_bench.cli import main as sim_main

    trace = tmp_path / "rec.csv"
    assert sim_main(["simulate", "--drive", "short-high", "--t-end-us", "700", "--out", str(trace)]) == 0
    table = tmp_path / "amp.csv"
    assert main(["drive-table", str(trace), "--out", str(table)]) == 0
    cfg = EstimatorConfig.from_mapping({"drive_correction": {"amplifier_drive": str(table)}})
    comp = build_compensator(cfg)
    assert comp is not None and comp.standard is not None and comp.standard.source == "amp.csv"
    assert abs(float(np.max(comp.standard.current_a)) - float(np.max(amplifier("short-high").standard.samples(
        700e-6, SAMPLE_PERIOD_S)))) < 0.01
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,current_A\n0,nan\n")
    with pytest.raises(ConfigError, match="amplifier_drive"):
        EstimatorConfig.from_mapping({"drive_correction": {"amplifier_drive": str(bad)}})
    assert main(["drive-table", str(tmp_path / "missing.csv"), "--out", str(table)]) != 0


def test_a_drive_keeps_a_bounded_number_of_grids():
    """Every injection's window may have another length (a hostile sender's too): the drive's sampled
    grids stay bounded."""
    drive = AmplifierDrive.trapezoid()
    for n in range(100, 400):
        drive.check(np.ones(n), SAMPLE_PERIOD_S)
    assert len(drive._grids) <= 16


def test_an_injection_still_at_a_restarted_daemons_correction_does_not_enter_the_drive():
    """After a restart the amplifier may drive one injection with the last correction it got (0.8 here)
    before the new daemon's first State none: learning starts again from the next one instead of
    averaging it in (a 5 % low drive would bias every correction after)."""
    rng = np.random.default_rng(8)
    std = _plant("standard")
    cur = [std.measure(17.0, 3e-6, 60.0, rng).current_a for _ in range(5)]
    learner = DriveLearner(needed=4)
    learner.add(0.8 * cur[0], SAMPLE_PERIOD_S)
    assert not learner.add(cur[1], SAMPLE_PERIOD_S) and learner.count == 1
    for c in cur[2:]:
        learner.add(c, SAMPLE_PERIOD_S)
    assert learner.drive is not None
    assert abs(learner.drive.check(cur[0], SAMPLE_PERIOD_S).scale - 1.0) < 0.005


def test_a_learned_drive_survives_a_restart_and_its_record_is_checked():
    """The drive a compensator learned goes into the daemon's state (float32, base64) and back: a
    compensator restored with it has the injector's drive at once, within float32 of the one learned;
    a configured drive ignores it; a record that is not a drive is refused with ValueError."""
    rng = np.random.default_rng(9)
    plant = _plant("short-high")
    comp = DriveCompensator(DriveTarget())
    for _ in range(4):
        comp.check_drive(2, plant.measure(17.0, 3e-6, 60.0, rng).current_a, SAMPLE_PERIOD_S)
    learned = comp.learned_drives()
    assert set(learned) == {2}
    restored = AmplifierDrive.from_dict(json.loads(json.dumps(learned[2].to_dict())))
    assert np.max(np.abs(restored.current_a - learned[2].current_a)) < 1e-5 * np.max(np.abs(learned[2].current_a))
    fresh = DriveCompensator(DriveTarget())
    assert fresh.drive_of(2) is None
    fresh.restore_drives({2: restored})
    drive, reason, scale = fresh.check_drive(2, plant.measure(17.0, 3e-6, 60.0, rng).current_a, SAMPLE_PERIOD_S)
    assert drive is restored and reason == "" and abs(scale - 1.0) < 0.01
    configured = DriveCompensator(DriveTarget(amplifier_drive="trapezoid"))
    configured.restore_drives({2: restored})
    assert configured.drive_of(2) is configured.standard and configured.learned_drives() == {}
    good = learned[2].to_dict()
    for bad in ({}, {**good, "current_a": "not base64!"}, {**good, "current_a": good["current_a"][:-4] + "AA=="[:2]},
                {**good, "dt_s": "fast"}, {**good, "dt_s": -1.0}, {**good, "current_a": ""}, [1, 2]):
        with pytest.raises(ValueError):
            AmplifierDrive.from_dict(bad)
