"""Choosing the hysteresis element: adopted only where both grids of plays explain the batch, and its
stated uncertainty covers what the two grids say differently."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import estimator.ident.learning.element as element
from estimator.ident.learning.electrical import HYSTERESIS_THRESHOLDS_C, ElectricalCalibration
from estimator.ident.learning.element import GRIDS_C, INTERLEAVED_THRESHOLDS_C, disagreement_of, widened
from estimator.model.chain import MeasurementChain
from estimator.model.parameters import load_nominal
from tests.ident.test_hysteresis_learning import _batch


def _cal(adequate: bool, z: float, chi2: float, lh_um: float = 4.0, hysteresis: bool = True) -> ElectricalCalibration:
    n = 3
    return ElectricalCalibration(load_nominal(), (), np.ones(0), np.ones(0), np.full(n, 18.0), np.full(n, lh_um),
                                 0.1, 0.1, adequate=adequate, misfit_z=z, chi2=chi2, hysteresis=hysteresis)


@pytest.fixture
def fits(monkeypatch: pytest.MonkeyPatch) -> dict:
    """calibrate_electrical replaced by canned results: the paper's model's, then one per grid."""
    canned: dict = {}

    def fake(injections, base=None, *, hysteresis=False, thresholds_c=HYSTERESIS_THRESHOLDS_C, **kw):
        canned.setdefault("calls", []).append(thresholds_c if hysteresis else None)
        return canned["grids"][GRIDS_C.index(thresholds_c)] if hysteresis else canned["plain"]
    monkeypatch.setattr(element, "calibrate_electrical", fake)
    monkeypatch.setattr(element, "widened", lambda best, other, injs, chain, window_s: replace(best, warnings=["widened"]))
    return canned


def test_a_part_the_paper_explains_is_never_calibrated_with_an_element(fits: dict) -> None:
    fits["plain"] = _cal(True, 2.0, 100.0, hysteresis=False)
    res = element.calibrate_with_hysteresis_if_needed([], hysteresis=True)
    assert res is fits["plain"] and fits["calls"] == [None]


def test_the_element_is_adopted_only_where_both_grids_explain_the_batch(fits: dict) -> None:
    fits["plain"] = _cal(False, 40.0, 900.0, hysteresis=False)
    fits["grids"] = [_cal(True, 3.0, 120.0), _cal(True, 2.5, 110.0, lh_um=4.1)]
    res = element.calibrate_with_hysteresis_if_needed([], hysteresis=True)
    assert fits["calls"] == [None, HYSTERESIS_THRESHOLDS_C, INTERLEAVED_THRESHOLDS_C]
    assert res.adequate and res.lh_um[0] == 4.1 and res.warnings == ["widened"]   # the better fit, widened

    fits["grids"] = [_cal(True, 7.4, 120.0), _cal(False, 20.2, 400.0)]
    res = element.calibrate_with_hysteresis_if_needed([], hysteresis=True)
    assert not res.adequate and res.misfit_z == 20.2
    assert "one grid of plays only" in res.refusal and res.refusal in res.warnings

    fits["grids"] = [_cal(False, 60.0, 2000.0), _cal(False, 50.0, 1900.0)]
    res = element.calibrate_with_hysteresis_if_needed([], hysteresis=True)
    assert res is fits["plain"]            # neither comes nearer: the refusal names the paper's model's miss
    fits["grids"][1] = _cal(False, 11.0, 500.0)
    assert element.calibrate_with_hysteresis_if_needed([], hysteresis=True) is fits["grids"][1]


def test_the_widened_uncertainty_covers_the_grids_disagreement() -> None:
    """Two calibrations of the same part 0.2 µm apart on every L_h: the adopted one states at least
    that, and the valve's stroke and opening it predicts carry the difference too."""
    injs, truth = _batch(4, 11)
    nu = np.array([t[0] for t in truth])
    lh = np.array([t[1] for t in truth])
    a = ElectricalCalibration(load_nominal(), (), np.ones(0), np.ones(0), nu, lh, 0.1, 0.1)
    b = replace(a, lh_um=lh + 0.2)
    d = disagreement_of(a, b, [inj.window(200e-6) for inj in injs])
    assert d.lh_sigma_m == pytest.approx(0.2e-6, rel=1e-9) and d.nu_rel_sigma == 0.0
    assert 0.002 < d.stroke_rel_sigma < 0.1 and 0.0 < d.opening_sigma_s < 20e-6
    own = replace(a.params.calibration, lh_sigma_m=0.05e-6, stroke_rel_sigma=0.003)
    res = widened(replace(a, params=replace(a.params, calibration=own)), b, injs, a.params.chain, 200e-6)
    cal = res.params.calibration
    assert cal.lh_sigma_m == pytest.approx(np.hypot(0.05e-6, 0.2e-6), rel=1e-9)
    assert cal.stroke_rel_sigma == pytest.approx(np.hypot(0.003, d.stroke_rel_sigma), rel=1e-9)
    assert cal.opening_sigma_s == pytest.approx(d.opening_sigma_s, rel=1e-9)
    assert "disagree on L_h by 0.200 µm" in res.warnings[-1]


def test_the_disagreement_is_taken_over_the_injections_the_calibration_fitted(monkeypatch: pytest.MonkeyPatch) -> None:
    """A batch where one injection comes with the chain already undone: the calibration puts every
    injection through the chain, and the grids' disagreement is judged on those same injections (the
    per-injection N_u and L_h are indexed by them), not on the raw ones."""
    injs, truth = _batch(3, 12)
    chain = MeasurementChain(u_filter_tau_s=1e-6, i_filter_tau_s=0.5e-6, i_skew_s=0.2e-6)   # an amplifier's
    mixed = [injs[0].through_chain(chain), *injs[1:]]
    seen: list = []
    monkeypatch.setattr(element, "disagreement_of", lambda a, b, batch: seen.extend(batch) or a.params.calibration)
    cal = ElectricalCalibration(load_nominal(), (), np.ones(0), np.ones(0), np.array([t[0] for t in truth]),
                                np.array([t[1] for t in truth]), 0.1, 0.1)
    widened(cal, cal, mixed, chain, 200e-6)
    assert len(seen) == 3 and all(inj.chain_corrected for inj in seen)
    np.testing.assert_array_equal(seen[1].current_a, injs[1].through_chain(chain).window(200e-6).current_a)
