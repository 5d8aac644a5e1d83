"""The lot-life scenario's verdicts on hysteresis parts (sim_bench.benches.lot_life): a part of the
learned element's own form must be learned with it; another shape may stay honestly refused."""

from __future__ import annotations

from types import SimpleNamespace

from sim_bench.benches.lot_life import FROM, _score_life


def _life(shape: str | None) -> SimpleNamespace:
    return SimpleNamespace(position=1, swap_at=None, beyond=[False], lh_um=[3.0], hysteresis=(1.0, shape) if shape else None,
                           parts=[SimpleNamespace(describe=lambda: "a part")])


def _out(err_um: float, status: str, n: int = FROM + 10) -> list[dict]:
    return [{"k": k, "lh_um": 3.0 + err_um, "lh_true_um": 3.0, "sigma_lh_um": 1.0, "status": status,
             "learning": "refused", "flagged": [], "beyond": False} for k in range(n)]


def test_a_refused_hysteresis_part_is_judged_by_its_status_and_its_shape():
    seconds = [0.001]
    bw = _score_life(_life("bouc-wen"), _out(0.8, "model_mismatch"), seconds, element=False)
    assert bw["failures"] == [] and bw["element"] is False       # refused, never ok: honest
    pi = _score_life(_life("prandtl-ishlinskii"), _out(0.8, "model_mismatch"), seconds, element=False)
    assert any("not learned with the element" in f for f in pi["failures"])
    learned = _score_life(_life("bouc-wen"), _out(0.8, "model_mismatch"), seconds, element=True)
    assert any("filtered L_h" in f for f in learned["failures"])   # learned: held to the L_h target
    ok_off = _score_life(_life("bouc-wen"), _out(0.8, "ok"), seconds, element=False)
    assert any("ok while" in f for f in ok_off["failures"])
    plain = _score_life(_life(None), _out(0.8, "model_mismatch"), seconds)
    assert any("filtered L_h" in f for f in plain["failures"])
