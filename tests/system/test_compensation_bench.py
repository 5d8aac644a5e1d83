"""The drive-compensation bench's verdicts (sim_bench.benches.compensation): σ judged over every lot's parts,
spreads and settling per lot."""

from __future__ import annotations

import numpy as np

from sim_bench.benches import compensation

TARGET = 22.0


def _run(bias_um: list[float], sigma_um: float, n: int = 100) -> compensation.Run:
    """A closed loop whose parts each sit ``bias_um`` off their predicted stroke (a learned model's bias)."""
    k = len(bias_um)
    predicted = np.full((k, n), TARGET)
    stroke = predicted + np.array(bias_um)[:, None]
    opening = np.full((k, n), 40.0)
    return compensation.Run(stroke, opening + 0.2, predicted, np.full((k, n), sigma_um), opening, np.full((k, n), 0.2),
                            np.ones((k, n), bool), [10] * k)



def _report(lots: list[compensation.Run]) -> dict:
    rep: dict = {"lots": [{"seed": seed, "closed": compensation.summarise(run, TARGET)} for seed, run in enumerate(lots)]}
    rep.update(compensation.pooled_z(rep["lots"]))
    return rep


def test_sigma_is_judged_over_all_the_lots_parts_not_part_by_part():
    # each part's error is a constant bias: part by part RMS(error/σ) is |bias|/σ (0.2 or 1.4), over all
    # parts sqrt(mean of squares) = 1.0
    lots = [_run([0.02, 0.14], 0.1), _run([0.14, 0.02], 0.1)]
    rep = _report(lots)
    per_part = [p["z_rms_stroke"] for lot in rep["lots"] for p in lot["closed"]["injectors"]]
    assert min(per_part) < 0.5 < 1.0 < max(per_part)
    assert abs(rep["z_rms_stroke"] - 1.0) < 1e-9
    assert not [f for f in compensation.failures(rep) if "RMS" in f]
    # σ ten times too small: confidently wrong, over the lots too
    rep = _report([_run([0.02, 0.14], 0.01), _run([0.14, 0.02], 0.01)])
    assert [f for f in compensation.failures(rep) if "stroke over the lots' parts" in f]


def test_the_bus_loops_sigma_is_judged_too():
    """σ of the bus's loop (the correction applied through its table) is judged over the lots' parts as
    the ECU's is: ten times too small there fails, though the ECU's loop covers."""
    good, small = _run([0.02, 0.14], 0.1), _run([0.14, 0.02], 0.01)
    rep = {"lots": [{"seed": 0, "closed": compensation.summarise(good, TARGET),
                     "closed_bus": compensation.summarise(small, TARGET)}]}
    rep.update(compensation.pooled_z(rep["lots"]))
    assert rep["bus_z_rms_stroke"] > 5 and abs(rep["z_rms_stroke"] - 1.0) < 1e-9
    failed = [f for f in compensation.failures(rep) if "RMS" in f]
    assert failed and all("the bus loop's" in f for f in failed)


def test_a_part_that_does_not_settle_fails_its_lot():
    late = _run([0.0, 0.0], 0.05)
    late.stroke_um[1, :60] += 1.0        # off target for 50 injections after its adoption at 10
    rep = _report([late])
    assert any(f.startswith("lot 0 (standard, closed): injector 1 settled after") for f in compensation.failures(rep))
    assert not _report([_run([0.0, 0.0], 0.05)])["lots"][0]["closed"]["injectors"][0]["overshoots"]


def test_a_correction_stopped_short_by_its_trust_region_is_not_settled_and_not_an_overshoot():
    """Injections whose correction said it stopped short of the target (``trust_limited``, its predicted
    stroke what that drive gives) delay the settling and are no overshoot; the same miss from a
    correction that claimed the target is one."""
    def stepped(flagged: bool) -> compensation.Run:
        run = _run([0.0, 0.0], 0.1)
        run.trust_limited = np.zeros(run.stroke_um.shape, bool)
        run.stroke_um[1, 14:21] -= 1.0            # a model failed at a probe: the correction steps back
        run.stroke_um[1, 23] -= 1.0
        if flagged:
            run.predicted_stroke_um[1, 14:21] -= 1.0
            run.predicted_stroke_um[1, 23] -= 1.0
            run.trust_limited[1, 14:21] = run.trust_limited[1, 23] = True
        return run

    said = compensation.summarise(stepped(True), TARGET)["injectors"][1]
    assert said["settle_injections"] == 11 and said["overshoots"] == 0
    unsaid = compensation.summarise(stepped(False), TARGET)["injectors"][1]
    assert unsaid["overshoots"] >= 1


def test_a_part_that_goes_model_mismatch_only_under_its_own_correction_fails_its_lot():
    """The same part, truths and noise: model_mismatch after adoption in the closed loop but never with
    the standard drive is the correction's doing; in both loops alike it is not."""
    def with_mismatch(at: list[int]) -> compensation.Run:
        run = _run([0.0, 0.0], 0.05)
        run.mismatch = np.zeros_like(run.applied)
        for k in at:
            run.mismatch[1, k] = True
        return run
    runs = {"open": with_mismatch([]), "closed": with_mismatch([70, 71]), "closed_bus": with_mismatch([])}
    assert compensation.own_mismatch(runs) == {"closed": [1], "closed_bus": []}
    rep = _report([runs["closed"]])
    rep["lots"][0]["own_mismatch"] = compensation.own_mismatch(runs)
    assert any("injector 1 went model_mismatch under its own correction" in f for f in compensation.failures(rep))
    runs["open"] = with_mismatch([40])
    assert compensation.own_mismatch(runs) == {"closed": [], "closed_bus": []}


def test_a_lot_with_hysteresis_parts_changes_only_their_voltage():
    """The benches' hysteresis lots: the same draws as the lot without, the named positions' parts on
    the mismatch plant (their voltage differs, their valve motion not), never beyond tolerance."""
    from sim_bench.hardware.series_life import LotSpec, draw_lot

    spec = compensation.lot_spec("standard")
    plain, hyst = draw_lot(4, 7, spec), draw_lot(4, 7, compensation.lot_spec("standard", hysteresis=True))
    marked = {pos for pos, _gain, _shape in compensation.HYSTERESIS_LOT if pos < 4}
    assert marked and [life.hysteresis is not None for life in hyst] == [i in marked for i in range(4)]
    for a, b in zip(plain, hyst):
        assert a.parts[0].factors == b.parts[0].factors and a.lh_um == b.lh_um and a.seed == b.seed
        (ma, _), (mb, _) = a.measure(0, 10, np.random.default_rng(1)), b.measure(0, 10, np.random.default_rng(1))
        assert ma.stroke_m == mb.stroke_m
        assert (np.max(np.abs(ma.voltage_v - mb.voltage_v)) > 1.0) == (b.hysteresis is not None)
    lot = draw_lot(12, 5, LotSpec(beyond_fraction=0.5, hysteresis=((2, 1.0, "bouc-wen"),)))
    assert lot[2].hysteresis == (1.0, "bouc-wen") and not lot[2].beyond[0]
