"""Electrical calibration: a series injector's own structural parameters from its current and voltage
alone, and what they do for its idle-stroke estimate."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from estimator.errors import ParameterError
from estimator.ident.learning.electrical import calibrate_electrical
from estimator.ident.measurement import Injection
from estimator.io.traces import write_trace
from estimator.model.parameters import InjectorParameters, load_nominal
from sim_bench.hardware import series_part
from sim_bench.hardware.plant import Plant, PlantConfig

from ..conftest import REPO

LH_UM = 3.0
BATCH = ((28.0, 15.5), (60.0, 17.0), (100.0, 18.5), (150.0, 20.0), (220.0, 16.0), (300.0, 19.5))


def _part_and_plant(seed: int) -> tuple[series_part.SeriesPart, Plant, np.random.Generator]:
    rng = np.random.default_rng(seed)
    part = series_part.draw(rng)
    return part, Plant(PlantConfig(window_s=200e-6), part.params), rng


def test_a_batch_at_several_preload_forces_recovers_the_part_and_its_idle_stroke():
    """Seeded series part (every structural parameter within ±10 %): six injections at 28-300 N bring
    the voltage residual to the noise level; with the calibrated parameters a new injection at the
    nominal preload is ok and within 0.2 µm, where the nominal parameters are model_mismatch."""
    from estimator.ident.fit.idle_stroke import identify, predict_valve
    from estimator.model.fast_sim import FastSimulator

    _part, plant, rng = _part_and_plant(5)
    injections = []
    for f, nu in BATCH:
        m = plant.measure(nu, LH_UM * 1e-6, f, rng)
        injections.append(Injection(m.current_a, m.voltage_v, m.dt_s, f))
    res = calibrate_electrical(injections)
    assert res.rms_after_v < 0.12 < 0.5 < res.rms_before_v          # 0.1 V noise
    assert np.all(np.abs(res.lh_um - LH_UM) < 0.2)
    for nu in (16.2, 19.8):
        m = plant.measure(nu, LH_UM * 1e-6, 28.0, rng)
        inj = Injection(m.current_a[:201], m.voltage_v[:201], m.dt_s, 28.0)
        nominal = identify(inj, FastSimulator(dt_s=m.dt_s))
        own = identify(inj, FastSimulator(res.params, m.dt_s))
        assert nominal.status.value == "model_mismatch"
        assert own.status.value == "ok" and abs(own.lh_m * 1e6 - LH_UM) < 0.2
        # the set states what it leaves in the valve's predicted motion, and that covers the prediction
        cal = res.params.calibration
        assert 0 < cal.stroke_rel_sigma < 0.01 and 0 < cal.opening_sigma_s < 1e-6
        whole = Injection(m.current_a, m.voltage_v, m.dt_s, 28.0)      # the charge, beyond the fit's window
        _tc, t_open, stroke = predict_valve(FastSimulator(res.params, m.dt_s), whole, own.nu_n_per_v, own.lh_m)
        assert abs(stroke - m.stroke_m) < 3 * math.hypot(cal.stroke_rel_sigma * stroke, own.sigma_lh_m)
        assert abs(t_open - m.t_open_s) < 3 * cal.opening_sigma_s + 0.5e-6


def test_a_batch_at_one_preload_force_is_reported_as_weak():
    _part, plant, rng = _part_and_plant(3)
    injections = []
    for nu in (15.5, 18.0, 20.5):
        m = plant.measure(nu, LH_UM * 1e-6, 28.0, rng)
        injections.append(Injection(m.current_a, m.voltage_v, m.dt_s, 28.0))
    res = calibrate_electrical(injections, max_iterations=4)
    assert any("preload forces span only" in w for w in res.warnings)


@pytest.mark.parametrize("kwargs,match", [({"tolerance": 0.0}, "tolerance"), ({"window_s": 1e-6}, "window"),
                                          ({"names": ("psa.nothing",)}, "unknown structural")])
def test_absurd_arguments_are_refused(kwargs, match):
    inj = Injection(np.zeros(401), np.zeros(401), 0.5e-6)
    with pytest.raises(ValueError, match=match):
        calibrate_electrical([inj, inj], **kwargs)


def test_the_written_parameter_file_loads_and_keeps_the_chain(tmp_path):
    p = series_part.scaled(load_nominal(), {"psa.kp_n_per_m": 1.05})
    p = InjectorParameters(p.psa, p.valve, series_part.TYPICAL_CHAIN)
    path = tmp_path / "inj.toml"
    path.write_text(p.to_toml("a header\nof two lines"))
    back = InjectorParameters.from_toml(path)
    assert back == p


@pytest.mark.slow
def test_cli_calibrate_electrical_then_identify_with_the_result(tmp_path):
    """As a calibration engineer runs it: traces in, a parameter file out, loaded by identify."""
    _part, plant, rng = _part_and_plant(5)
    paths = []
    for k, (f, nu) in enumerate(BATCH):
        m = plant.measure(nu, LH_UM * 1e-6, f, rng)
        t = np.arange(m.current_a.size) * m.dt_s
        paths.append(tmp_path / f"cal{k}.csv")
        write_trace(paths[-1], {"t_s": t, "current_A": m.current_a, "voltage_V": m.voltage_v}, {"preload_force_n": f})
    m = plant.measure(17.5, LH_UM * 1e-6, 28.0, rng)
    write_trace(tmp_path / "new.csv", {"t_s": np.arange(m.current_a.size) * m.dt_s, "current_A": m.current_a,
                                       "voltage_V": m.voltage_v}, {"preload_force_n": 28.0})
    run = [sys.executable, "-m", "estimator"]
    r = subprocess.run([*run, "calibrate", "--electrical", *map(str, paths), "--out", str(tmp_path / "inj.toml")],
                       capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert "mV after" in r.stdout
    r = subprocess.run([*run, "identify", str(tmp_path / "new.csv"), "--params", str(tmp_path / "inj.toml"), "--json"],
                       capture_output=True, text=True, timeout=300, cwd=REPO)
    est = json.loads(r.stdout)
    assert est["status"] == "ok" and abs(est["lh_um"] - LH_UM) < 0.2
    r = subprocess.run([*run, "calibrate", "--electrical", str(paths[0]), "--tolerance", "-1"],
                       capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "error" in r.stderr


def test_a_batch_the_structure_cannot_explain_is_reported_unusable():
    """Hysteresis and a series resistance are not structural parameters: no parameter set explains
    such a batch, and the calibration says so instead of returning parameters as if they fitted."""
    rng = np.random.default_rng(4)
    plant = Plant(PlantConfig(window_s=200e-6, mismatch=True))
    injections = []
    for f, nu in BATCH[:4]:
        m = plant.measure(nu, LH_UM * 1e-6, f, rng)
        injections.append(Injection(m.current_a, m.voltage_v, m.dt_s, f))
    res = calibrate_electrical(injections, max_iterations=8, max_restarts=0)
    assert not res.adequate and res.misfit_z > 4
    assert any("does not explain the batch" in w for w in res.warnings)


def test_cli_serial_selects_one_injectors_traces(tmp_path):
    """--serial keeps the traces whose metadata name that injector; one trace cannot be calibrated."""
    _, plant, rng = _part_and_plant(3)
    paths = []
    for k, (serial, (f, nu)) in enumerate(zip("AAB", BATCH)):
        m = plant.measure(nu, LH_UM * 1e-6, f, rng)
        paths.append(tmp_path / f"t{k}.csv")
        write_trace(paths[-1], {"t_s": np.arange(m.current_a.size) * m.dt_s, "current_A": m.current_a,
                                "voltage_V": m.voltage_v}, {"preload_force_n": f, "serial": serial})
    r = subprocess.run([sys.executable, "-m", "estimator", "calibrate", "--electrical", *map(str, paths), "--serial", "B"],
                       capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 2 and "at least two usable injections, got 1" in r.stderr


def _warm_up_sequence(plant: Plant, rng: np.random.Generator, n: int):
    """A series injector warming up (N_u 15.5 -> 20 N/V) while the rail pressure cycles (28-300 N)."""
    for k in range(n):
        f = BATCH[k % len(BATCH)][0]
        m = plant.measure(15.5 + 4.5 * k / max(n - 1, 1), LH_UM * 1e-6, f, rng)
        yield Injection(m.current_a, m.voltage_v, m.dt_s, f, 0, k, float("nan"), 2.0 * k)


def test_self_calibration_adopts_the_injectors_own_model_and_then_it_is_ok():
    """The tracker collects a mismatched injector's injections; once they span the preload forces it
    calibrates, tests the result on held-out injections, adopts it and re-acquires: from then on the
    injector is explained (no model_mismatch) and its L_h is within 0.1 µm."""
    from estimator.ident.learning.selfcal import SelfCalConfig
    from estimator.ident.tracking.tracker import Tracker

    _, plant, rng = _part_and_plant(5)
    tracker = Tracker(self_calibration=SelfCalConfig(window=10))
    results, states = [], []
    for inj in _warm_up_sequence(plant, rng, 24):
        results.append(tracker.update(inj))
        states.append(tracker.calibration[0].state)
    adopted = states.index("adopted")
    assert 8 <= adopted <= 14 and states[adopted - 1] == "learning"
    assert tracker.calibration[0].held_out_chi2 > 25 and 0 in tracker.own_pools
    assert all(r.status.value != "ok" for r in results[:adopted])
    after = results[adopted + 2:]
    assert all(r.status.value in ("ok", "unconfirmed") for r in after)
    assert max(abs(r.lh_m * 1e6 - LH_UM) for r in after) < 0.1


def test_self_calibration_stays_idle_on_an_injector_the_model_explains():
    from estimator.ident.learning.selfcal import SelfCalConfig
    from estimator.ident.tracking.tracker import Tracker

    rng = np.random.default_rng(8)
    tracker = Tracker(self_calibration=SelfCalConfig(window=5))
    for inj in _warm_up_sequence(Plant(PlantConfig(window_s=200e-6)), rng, 8):
        assert tracker.update(inj).status.value in ("ok", "unconfirmed")
    assert tracker.calibration[0].state == "idle" and not tracker.own_pools


@pytest.mark.slow
def test_cli_track_self_calibrate(tmp_path):
    _, plant, rng = _part_and_plant(5)
    paths = []
    for inj in _warm_up_sequence(plant, rng, 14):
        paths.append(tmp_path / f"inj{inj.counter:02d}.csv")
        write_trace(paths[-1], {"t_s": np.arange(inj.current_a.size) * inj.dt_s, "current_A": inj.current_a,
                                "voltage_V": inj.voltage_v}, {"preload_force_n": inj.f_open_n, "time_s": inj.time_s})
    r = subprocess.run([sys.executable, "-m", "estimator", "track", "--self-calibrate", *map(str, paths)],
                       capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(line) for line in r.stdout.splitlines()]
    states = [line["learning"]["state"] for line in lines]
    assert states[0] == "learning" and states[-1] == "adopted", states
    assert lines[-1]["status"] in ("ok", "unconfirmed") and abs(lines[-1]["filtered"]["lh_um"] - LH_UM) < 0.1


def test_the_uncertainty_a_calibration_leaves_is_in_every_sigma_and_is_not_averaged_away(tmp_path):
    """A calibrated parameter set carries how uncertain it leaves N_u and L_h ([calibration] in its
    file). A single estimate's σ includes it, and so does the filtered σ after many injections: the
    same for every injection of the injector, averaging must not shrink it below it."""
    from dataclasses import replace

    from estimator.ident.fit.idle_stroke import identify
    from estimator.ident.tracking.tracker import Tracker
    from estimator.model.fast_sim import FastSimulator
    from estimator.model.parameters import CalibrationUncertainty

    exact = load_nominal()
    calibrated = replace(exact, calibration=CalibrationUncertainty(nu_rel_sigma=0.002, lh_sigma_m=0.08e-6))
    path = tmp_path / "cal.toml"
    path.write_text(calibrated.to_toml("calibrated"))
    assert "[calibration]" in path.read_text() and InjectorParameters.from_toml(path) == calibrated
    plant = Plant(PlantConfig())
    rng = np.random.default_rng(21)
    injections = []
    for k in range(40):
        m = plant.measure(17.5, LH_UM * 1e-6, 28.0, rng)
        injections.append(Injection(m.current_a, m.voltage_v, m.dt_s, 28.0, 0, k, float("nan"), 0.1 * k))
    plain, cal = identify(injections[0], FastSimulator(exact)), identify(injections[0], FastSimulator(calibrated))
    assert cal.lh_m == pytest.approx(plain.lh_m)
    assert cal.sigma_lh_m ** 2 == pytest.approx(plain.sigma_lh_m ** 2 + 0.08e-6 ** 2, rel=1e-6)
    assert cal.sigma_nu ** 2 == pytest.approx(plain.sigma_nu ** 2 + (cal.nu_n_per_v * 0.002) ** 2, rel=1e-6)
    tracker = Tracker(sim=FastSimulator(calibrated))
    results = [tracker.update(inj) for inj in injections]
    assert all(r.status.value == "ok" for r in results[5:])
    assert min(r.sigma_lh_m for r in results[5:]) >= 0.08e-6
    assert min(r.sigma_nu for r in results[5:]) >= 17.5 * 0.002 * 0.99
    with pytest.raises(ParameterError, match="calibration"):
        InjectorParameters.from_mapping({**calibrated.to_mapping(), "calibration": {"nu_rel_sigma": -1.0}})


def _nominal_batch(current_noise_a: float) -> list[Injection]:
    from sim_bench.hardware.plant import AdcConfig
    rng = np.random.default_rng(21)
    plant = Plant(PlantConfig(window_s=200e-6, adc=AdcConfig(current_noise_a=current_noise_a)))
    out = []
    for f, nu in BATCH:
        m = plant.measure(nu, LH_UM * 1e-6, f, rng)
        out.append(Injection(m.current_a, m.voltage_v, m.dt_s, f))
    return out


def test_the_pull_of_the_measured_currents_noise_on_the_chain_is_in_its_sigma(monkeypatch):
    """The simulated voltage is driven by the measured current, whose noise a U filter plus an equal I
    skew smooth away: an exact injector's chain comes out at about 0.2 µs each at 0.02 A of current
    noise. Its reported standard deviation includes that pull; without it the chain was beyond four
    of them."""
    from estimator.ident.learning import electrical

    batch = _nominal_batch(0.02)
    res = calibrate_electrical(batch)
    # the preload forces it was calibrated over, which its valve motion was checked at
    f = [inj.f_open_n for inj in batch]
    assert (res.params.calibration.preload_lo_n, res.params.calibration.preload_hi_n) == (min(f), max(f))
    for name, sd in res.chain_sigma_us.items():
        assert abs(getattr(res.params.chain, name) * 1e6) <= 3 * sd, (name, getattr(res.params.chain, name), sd)
    monkeypatch.setattr(electrical, "current_noise_a", lambda current: 0.0)   # the pull left out
    biased = calibrate_electrical(batch)
    assert any(abs(getattr(biased.params.chain, n) * 1e6) > 3 * sd for n, sd in biased.chain_sigma_us.items())


def test_noise_gain_and_current_noise():
    from estimator.ident.fit.adequacy import current_noise_a
    from estimator.ident.learning.electrical import noise_gain

    dt = 0.5e-6
    assert noise_gain(0.0, 0.0, dt) == 1.0
    assert noise_gain(0.0, 0.25e-6, dt) == pytest.approx(0.5)          # half a sample: (1/2)^2 + (1/2)^2
    assert noise_gain(0.0, 0.5e-6, dt) == pytest.approx(1.0)           # a whole sample moves, smooths nothing
    assert 0.3 < noise_gain(0.53e-6, 0.0, dt) < 0.7 and noise_gain(2e-6, 0.0, dt) < noise_gain(0.5e-6, 0.0, dt)
    rng = np.random.default_rng(4)
    t = np.arange(400)
    ripple = 4.3 + 0.3 * np.abs((t % 16) - 8) / 8                      # an 8 µs triangle, as the bench amplifier's
    assert current_noise_a(ripple + 0.01 * rng.standard_normal(t.size)) == pytest.approx(0.01, rel=0.3)   # the corners: 0.0125


def _write_life(tmp_path, life, n, prefix, stated_preload_n=None):
    paths = []
    for inj, _m, truth in life.injections(n):
        t = np.arange(inj.current_a.size) * inj.dt_s
        paths.append(tmp_path / f"{prefix}{truth['k']}.csv")
        write_trace(paths[-1], {"t_s": t, "current_A": inj.current_a, "voltage_V": inj.voltage_v},
                    {"preload_force_n": inj.f_open_n if stated_preload_n is None else stated_preload_n})
    return paths


@pytest.mark.slow
def test_cli_refuses_a_batch_without_writing_a_file_and_flags_a_part_beyond_tolerance(tmp_path):
    """A hysteresis part whose traces all state one preload force (the rail pressure wandered 28-300 N):
    no model explains it, with a hysteresis element or without: exit 1, 'refused' on stderr, no
    parameter file. The same part's true traces: calibrated with a hysteresis element, written to its
    file. A part with a mounting stiffness 15-20 % off: its file is written and the JSON names the
    parameter out_of_tolerance."""
    from sim_bench.benches.refusal_bench import part_life

    run = [sys.executable, "-m", "estimator", "calibrate", "--electrical", "--hysteresis"]
    part = (1.0, "prandtl-ishlinskii")
    wrong = _write_life(tmp_path, part_life(2000, hysteresis=part), 16, "w", stated_preload_n=150.0)
    r = subprocess.run([*run, *map(str, wrong), "--out", str(tmp_path / "w.toml")], capture_output=True, text=True,
                       timeout=600, cwd=REPO)
    assert r.returncode == 1 and "refused" in r.stderr and not (tmp_path / "w.toml").exists()
    hyst = _write_life(tmp_path, part_life(2000, hysteresis=part), 16, "h")
    r = subprocess.run([*run, *map(str, hyst), "--out", str(tmp_path / "h.toml")], capture_output=True, text=True,
                       timeout=600, cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert "[hysteresis]" in (tmp_path / "h.toml").read_text()
    life = part_life(4001, beyond=True)
    beyond = _write_life(tmp_path, life, 24, "b")
    r = subprocess.run([*run, *map(str, beyond), "--out", str(tmp_path / "b.toml"), "--json", str(tmp_path / "b.json")],
                       capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "b.json").read_text())
    worst = max(life.parts[0].factors, key=lambda n: abs(life.parts[0].factors[n] - 1))
    assert doc["out_of_tolerance"] == [worst] and "out_of_tolerance:" in r.stdout
    assert (tmp_path / "b.toml").exists()


# the plateau-current scales a closed loop drove a short-high amplifier's injector with (injections 13-40)
_CLOSED_LOOP_SCALES = (0.900, 0.901, 0.863, 0.878, 0.913, 0.901, 0.922, 0.935, 0.916, 0.917, 0.948, 0.942, 0.949,
                       0.925, 0.968, 0.933, 0.963, 0.941, 0.961, 0.929, 0.930, 0.955, 0.987, 0.991, 0.966, 0.960,
                       0.929)


@pytest.mark.slow
def test_a_second_start_at_an_earlier_model_finds_the_deeper_minimum():
    """A refinement window of a series part at three corners of its tolerance, driven by its own
    correction (scales 0.86-0.99 of a short-high amplifier's drive): fitted from the tables alone the
    calibration settles in a minimum with the valve mass 26 % off (on the bench its stroke came out
    0.24 µm long); started also from a model near the part (here its own structure, where a refinement
    starts from the model in use) it finds the deeper minimum there."""
    from estimator.model.parameters import STRUCTURAL
    from sim_bench.benches.compensation import lot_spec
    from sim_bench.hardware.series_life import draw_lot

    life = draw_lot(8, 2, lot_spec("short-high"))[4]
    rng = np.random.default_rng(life.seed)
    walk = life.preload_walk(40, np.random.default_rng(life.seed + 1))
    batch = []
    for k in range(38):
        scale = _CLOSED_LOOP_SCALES[k - 13] if k >= 13 else None
        m, _ = life.measure(k, 150, rng, None if scale is None else (lambda f, s=scale: s), walk[k])
        if k >= 16:
            batch.append(Injection(m.current_a, m.voltage_v, m.dt_s, m.f_open_n))
    true = life.parts[0].params

    def worst(params: InjectorParameters) -> float:
        return max(abs(getattr(getattr(params, t), n) / getattr(getattr(true, t), n) - 1) for t, n in STRUCTURAL)

    alone = calibrate_electrical(batch)
    both = calibrate_electrical(batch, also_from=true)
    assert both.chi2 < alone.chi2 - 5.0
    assert worst(alone.params) > 0.15 > 0.10 > worst(both.params)


def test_a_hot_part_beyond_the_tables_n_u_range_is_learned_with_its_range_widened():
    """A series part run hot, its N_u 21.3-22.0 N/V beyond Table 1's 15-21 (its own structure within
    ±10 %): the batch presses on the range's edge, so it is fitted again with the range widened by the
    tolerance. The learned model carries that range; its N_u, in its own structure's terms, follows the
    truth to within 0.05 N/V of one common shift, its L_h within 0.2 µm, and a new hot injection is
    ``ok`` with it, not at a search bound."""
    from dataclasses import replace

    from estimator.ident.fit.idle_stroke import identify
    from estimator.model.fast_sim import FastSimulator

    part, _plant, rng = _part_and_plant(7)
    params = part.params
    hot = replace(params, psa=params.psa.with_nu_range(15.0, 23.0))     # the plant simulates beyond 21
    plant = Plant(PlantConfig(window_s=200e-6), hot)
    batch = ((28.0, 21.3), (60.0, 21.5), (100.0, 21.8), (150.0, 22.0), (220.0, 21.4), (300.0, 21.9))
    injections = []
    for f, nu in batch:
        m = plant.measure(nu, LH_UM * 1e-6, f, rng)
        injections.append(Injection(m.current_a, m.voltage_v, m.dt_s, f))
    res = calibrate_electrical(injections)
    assert res.adequate
    assert 21.0 < 22.1 < res.params.psa.nu_max_n_per_v <= 21.0 * 1.1 + 1e-9
    assert res.params.psa.nu_min_n_per_v == load_nominal().psa.nu_min_n_per_v
    kept = InjectorParameters.from_mapping(res.params.to_mapping())      # as the daemon's state keeps it
    assert kept.psa.nu_max_n_per_v == res.params.psa.nu_max_n_per_v
    shift = res.nu_n_per_v - np.array([nu for _f, nu in batch])
    assert np.ptp(shift) < 0.05 and np.all(np.abs(res.lh_um - LH_UM) < 0.2)
    m = plant.measure(21.7, LH_UM * 1e-6, 120.0, rng)
    inj = Injection(m.current_a[:201], m.voltage_v[:201], m.dt_s, 120.0)
    own = identify(inj, FastSimulator(res.params, m.dt_s))
    assert own.status.value == "ok" and abs(own.nu_n_per_v - 21.7 - np.mean(shift)) < 0.05
    assert abs(own.lh_m * 1e6 - LH_UM) < 0.2
