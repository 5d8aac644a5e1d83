"""Drive corrections (estimator.drive.correction): the default target reached anywhere in the operating
range, held and computed again without an ok estimate, carried across idle by the preload table, kept
within the limits they were computed with."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from estimator.drive.correction import Correction, DriveCompensator, DriveTarget, respond
from estimator.ident.simulators import SimulatorPool

COV = np.diag([0.01 ** 2, 0.05 ** 2])   # (N/V)², µm²


def compensator(**kw) -> DriveCompensator:
    """A compensator that takes the amplifier's drive to be the built-in trapezoid (no current given)."""
    return DriveCompensator(DriveTarget(amplifier_drive="trapezoid", **kw))


@pytest.fixture(scope="module")
def sim():
    return SimulatorPool().get(0.5e-6)


@pytest.mark.parametrize("nu", [15.0, 21.0])
@pytest.mark.parametrize("lh_um", [0.5, 9.5])
@pytest.mark.parametrize("preload_n", [28.0, 300.0])
def test_the_default_target_is_reached_anywhere_in_the_operating_range(sim, nu, lh_um, preload_n):
    """A cold part with no idle stroke at idle and a warm one with a long idle stroke at full load reach
    the same stroke and opening instant within the default limits (the nominal injector's stroke, the
    earlier default, is out of reach for the second)."""
    comp = compensator()
    target_stroke, target_opening = comp.target_at(sim)
    c = comp.update(0, True, sim, nu, lh_um, COV, preload_n, sim)
    stroke, opening = respond(sim, c.scale, nu, lh_um, preload_n)
    assert c.valid and not c.held and not c.at_limit, c
    assert abs(stroke - target_stroke) < 0.01 and abs(c.offset_us + opening - target_opening) < 0.2
    assert abs(c.stroke_um - stroke) < 0.01 and abs(c.opening_us - (c.offset_us + opening)) < 0.2
    if nu == 21.0 and lh_um == 9.5 and preload_n == 300.0:
        old = compensator(default="nominal", scale_limits=(0.7, 1.5)).update(0, True, sim, nu, lh_um, COV, preload_n, sim)
        assert old.at_limit


def test_the_nominal_rule_leaves_the_nominal_injector_as_it_is(sim):
    c0 = compensator(default="nominal").update(1, True, sim, 16.4, 3.0, COV, 28.0, sim)
    assert abs(c0.scale - 1.0) < 1e-4 and abs(c0.offset_us) < 0.01


def test_sigma_follows_the_estimate_covariance(sim):
    comp = compensator()
    small = comp.update(0, True, sim, 16.0, 5.0, COV / 4, 100.0, sim)
    comp.forget(0)
    large = comp.update(0, True, sim, 16.0, 5.0, COV, 100.0, sim)
    assert large.sigma_stroke_um == pytest.approx(2 * small.sigma_stroke_um, rel=0.02)
    # the stroke moves about one to one with L_h
    assert 0.04 < large.sigma_stroke_um < 0.07


def test_without_an_ok_estimate_the_correction_is_computed_again_for_the_next_preload(sim):
    """After an estimate that is not ok the correction comes from the last ok estimate, at the new
    preload force: across idle, where the opening instant bends, the first-order carry of the last
    correction would open the valve microseconds off."""
    comp = compensator()
    target_stroke, target_opening = comp.target_at(sim)
    none = comp.update(3, False, sim, 16.0, 5.0, COV, 100.0, sim)
    assert not none.valid and not none.held and none.at(100.0) == (1.0, 0.0)   # the standard drive
    good = comp.update(3, True, sim, 16.0, 5.0, COV, 150.0, sim)
    held = comp.update(3, False, sim, 16.0, 7.5, COV, 31.0, sim)               # a mismatched estimate
    assert held.held and held.valid and held.preload_n == 31.0 and "not ok" in held.reason
    stroke, opening = respond(sim, held.scale, 16.0, 5.0, 31.0)                # from the ok estimate, not 7.5 µm
    assert abs(stroke - target_stroke) < 0.02 and abs(held.offset_us + opening - target_opening) < 0.3
    carried = replace(good, table=())                                          # the earlier rule
    scale, offset = carried.at(31.0)
    _, opening_carried = respond(sim, scale, 16.0, 5.0, 31.0)
    assert abs(offset + opening_carried - target_opening) > 1.0
    again = comp.update(3, True, sim, 16.0, 7.5, COV, 100.0, sim)
    assert again.valid and not again.held and again.scale > good.scale        # more idle stroke, more current
    comp.forget(3)
    assert not comp.last(3).valid


def test_the_preload_table_carries_a_correction_across_idle_within_a_microsecond(sim):
    """An amplifier applying the published correction at another preload force (Correction.at, as the
    DriveCorrectionTable rows give it) opens the valve within 0.5 µs and 0.05 µm of the target at every
    preload force; the per-kN sensitivities alone are microseconds off near idle."""
    comp = compensator()
    target_stroke, target_opening = comp.target_at(sim)
    for k in range(25):
        c = comp.update(0, True, sim, 19.0, 6.0, COV, 100.0 + k, sim)
    assert len(c.table) == len(DriveTarget().table_preloads_n)
    worst, worst_plain = (0.0, 0.0), 0.0
    for f in np.linspace(28.0, 300.0, 69):
        scale, offset = c.at(f)
        stroke, opening = respond(sim, scale, 19.0, 6.0, f)
        worst = (max(worst[0], abs(stroke - target_stroke)), max(worst[1], abs(offset + opening - target_opening)))
        scale, offset = replace(c, table=()).at(f)
        worst_plain = max(worst_plain, abs(offset + respond(sim, scale, 19.0, 6.0, f)[1] - target_opening))
    assert worst[0] < 0.05 and worst[1] < 0.5, worst
    assert worst_plain > 1.0


def test_each_table_row_states_the_sigma_of_what_it_gives_at_its_preload_force():
    """A model calibrated at 60-250 N: every row of the table states the σ of the stroke and opening
    instant it gives, as a correction computed at that row's preload force states them, the rows below
    60 N with the motion the model extrapolates there. ``sigma_at`` gives the correction's own σ at its
    preload force and the rows' elsewhere (an amplifier on the bus applies the rows at idle, where the
    correction published at full load states a fraction of it)."""
    from estimator.model.fast_sim import FastSimulator
    from estimator.model.parameters import CalibrationUncertainty, load_nominal

    plain = SimulatorPool().get(0.5e-6)
    spanned = FastSimulator(replace(load_nominal(), calibration=CalibrationUncertainty(
        preload_lo_n=60.0, preload_hi_n=250.0)), 0.5e-6)
    comp = compensator()
    for _ in range(35):    # every row computed with this model and estimate
        c = comp.update(0, True, spanned, 17.0, 5.0, COV, 150.0, plain)
    assert len(c.table) == len(DriveTarget().table_preloads_n) and all(len(row) == 5 for row in c.table)
    for f, scale, offset, sigma_s, sigma_o in c.table:
        there = compensator().update(0, True, spanned, 17.0, 5.0, COV, f, plain)
        assert scale == pytest.approx(there.scale, abs=2e-3) and offset == pytest.approx(there.offset_us, abs=0.05)
        assert sigma_s == pytest.approx(there.sigma_stroke_um, rel=0.05, abs=2e-3), f
        assert sigma_o == pytest.approx(there.sigma_opening_us, rel=0.05, abs=0.01), f
    by_f = {row[0]: row for row in c.table}
    assert by_f[28.0][4] > 3 * by_f[100.0][4]                   # the opening instant bends toward idle
    assert c.sigma_at(150.0) == (c.sigma_stroke_um, c.sigma_opening_us)
    assert c.sigma_at(28.0) == pytest.approx(by_f[28.0][3:], rel=0.05)
    assert c.sigma_at(28.0)[1] > 3 * c.sigma_opening_us
    assert replace(c, table=()).sigma_at(28.0) == (c.sigma_stroke_um, c.sigma_opening_us)


def test_a_held_correction_states_the_uncertainty_of_its_carried_n_u(sim):
    """Held for ten injections, a correction carries N_u on by the last ok estimate's drift rate; a
    warm-up's rate falls as it goes on, so the carried N_u may be off by a good share of the carry:
    its σ grows with the carry, and covers the stroke the drive gives when N_u rose half as far."""
    comp = compensator()
    comp.update(1, True, sim, 17.0, 5.0, COV, 150.0, sim, rate_n_per_v_s=0.1, time_s=0.0)
    first = comp.update(1, False, sim, 17.0, 5.0, COV, 150.0, sim, time_s=1.0)
    late = comp.update(1, False, sim, 17.0, 5.0, COV, 150.0, sim, time_s=10.0)
    assert first.held and late.held
    assert late.sigma_stroke_um > 3 * first.sigma_stroke_um
    stroke, _ = respond(sim, late.scale, 17.5, 5.0, 150.0)             # N_u rose by 0.5, not the carried 1.0
    assert abs(stroke - late.stroke_um) < 2 * late.sigma_stroke_um < 4 * abs(stroke - late.stroke_um)


def _fresh_table(sim, nu: float, lh_um: float) -> tuple:
    comp = compensator()
    for _ in range(35):    # every row simulated at this estimate
        c = comp.update(0, True, sim, nu, lh_um, COV, 100.0, sim)
    return c.table


def test_table_rows_follow_a_moved_estimate_and_a_row_without_a_derivative_is_simulated_at_once(sim):
    """After the estimate moves (L_h by 1 µm: the opening instant by about 4 µs) the next table's rows,
    carried by their derivatives, are within 0.6 µs of a table simulated anew at every row (kept at
    their last simulation they were 4.6 µs off until each row's turn came). A row whose opening
    derivative is no derivative (taken across a bend of the opening instant) and would carry it by
    tens of microseconds is simulated again at once."""
    from estimator.drive import row_carry

    comp = compensator()
    for _ in range(35):
        comp.update(0, True, sim, 19.0, 6.0, COV, 100.0, sim)
    c = comp.update(0, True, sim, 19.3, 7.0, COV, 100.0, sim)
    fresh = _fresh_table(sim, 19.3, 7.0)
    assert max(abs(a[2] - b[2]) for a, b in zip(c.table, fresh)) < 0.6
    assert max(abs(a[1] - b[1]) for a, b in zip(c.table, fresh)) < 0.003
    rows = comp._injectors[0].rows
    for _ in range(35):    # every row simulated at the new estimate
        comp.update(0, True, sim, 19.3, 7.0, COV, 100.0, sim)
    bent = 12
    comp._injectors[0].grid[bent, row_carry.DO_DNU] = 400.0           # µs per N/V: across a jump of the opening
    c = comp.update(0, True, sim, 19.31, 7.0, COV, 100.0, sim)
    assert abs(c.table[bent][2] - _fresh_table(sim, 19.31, 7.0)[bent][2]) < 0.1
    assert abs(rows[bent].response.d_nu[1]) < 50.0                  # taken afresh


def test_table_rows_take_their_derivatives_at_the_drive_they_settle_at(sim):
    """A row computed for the first time takes its derivatives at the scale the target asks for, not at
    the standard drive's 1.0: carried by them over a 0.1 µm move of L_h (no row moved far enough to be
    simulated), every row's offset is within 0.03 µs of a table simulated anew (taken at 1.0, rows
    settling at 0.75–0.9 missed by up to 0.11 µs: a third of their move)."""
    for nu, lh in ((17.0, 3.0), (19.0, 6.0)):
        comp = compensator()
        for _ in range(5):   # every row computed once, four an injection
            comp.update(0, True, sim, nu, lh, COV, 100.0, sim)
        c = comp.update(0, True, sim, nu, lh + 0.1, COV, 100.0, sim)
        fresh = _fresh_table(sim, nu, lh + 0.1)
        assert max(abs(a[2] - b[2]) for a, b in zip(c.table, fresh)) < 0.03, (nu, lh)


def test_a_far_row_whose_derivatives_hold_costs_one_simulation_not_six(sim, monkeypatch):
    """A row the estimate moved beyond ``CARRY_OPENING_US`` is simulated at once; its derivatives are
    taken again only where that simulation shows they did not hold (before, always: six simulations
    a row instead of one or two)."""
    import estimator.drive.correction as corr_mod

    comp = compensator()
    for _ in range(5):
        comp.update(0, True, sim, 17.0, 3.0, COV, 100.0, sim)
    rows = []
    real = corr_mod.respond

    def counted(*a, **kw):   # the table's simulations (the correction's own are at 100 N)
        rows.extend([a[4]] if a[4] != 100.0 else [])
        return real(*a, **kw)
    monkeypatch.setattr(corr_mod, "respond", counted)
    c = comp.update(0, True, sim, 17.0, 3.3, COV, 100.0, sim)    # opening instants move by about 1.3 µs
    assert 1 <= len(rows) <= 2 * corr_mod.FAR_ROWS, rows
    monkeypatch.setattr(corr_mod, "respond", real)
    fresh = _fresh_table(sim, 17.0, 3.3)
    assert max(abs(a[2] - b[2]) for a, b in zip(c.table, fresh)) < 0.15


def test_the_limits_hold_and_say_so(sim):
    comp = compensator(scale_limits=(0.9, 1.1), stroke_um=14.0)
    c = comp.update(0, True, sim, 15.0, 1.0, COV, 28.0, sim)
    assert c.at_limit and c.scale == pytest.approx(0.9) and c.stroke_um > c.target_stroke_um + 1.0
    assert c.at(28.0)[0] >= 0.9 and c.scale_limits == (0.9, 1.1)     # the limits it was computed with
    stroke, _ = respond(sim, 0.9, 15.0, 1.0, 28.0)
    assert abs(c.stroke_um - stroke) < 0.01                           # what the limited drive gives


def test_a_configured_target_and_absurd_ones():
    sim = SimulatorPool().get(0.5e-6)
    c = compensator(stroke_um=20.0, opening_us=45.0).update(0, True, sim, 16.0, 4.0, COV, 60.0, sim)
    stroke, opening = respond(sim, c.scale, 16.0, 4.0, 60.0)
    assert abs(stroke - 20.0) < 0.01 and abs(c.offset_us + opening - 45.0) < 0.2
    for bad in ({"scale_limits": (1.2, 0.8)}, {"offset_limits_us": (5.0, -5.0)}, {"stroke_um": -1.0},
                {"opening_us": math.nan}, {"default": "median"}, {"table_preloads_n": (100.0, 50.0)},
                {"drive_tolerance": 0.0}, {"learn_injections": 0}, {"part_margin": 0.7},
                {"operating_lh_um": (5.0, 1.0)}):
        with pytest.raises(ValueError):
            DriveTarget(**bad)
    with pytest.raises(ValueError, match="widen scale_limits"):   # no stroke every part reaches
        compensator(scale_limits=(0.7, 1.5)).target_at(sim)


def test_to_dict_has_no_nan():
    d = Correction().to_dict()
    assert d["stroke_um"] is None and d["scale"] == 1.0 and d["valid"] is False
    d = Correction(valid=True, table=((28.0, 1.0, 2.0), (300.0, 1.1, 3.0))).to_dict()
    assert json.loads(json.dumps(d))["table"] == [[28.0, 1.0, 2.0], [300.0, 1.1, 3.0]]


def test_a_swapped_part_holds_its_correction_until_it_is_learned_again():
    """A series injector whose part is swapped at injection 45: the correction comes only from ok
    estimates (never from a mismatched one), is held through the swap and derived again for the new
    part once it is learned, and then drives the new part's valve to the target."""
    from estimator.ident.measurement import Injection
    from estimator.ident.status import Status
    from estimator.pipeline import build_pipeline
    from estimator.service.config import DaemonConfig
    from sim_bench.hardware.series_life import LotSpec, draw_lot

    life = draw_lot(2, 2, LotSpec(swap_at=45, swapped=(1,)))[1]
    assert abs(life.lh_um[0] - life.lh_um[1]) > 2.0            # the new part needs another drive
    _, _, processor, _ = build_pipeline(DaemonConfig())
    rng, walk = np.random.default_rng(life.seed), life.preload_walk(111, np.random.default_rng(life.seed + 1))
    target_stroke, _ = processor.compensator.target_at(SimulatorPool().get(0.5e-6))
    rows, last = [], None
    for k in range(110):
        scale_for = (lambda f, c=last: c.at(f)[0]) if last is not None and last.valid else None
        m, _truth = life.measure(k, 110, rng, scale_for, walk[k])
        pub = processor.estimate(Injection(m.current_a, m.voltage_v, m.dt_s, m.f_open_n, 1, k, math.nan, float(k)),
                                 walk[k + 1])
        c = pub.correction
        rows.append((k, pub.result.status, c.valid, c.held, c.scale, m.stroke_m * 1e6))
        last = c
        if pub.result.status != Status.OK:
            assert c.held or not c.valid, f"injection {k}: a correction from a {pub.result.status} estimate"
    before = [r for r in rows if 30 <= r[0] < 45 and r[2] and not r[3]]
    assert before, "no correction for the first part"
    scale_before = before[-1][4]
    after = [r for r in rows if r[0] >= 45 and r[2] and not r[3]]
    held = [r for r in rows if 45 <= r[0] < after[0][0]] if after else []
    assert held and all(r[3] for r in held)                    # held: from the old part's last ok estimate
    assert after and abs(after[-1][4] - scale_before) > 0.01   # derived again for the new part
    settled = [r[5] for r in rows[-15:]]
    assert max(abs(s - target_stroke) for s in settled) < 0.3


def test_a_calibrations_stated_motion_uncertainty_is_in_the_sigma():
    """A parameter set that states what its uncertainty leaves in the valve's motion: the correction's
    σ adds it to what the estimate's covariance gives (stroke relative, opening instant absolute)."""

    from estimator.model.fast_sim import FastSimulator
    from estimator.model.parameters import CalibrationUncertainty, load_nominal

    plain = SimulatorPool().get(0.5e-6)
    stated = FastSimulator(replace(load_nominal(), calibration=CalibrationUncertainty(
        stroke_rel_sigma=0.01, opening_sigma_s=0.5e-6)), 0.5e-6)
    a = compensator().update(0, True, plain, 16.0, 5.0, COV, 100.0, plain)
    b = compensator().update(0, True, stated, 16.0, 5.0, COV, 100.0, plain)
    assert b.sigma_stroke_um ** 2 == pytest.approx(a.sigma_stroke_um ** 2 + (0.01 * b.stroke_um) ** 2, rel=1e-3)
    assert b.sigma_opening_us ** 2 == pytest.approx(a.sigma_opening_us ** 2 + 0.5 ** 2, rel=1e-3)


def test_below_the_preload_forces_a_model_was_calibrated_over_sigma_covers_its_extrapolation_to_idle():
    """A model calibrated at 60-250 N and used at 30 N: the whole motion it extrapolates from 60 N
    down is in σ (the valve's own spring and pressure balance decide it there, and the voltage hardly
    sees them); at 100 N, and above 250 N, σ is what the calibration states; a parameter set that does
    not state its preload forces adds nothing."""
    from estimator.model.fast_sim import FastSimulator
    from estimator.model.parameters import CalibrationUncertainty, ParameterError, load_nominal

    plain = SimulatorPool().get(0.5e-6)
    spanned = FastSimulator(replace(load_nominal(), calibration=CalibrationUncertainty(
        preload_lo_n=60.0, preload_hi_n=250.0)), 0.5e-6)
    for f in (100.0, 280.0):
        a = compensator().update(0, True, plain, 16.0, 5.0, COV, f, plain)
        b = compensator().update(0, True, spanned, 16.0, 5.0, COV, f, plain)
        assert b.sigma_stroke_um == pytest.approx(a.sigma_stroke_um) and b.sigma_opening_us == a.sigma_opening_us
    a = compensator().update(0, True, plain, 16.0, 5.0, COV, 30.0, plain)
    b = compensator().update(0, True, spanned, 16.0, 5.0, COV, 30.0, plain)
    s60, o60 = respond(plain, b.scale, 16.0, 5.0, 60.0)
    assert b.scale == a.scale and b.stroke_um == a.stroke_um
    assert b.sigma_stroke_um ** 2 == pytest.approx(a.sigma_stroke_um ** 2 + (b.stroke_um - s60) ** 2,
                                                   rel=1e-3)
    assert b.sigma_opening_us ** 2 == pytest.approx(
        a.sigma_opening_us ** 2 + (b.opening_us - b.offset_us - o60) ** 2, rel=1e-3)
    assert b.sigma_opening_us > a.sigma_opening_us + 0.4          # the opening instant bends toward idle
    with pytest.raises(ParameterError):
        CalibrationUncertainty(preload_lo_n=250.0, preload_hi_n=60.0)


def test_the_motion_uncertainty_replaces_the_share_of_n_u_and_l_h_it_stands_for():
    """An injector estimated with a parameter set that leaves 0.2 µm in L_h but states 0.1 % in the
    stroke: its published σ(L_h) is at least 0.2 µm, yet the correction's σ of the stroke is not built
    from it (the stroke moves about one to one with L_h): the stated figure stands for that share. A
    model learned from a first window only is not trusted with that statement until its refinement."""

    from estimator.drive.correction import correction_after
    from estimator.ident.learning.selfcal import CalibrationStatus
    from estimator.ident.measurement import Injection
    from estimator.ident.status import Learning
    from estimator.ident.tracking.tracker import Tracker
    from estimator.model.drive import STANDARD_AMPLITUDE_A, StandardDrive
    from estimator.model.fast_sim import FastSimulator
    from estimator.model.parameters import CalibrationUncertainty, load_nominal
    from sim_bench.hardware.plant import Plant, PlantConfig

    params = replace(load_nominal(), calibration=CalibrationUncertainty(nu_rel_sigma=0.005, lh_sigma_m=0.2e-6,
                                                                        stroke_rel_sigma=0.001))
    unstated = replace(params, calibration=replace(params.calibration, stroke_rel_sigma=0.0))
    plant = Plant(PlantConfig(window_s=200e-6))   # the whole charge: the truth the correction predicts
    first_window = CalibrationStatus(Learning.MONITORING, source="learned", refined=False)
    refined = replace(first_window, refined=True)
    cases = ((params, None, lambda s: s < 0.06), (unstated, None, lambda s: s > 0.15),
             (params, first_window, lambda s: s > 0.15), (params, refined, lambda s: s < 0.06))
    for stated, status, expect in cases:
        rng = np.random.default_rng(7)
        tracker = Tracker(sim=FastSimulator(stated))
        learning = _Statuses({0: status}) if status is not None else None
        comp = compensator()
        c = Correction()
        for k in range(14):   # driven with each correction: the scale reaches levels the model was checked at
            drive = StandardDrive(STANDARD_AMPLITUDE_A * c.scale) if c.valid else None
            m = plant.measure(17.5, 3e-6, 100.0, rng, drive)
            inj = Injection(m.current_a, m.voltage_v, m.dt_s, 100.0, 0, k, math.nan, 0.1 * k)
            res = tracker.update(inj)
            if k >= 7:
                tracker.learning = learning   # the statuses the correction reads, set after the update
                c = correction_after(comp, tracker, inj, res)
                tracker.learning = None
        assert res.status.value == "ok" and res.sigma_lh_m >= 0.2e-6
        assert c.valid and not c.trust_limited and expect(c.sigma_stroke_um), (status, c.sigma_stroke_um)


class _Statuses:
    """Stands in for a tracker's learning, of which the correction reads only the statuses."""

    def __init__(self, status: dict) -> None:
        self.status = status


def test_the_sigma_covers_the_injection_to_injection_jitter_and_one_odd_injection_does_not_blow_it_up(sim):
    """The estimator's own prediction of each injection (from its measured current) scatters by 0.3 µs
    around what the correction predicted: σ of the opening grows to cover it; one injection 30 µs off
    (a part swapped under the same id) moves it by a bounded step; a new model measures it anew."""
    from estimator.drive.standard import AmplifierDrive

    plant_current = AmplifierDrive.trapezoid().samples(0.5e-6, 200e-6)

    def driven(jitter_us: float) -> tuple[DriveCompensator, Correction]:
        comp = compensator()
        rng = np.random.default_rng(1)
        c = comp.update(0, True, sim, 18.0, 4.0, COV, 100.0, sim, current_a=plant_current, dt_s=0.5e-6,
                        this_preload_n=100.0)
        for _ in range(40):
            predicted = (c.stroke_um + jitter_us / 10 * rng.standard_normal(),
                         c.opening_us - c.offset_us + jitter_us * rng.standard_normal())
            c = comp.update(0, True, sim, 18.0, 4.0, COV, 100.0, sim, current_a=c.scale * plant_current,
                            dt_s=0.5e-6, this_preload_n=100.0, predicted=predicted)
        return comp, c

    quiet = driven(0.0)[1].sigma_opening_us   # the same corrections, every injection as predicted
    comp, c = driven(0.3)
    assert 0.2 < math.sqrt(c.sigma_opening_us ** 2 - quiet ** 2) < 0.45
    odd = (c.stroke_um, c.opening_us - c.offset_us + 30.0)
    c = comp.update(0, True, sim, 18.0, 4.0, COV, 100.0, sim, current_a=c.scale * plant_current, dt_s=0.5e-6,
                    this_preload_n=100.0, predicted=odd)
    assert c.sigma_opening_us < 1.0
    before = c.sigma_opening_us
    other = SimulatorPool().get(0.5e-6 * (1 + 1e-9))   # stands for another model of the injector
    c = comp.update(0, True, other, 18.0, 4.0, COV, 100.0, sim, current_a=c.scale * plant_current, dt_s=0.5e-6,
                    this_preload_n=100.0)
    assert c.sigma_opening_us ** 2 < before ** 2 - 0.2 ** 2


def test_the_correction_moves_only_as_far_as_the_model_was_checked(sim):
    """A model checked only at the standard drive: a warm part with a long idle stroke needs ≈ 1.3× its
    current, but the correction goes one ``TRUST_STEP`` beyond the checked levels, says so, publishes
    what that drive gives with σ widened for the extrapolation, and reaches the target step by step
    as ok estimates at the new levels confirm the model; an estimate that is not ok checks nothing; a
    new model starts at the level it was first seen ok at; without a measured current nothing limits."""
    from estimator.drive.correction import TRUST_STEP, respond
    from estimator.drive.standard import AmplifierDrive

    drive = AmplifierDrive.trapezoid()
    plant_current = drive.samples(0.5e-6, 200e-6)
    free = compensator().update(0, True, sim, 20.5, 8.0, COV, 100.0, sim)
    assert free.valid and not free.trust_limited and free.scale > 1.0 + TRUST_STEP + 0.03, free
    comp = compensator()
    c = comp.update(0, True, sim, 20.5, 8.0, COV, 100.0, sim, current_a=plant_current, dt_s=0.5e-6)
    assert c.trust_limited and not c.at_limit and c.scale == pytest.approx(1.0 + TRUST_STEP, abs=1e-3), c
    assert c.checked == pytest.approx((1.0, 1.0), abs=1e-3)
    assert c.stroke_um == pytest.approx(respond(sim, c.scale, 20.5, 8.0, 100.0, drive)[0], abs=0.02)
    assert c.stroke_um < c.target_stroke_um - 1.0
    assert c.sigma_stroke_um > free.sigma_stroke_um + 0.05     # the extrapolation is in σ
    steps = 0
    while c.trust_limited:
        before = c.scale
        c = comp.update(0, True, sim, 20.5, 8.0, COV, 100.0, sim, current_a=c.scale * plant_current, dt_s=0.5e-6)
        assert c.scale <= before + TRUST_STEP + 1e-6
        steps += 1
        assert steps < 6
    assert c.scale == pytest.approx(free.scale, abs=0.01) and c.stroke_um == pytest.approx(c.target_stroke_um, abs=0.02)
    assert c.sigma_stroke_um > free.sigma_stroke_um + 0.02    # not checked at this level yet
    c = comp.update(0, True, sim, 20.5, 8.0, COV, 100.0, sim, current_a=c.scale * plant_current, dt_s=0.5e-6)
    assert c.sigma_stroke_um == pytest.approx(free.sigma_stroke_um, rel=0.05)  # now it is
    checked = c.checked
    held = comp.update(0, False, sim, 20.5, 8.0, COV, 100.0, sim, current_a=1.45 * plant_current, dt_s=0.5e-6)
    assert held.held and held.checked == checked                         # not ok: nothing checked at 1.45
    other = SimulatorPool().get(0.5e-6 * (1 + 1e-9))   # stands for another model of the injector
    c = comp.update(0, True, other, 20.5, 8.0, COV, 100.0, sim, current_a=1.2 * plant_current, dt_s=0.5e-6)
    assert c.checked == pytest.approx((1.2, 1.2), abs=1e-3)


def test_a_level_the_model_failed_at_halves_the_trust_region_and_levels_that_pass_grow_it_back(sim):
    """A probe beyond the checked levels is recognised from the measured current; the estimator rejects
    it when the model fails there (``failed_probe``): the correction, held from the last ok estimate,
    stays halfway between the checked levels and the failed one, and each new level that passes
    doubles the step again (at most ``TRUST_STEP``). Nothing changes below the checked levels."""
    from estimator.drive.correction import CHECKED_SLACK, TRUST_STEP
    from estimator.drive.standard import AmplifierDrive

    current = AmplifierDrive.trapezoid().samples(0.5e-6, 200e-6)
    comp = compensator()

    def step(ok: bool, scale: float, failed: bool = False) -> Correction:
        return comp.update(0, ok, sim, 20.5, 8.0, COV, 100.0, sim, current_a=scale * current, dt_s=0.5e-6,
                           time_s=0.0, failed_probe=failed)

    c = step(True, 1.0)
    assert c.trust_limited and c.scale == pytest.approx(1.0 + TRUST_STEP, abs=1e-3)
    assert not comp.unchecked(0, sim, (1.0 + 0.5 * CHECKED_SLACK) * current, 0.5e-6)
    probe = c.scale * current
    assert comp.unchecked(0, sim, probe, 0.5e-6) and not comp.unchecked(0, None, probe, 0.5e-6)
    assert not comp.unchecked(1, sim, probe, 0.5e-6)                     # an injector with nothing checked
    c = step(False, 1.0 + TRUST_STEP, failed=True)
    assert c.held and c.scale == pytest.approx(1.0 + TRUST_STEP / 2, abs=1e-3) and c.checked == pytest.approx((1.0, 1.0))
    c = step(False, c.scale, failed=True)                                 # failed again: halved again
    assert c.scale == pytest.approx(1.0 + TRUST_STEP / 4, abs=1e-3)
    c = step(True, c.scale)                                               # passed: checked, the step doubles
    assert c.checked[1] == pytest.approx(1.0 + TRUST_STEP / 4, abs=1e-3)
    assert c.scale == pytest.approx(1.0 + TRUST_STEP / 4 + TRUST_STEP / 2, abs=1e-3)
    c = step(True, c.scale)                                               # more than a half step: the target
    assert not c.trust_limited and c.scale > 1.0 + 3 * TRUST_STEP / 4 + TRUST_STEP / 2 + 0.01
    held = step(False, 1.0, failed=True)   # not beyond the checked levels: a failure there narrows nothing
    assert held.held and held.scale == pytest.approx(c.scale, abs=1e-3)


def test_a_failed_level_within_the_slack_of_the_checked_ones_ends_the_trust_region_there(sim):
    """Halved down to within ``CHECKED_SLACK`` of the checked levels, the trust region ends at them: a
    level that close counts as checked, and the model failing there would read as a changed part. The
    correction stays at the checked level until a new model (a refinement) starts a new region."""
    from estimator.drive.correction import CHECKED_SLACK, TRUST_STEP
    from estimator.drive.standard import AmplifierDrive

    current = AmplifierDrive.trapezoid().samples(0.5e-6, 200e-6)
    comp = compensator()

    def step(ok: bool, scale: float, failed: bool = False, model=sim) -> Correction:
        return comp.update(0, ok, model, 20.5, 8.0, COV, 100.0, sim, current_a=scale * current, dt_s=0.5e-6,
                           time_s=0.0, failed_probe=failed)

    c = step(True, 1.0)
    while c.scale > 1.0 + 2 * CHECKED_SLACK:
        c = step(False, c.scale, failed=True)
    assert c.held and c.scale == pytest.approx(1.0 + TRUST_STEP / 8, abs=1e-3)
    c = step(False, c.scale, failed=True)                 # 0.0125 beyond: half of it is within the slack
    assert c.held and c.scale == pytest.approx(1.0, abs=1e-3) and c.trust_limited
    assert step(True, 1.0).scale == pytest.approx(1.0, abs=1e-3)          # no further while this model serves
    from estimator.model.fast_sim import FastSimulator

    other = FastSimulator(sim.params, 0.5e-6)            # another model of the injector
    assert step(True, 1.0, model=other).scale == pytest.approx(1.0 + TRUST_STEP, abs=1e-3)


def test_a_held_correction_near_the_top_of_the_n_u_range_steps_back_after_a_failed_probe(sim):
    """A warming part near the top of the model's N_u range: held after a failed probe, its correction
    is computed again with N_u carried by the drift rate, which overshoots the range. The carried N_u
    stays within it, so the held correction is recomputed inside the narrowed trust region; it used to
    fail ("N_u outside the range") and repeat the failed level for as long as the part was held."""
    from estimator.drive.correction import TRUST_STEP
    from estimator.drive.standard import AmplifierDrive

    current = AmplifierDrive.trapezoid().samples(0.5e-6, 200e-6)
    comp = compensator()
    top = sim.nu_range[1]
    c = comp.update(0, True, sim, top - 0.02, 8.0, COV, 200.0, sim, rate_n_per_v_s=0.05, time_s=0.0,
                    current_a=current, dt_s=0.5e-6)
    assert c.trust_limited and c.scale == pytest.approx(1.0 + TRUST_STEP, abs=1e-3)
    for k in range(1, 6):    # the probe failed, then every held injection: N_u carried 0.05-0.25 beyond
        c = comp.update(0, False, sim, math.nan, math.nan, None, 200.0, sim, time_s=float(k),
                        current_a=c.scale * current, dt_s=0.5e-6, failed_probe=True)
        assert c.held and "computed again" in c.reason, c.reason
        assert c.scale <= 1.0 + TRUST_STEP / 2 ** k + 1e-3


def test_a_steady_operating_point_is_carried_and_carries_no_error(sim, monkeypatch):
    """At a steady preload force with a slowly drifting estimate the correction is carried from its last
    simulation by its derivatives (far fewer simulations than corrections) and stays within 0.02 µm and
    0.1 µs of a correction simulated anew; a rail-pressure step is simulated."""
    import estimator.drive.correction as corr_mod

    calls = []
    counting = [False]
    real = corr_mod.respond

    def counted(*a, **kw):   # the simulations at the correction's own preload force (the table's are apart)
        calls.extend([1] if counting[0] and a[4] == 100.0 else [])
        return real(*a, **kw)
    monkeypatch.setattr(corr_mod, "respond", counted)
    comp = compensator()
    comp.update(0, True, sim, 18.0, 4.0, COV, 100.0, sim)
    for k in range(24):
        nu = 18.0 + 0.002 * k
        counting[0] = True
        c = comp.update(0, True, sim, nu, 4.0, COV, 100.0, sim)
        counting[0] = False
        fresh = compensator().update(0, True, sim, nu, 4.0, COV, 100.0, sim)
        assert c.stroke_um == pytest.approx(fresh.stroke_um, abs=0.02)
        assert c.opening_us == pytest.approx(fresh.opening_us, abs=0.1)
        assert c.scale == pytest.approx(fresh.scale, abs=0.002)
    carried = len(calls)
    assert carried <= 2, carried                   # 24 without the carry
    calls.clear()
    counting[0] = True
    comp.update(0, True, sim, 18.05, 4.0, COV, 100.0 + 50.0, sim)
    comp.update(0, True, sim, 18.05, 4.0, COV, 100.0, sim)
    assert calls, "a rail-pressure step is simulated, not carried"


def test_a_correction_made_by_name_is_the_constructors():
    """``Correction.of`` (every injection's, without the frozen dataclass's per-field ``__setattr__``)
    gives what the constructor gives, field for field, defaults included; a field it does not have is
    an error, and the result is as frozen."""
    from dataclasses import FrozenInstanceError, fields

    values = {f.name: v for f, v in zip(fields(Correction), (
        1.1, -0.4, 11.0, 60.0, 0.05, 0.2, 11.0, 60.5, 0.01, -2.0, 80.0, True, False, True, (0.6, 1.8), (-9.0, 9.0),
        "why", 1.02, ((40.0, 1.1, 0.1, 0.05, 0.3),), (0.9, 1.1), True))}
    assert len(values) == len(fields(Correction))
    assert Correction.of(**values) == Correction(**values)
    assert Correction.of(scale=1.2).__dict__ == Correction(scale=1.2).__dict__
    with pytest.raises(TypeError, match="no field bogus"):
        Correction.of(bogus=1.0)
    with pytest.raises(FrozenInstanceError):
        Correction.of(scale=1.2).scale = 1.3  # type: ignore[misc]


def test_the_estimates_noise_at_a_steady_preload_force_is_carried_but_a_preload_move_near_idle_is_not(
        sim, monkeypatch):
    """The estimate's injection-to-injection noise (L_h ±0.02 µm, moving the stroke 0.04 µm each time) at
    a steady preload force is carried by the derivatives, within 0.005 µm and 0.03 µs of a correction
    simulated anew (the stroke and the opening instant are close to linear in N_u and L_h); a preload
    force that moves the stroke 0.05 µm or the opening instant 0.2 µs near idle, where the opening
    bends, is simulated."""
    import estimator.drive.correction as corr_mod

    forces: list[float] = []
    real = corr_mod.respond

    def counted(*a, **kw):
        forces.append(a[4])
        return real(*a, **kw)
    monkeypatch.setattr(corr_mod, "respond", counted)
    comp = compensator()
    comp.update(0, True, sim, 17.0, 4.0, COV, 100.0, sim)
    forces.clear()
    for k in range(24):
        lh_um, nu = 4.0 + (0.02 if k % 2 else -0.02), 17.0 + 0.003 * k
        c = comp.update(0, True, sim, nu, lh_um, COV, 100.0, sim)
        n = len(forces)
        fresh = compensator().update(0, True, sim, nu, lh_um, COV, 100.0, sim)
        del forces[n:]
        assert c.stroke_um == pytest.approx(fresh.stroke_um, abs=0.005)
        assert c.opening_us == pytest.approx(fresh.opening_us, abs=0.03)
    assert forces.count(100.0) <= 2, forces.count(100.0)      # 26 when 0.02 µm and 0.1 µs were carried
    comp.update(0, True, sim, 17.0, 4.0, COV, 36.0, sim)
    d_f = comp._injectors[0].main.response.d_f   # the preload force's share of the move beyond its own limits,
    moved = 36.0 + min(0.05 / abs(d_f[0]), 0.2 / abs(d_f[1]))   # within the estimate's
    forces.clear()
    comp.update(0, True, sim, 17.0, 4.0, COV, moved, sim)
    assert moved in forces, "a preload move near idle is simulated, not carried"


def test_a_deferred_compensator_leaves_the_tables_simulations_to_the_idle_worker(sim, monkeypatch):
    """Deferred (the daemon's): an injection's correction simulates nothing for the preload table and
    refreshes no derivative merely due by age; :meth:`background` does both. It then holds exactly the
    table an immediate compensator computes for the same estimates, and each correction is the same
    (within the carry's second-order error once the derivatives were refreshed) but for its table, the previous estimate's. Left undone, the work runs before the
    injector's next injection."""
    import estimator.drive.correction as corr_mod

    estimates = [(17.0 + 0.01 * k, 3.0 + 0.04 * k, 90.0 + (45.0 if k % 5 == 4 else 0.0)) for k in range(40)]
    now, later = compensator(), DriveCompensator(DriveTarget(amplifier_drive="trapezoid"), deferred=True)
    counting: list[list[float] | None] = [None]
    calls: list[float] = []
    immediate: list[float] = []
    real = corr_mod.respond

    def counted(*a, **kw):   # the preload force of each simulation
        if counting[0] is not None:
            counting[0].append(a[4])
        return real(*a, **kw)
    monkeypatch.setattr(corr_mod, "respond", counted)
    before: tuple = ()
    for k, (nu, lh_um, preload_n) in enumerate(estimates):
        counting[0] = immediate if k > 8 else None    # the model's first corrections (every row new) apart
        a = now.update(0, True, sim, nu, lh_um, COV, preload_n, sim)
        counting[0] = calls if k > 8 else None
        b = later.update(0, True, sim, nu, lh_um, COV, preload_n, sim)
        counting[0] = None
        assert later.has_background
        if k < corr_mod.REFRESH_INJECTIONS:     # then the derivatives, refreshed one injection apart
            assert replace(b, table=()) == replace(a, table=()), k
        else:
            # carried from another simulation: the same within the carry's second-order error
            assert (b.scale, b.stroke_um) == pytest.approx((a.scale, a.stroke_um), abs=2e-3)
            assert b.opening_us == pytest.approx(a.opening_us, abs=1e-2)
        assert b.table == before
        while later.background():
            pass
        assert not later.has_background and later.last(0).table == a.table
        before = a.table
    own = (90.0, 135.0)     # the corrections' preload forces: the table's rows are at others
    assert all(f in own for f in calls), sorted(set(calls))
    assert sum(f not in own for f in immediate) >= 20, immediate    # what the immediate one spends on the table
    assert len(calls) < len(immediate)
    skipped = DriveCompensator(DriveTarget(amplifier_drive="trapezoid"), deferred=True)
    for nu, lh_um, preload_n in estimates[:6]:
        c = skipped.update(0, True, sim, nu, lh_um, COV, preload_n, sim)   # never idle
    assert c.table and skipped.has_background


def test_a_closed_loop_steps_back_from_a_level_its_model_fails_at_through_public_names():
    """``estimate_unchecked`` + ``correction_after``: the first injection beyond the checked levels is
    of a part the model does not explain there (standing for a model that does not hold at that
    drive): it is rejected as a failed probe, never ``model_mismatch``, the correction steps back
    halfway, and the loop goes on to the target as the levels pass."""
    from estimator import Tracker, correction_after, estimate_unchecked
    from estimator.drive.correction import TRUST_STEP
    from estimator.ident.measurement import Injection
    from estimator.ident.status import Status
    from estimator.model.drive import STANDARD_AMPLITUDE_A, StandardDrive
    from sim_bench.hardware.plant import Plant, PlantConfig
    from sim_bench.hardware.series_part import SeriesPart

    good = Plant(PlantConfig(window_s=200e-6))
    bad = Plant(PlantConfig(window_s=200e-6), SeriesPart({"psa.kg1_n_per_m": 0.99, "psa.kp_n_per_m": 1.01,
                                                          "psa.m3_kg": 0.99}).params)
    rng = np.random.default_rng(3)
    tracker, comp, c = Tracker(), compensator(), Correction()
    probed = None
    for k in range(14):
        plant = bad if c.valid and c.trust_limited and probed is None else good
        m = plant.measure(20.5, 8e-6, 100.0, rng, StandardDrive(STANDARD_AMPLITUDE_A * c.scale) if c.valid else None)
        inj = Injection(m.current_a, m.voltage_v, m.dt_s, 100.0, 0, k, math.nan, 0.1 * k)
        res = estimate_unchecked(comp, tracker, inj)
        before = c
        c = correction_after(comp, tracker, inj, res)
        assert res.status != Status.MODEL_MISMATCH
        if plant is bad:
            probed = k
            assert res.failed_probe and res.status == Status.REJECTED
            assert c.held and c.scale == pytest.approx(before.checked[1] + TRUST_STEP / 2, abs=2e-3)
    assert probed is not None and res.status == Status.OK and not c.trust_limited
    assert c.stroke_um == pytest.approx(c.target_stroke_um, abs=0.05)
