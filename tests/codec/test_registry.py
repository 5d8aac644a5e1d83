"""One source of truth: the record classes are the codec's registry, the automaton's
constants come from dynamics, the bench scenarios carry their targets."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import cantools
import pytest

from estimator.codec.errors import ContractError
from estimator.codec.ingest import Counters
from estimator.codec.records import (
    CONTRACT,
    HEARTBEAT_COUNTERS,
    REGISTRY,
    Codec,
    Command,
    EstimatorStatus,
    Record,
    load_database,
)

from ..conftest import REPO

DBC = REPO / "dbc" / "injector.dbc"

NEW_MESSAGE = '''
BO_ 560 InjectorHealth: 8 Estimator
 SG_ InjectorId : 0|3@1+ (1,0) [0|7] ""  Tester
 SG_ DriftRate : 8|16@1- (0.001,0) [-32.768|32.767] "um/h"  Tester
'''


@dataclass(frozen=True)
class InjectorHealth(Record):
    """A message that is not in the product: added by one class and its DBC lines."""

    injector_id: int
    drift_um_per_h: float
    MESSAGE: ClassVar[str] = "InjectorHealth"
    SIGNALS: ClassVar[dict[str, str]] = {"injector_id": "InjectorId", "drift_um_per_h": "DriftRate"}
    OUTPUT: ClassVar[bool] = True


def _dbc_with_new_message(tmp_path):
    text = DBC.read_text()
    text = text.replace("\nBO_ 768 SimTruth", NEW_MESSAGE + "\nBO_ 768 SimTruth", 1)
    text = text.replace('BA_ "VFrameFormat" BO_ 544 0;', 'BA_ "VFrameFormat" BO_ 544 0;\nBA_ "VFrameFormat" BO_ 560 0;')
    path = tmp_path / "extended.dbc"
    path.write_text(text)
    return path


def test_a_new_message_needs_the_dbc_and_one_class(tmp_path):
    registry = (*REGISTRY, InjectorHealth)
    codec = Codec(load_database(_dbc_with_new_message(tmp_path)), registry=registry)
    frame = codec.encode(InjectorHealth(3, -1.25))
    assert frame.arbitration_id == 560 and codec.decode(frame) == InjectorHealth(3, -1.25)
    assert 560 in codec.output_ids()
    # without its DBC lines the class is a contract violation, named
    with pytest.raises(ContractError, match="message InjectorHealth missing"):
        Codec(load_database(DBC), registry=registry)


def test_the_contract_is_the_registry():
    assert set(CONTRACT) == {rt.MESSAGE for rt in REGISTRY}
    for rt in REGISTRY:
        assert set(CONTRACT[rt.MESSAGE].signals) == set(rt.SIGNALS.values()) | set(rt.CODEC_SIGNALS)
    assert CONTRACT["EstimateState"].classic


def test_command_enum_matches_the_dbc_value_table():
    db = cantools.database.load_file(str(DBC))
    choices = db.get_message_by_name("EstimatorCommand").get_signal_by_name("Command").choices
    assert {int(k): str(v) for k, v in choices.items()} == {c.value: c.name.lower() for c in Command}


def test_counters_and_heartbeat_share_one_field_list():
    c = Counters()
    for name in HEARTBEAT_COUNTERS:
        assert getattr(c, name) == 0 and name in EstimatorStatus.SIGNALS
    assert "accepted" in HEARTBEAT_COUNTERS and "queue_depth" not in HEARTBEAT_COUNTERS
    c.reject("order")
    assert c.rejected_missing == 1 and c.reasons == {"order": 1}
    with pytest.raises(ValueError):
        c.reject("no-such-reason")


def test_a_bench_scenario_without_targets_cannot_be_registered():
    from sim_bench.hardware import scenarios

    with pytest.raises(ValueError, match="no targets"):
        scenarios.register(scenarios.Scenario("untargeted", None))
    with pytest.raises(ValueError, match="twice"):
        scenarios.register(scenarios.SCENARIOS["nominal"])
    assert "untargeted" not in scenarios.SCENARIOS
    assert all(isinstance(sc.targets, scenarios.BenchTargets) for sc in scenarios.SCENARIOS.values())


def test_cli_scenario_choices_come_from_the_registry(capsys):
    from sim_bench.cli import build_parser
    from sim_bench.hardware import scenarios

    parser = build_parser()
    for argv in (["bench", "--scenario", "no-such"], ["node", "--scenario", "no-such"]):
        with pytest.raises(SystemExit):
            parser.parse_args(argv)
        err = capsys.readouterr().err
        assert all(name in err for name in scenarios.SCENARIOS)
    assert parser.parse_args(["bench", "--scenario", "all"]).scenario == "all"


def test_the_kernel_runs_the_automaton_of_dynamics():
    import numpy as np

    from estimator.model import dynamics as dyn
    from estimator.model import kernel
    from estimator.model.automaton import build_automaton
    from estimator.model.fast_sim import FastSimulator

    sim = FastSimulator()
    aut = build_automaton(dyn.build_structure(sim.params), dyn.Z_SCALE)
    for got, want in zip(sim.automaton, aut):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(aut.region_mode, dyn.REGION_MODE)
    assert (kernel.NZ, kernel.NX, kernel.STATUS_OK) == (dyn.NZ, dyn.NX, dyn.STATUS_OK)
    # the kernel's output rows are dynamics.output_rows in scaled units
    nu = np.array([15.3, 18.0, 20.9])
    cand = kernel._candidates(sim._model, np.zeros((3, 4), dtype=np.int64), np.zeros((3, 4)), nu, np.full(3, 3e-6),
                              np.full(3, 28.0), np.full((3, dyn.NZ), np.nan), np.zeros(3, dtype=np.int64))
    np.testing.assert_array_equal(cand.cout, dyn.output_rows(sim.params, nu) / dyn.Z_SCALE)
