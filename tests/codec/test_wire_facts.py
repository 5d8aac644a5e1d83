"""Facts of the bus contract the DBC alone holds (status words and codes, "not measured", signal ranges), read through the codec."""

from __future__ import annotations

import pytest

from estimator.codec.database import default_dbc_path
from estimator.codec.errors import ContractError
from estimator.codec.records import Codec, InjectionHeader, load_database
from estimator.ident.status import CALIBRATION_STATES, Status


def test_every_status_and_calibration_state_has_its_own_code_and_comes_back():
    codec = Codec()
    codes = {codec.status_code(s) for s in Status}
    assert len(codes) == len(Status)
    for s in Status:
        assert codec.status_of(codec.status_code(s)) is s
        assert codec.status_code(s.value) == codec.status_code(s)
    assert codec.status_of(max(codes) + 1) is None
    assert len({codec.calibration_code(w) for w in CALIBRATION_STATES}) == len(CALIBRATION_STATES)
    assert [codec.calibration_state(codec.calibration_code(w)) for w in CALIBRATION_STATES] == list(CALIBRATION_STATES)
    sig = load_database().get_message_by_name("EstimateState").get_signal_by_name("Status")
    assert {str(v): int(k) for k, v in sig.choices.items()} == {s.value: codec.status_code(s) for s in Status}


def test_a_dbc_that_lacks_a_status_word_is_refused(tmp_path):
    text = default_dbc_path().read_text()
    assert ' 7 "model_mismatch"' in text
    dbc = tmp_path / "old.dbc"
    dbc.write_text(text.replace(' 7 "model_mismatch"', ""))
    with pytest.raises(ContractError, match="model_mismatch"):
        Codec(load_database(dbc))


def test_an_unmeasured_fuel_temperature_is_nan_in_the_record_and_the_dbcs_minimum_on_the_wire():
    codec = Codec()
    lo, hi = codec.signal_range(InjectionHeader, "fuel_temperature_c")
    sig = codec.messages[InjectionHeader].get_signal_by_name("FuelTemperature")
    assert (lo, hi) == (sig.minimum, sig.maximum)
    at_minimum = codec.encode(InjectionHeader(2, 9, 500, 201, 28.5, lo)).data
    assert codec.encode(InjectionHeader(2, 9, 500, 201, 28.5, float("nan"))).data == at_minimum
    for sent, got in ((float("nan"), None), (lo, None), (lo + 1.0, lo + 1.0), (81.0, 81.0), (hi + 40.0, hi)):
        t = codec.decode(codec.encode(InjectionHeader(2, 9, 500, 201, 28.5, sent))).fuel_temperature_c
        assert (t != t) if got is None else t == got, (sent, t)


def test_a_restored_state_holds_a_fuel_temperature_the_bus_can_carry():
    """The pipeline's tracker takes the contract's FuelTemperature range from the DBC for the states it
    restores; a library tracker without a contract only asks for a finite one."""
    from estimator.ident.tracking.tracker import Tracker, TrackerState
    from estimator.pipeline import build_tracker
    from estimator.service.config import DaemonConfig
    tracker = build_tracker(DaemonConfig())
    tracker.set_prior(4, 17.0, 3.0)
    saved = tracker.states[4].to_dict()
    lo, hi = Codec().signal_range(InjectionHeader, "fuel_temperature_c")
    for t, kept in ((hi, True), (hi + 1.0, False), (lo - 1.0, False)):
        fresh = build_tracker(DaemonConfig())
        problems = fresh.restore({4: TrackerState.from_dict({**saved, "temperature_c": t})})
        assert (4 in fresh.states) == kept and (not problems) == kept, (t, problems)
    assert Tracker().restore({4: TrackerState.from_dict({**saved, "temperature_c": hi + 1.0})}) == []
