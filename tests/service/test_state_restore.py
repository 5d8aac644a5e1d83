"""State files that crash or poison: seeded fuzz over types, shapes and ranges of every entry.

A bad entry is dropped with one warning, never restored and never written back (the original file
is kept as ``.rejected``); a bad file never stops the daemon; what is restored can be updated."""

from __future__ import annotations

import copy
import json
import logging
import random

import pytest

from estimator.ident.config import TrackerConfig
from estimator.ident.tracking.tracker import Tracker
from estimator.service.config import DaemonConfig
from estimator.service.daemon import Daemon
from estimator.service.state_store import FORMAT, VERSION, load_states, save_states

from ..helpers import measured


@pytest.fixture(scope="module")
def good_entry() -> dict:
    t = Tracker(TrackerConfig())
    for k in range(4):
        inj, _ = measured(17.2, 3.1, 500 + k, window_s=100e-6)
        t.update(inj)
    return t.states[0].to_dict()


def write(path, injectors) -> None:
    path.write_text(json.dumps({"format": FORMAT, "version": VERSION, "saved_at": 0, "injectors": injectors}))


def daemon(tmp_path) -> Daemon:
    return Daemon(DaemonConfig(bus="virtual:unused", state_dir=tmp_path))


@pytest.mark.parametrize("injectors", [[1, 2], "x", 5, None, {"0": 1}, {"0": []}, {"zero": {}}, {"9": {}}])
def test_bad_injectors_never_stop_the_daemon(tmp_path, injectors, good_entry):
    write(tmp_path / "estimator-state.json", injectors)
    d = daemon(tmp_path)
    d.restore()                       # no exception: a bad file is reported and ignored
    assert d.tracker.states == {}


@pytest.mark.parametrize("field, value, why", [
    ("accepted", "many", "accepted"), ("x", [100, 500, 0, 0.06, 0], "N_u"), ("x", [17.0, 14.9, 0, 0.06, 0], "L_h"),
    ("x", [32.77, 32.77, 0, 0.06, 0], "N_u"), ("x", [17.0, 3.0, 50.0, 0.06, 0], "drift rate"),
    ("x", [17.0, 3.0, 0, 0.06, 0.5], "wear rate"),
    ("p", [[1e6, 0, 0, 0, 0], [0, 1, 0, 0, 0], [0, 0, 1e-4, 0, 0], [0, 0, 0, 1e-4, 0], [0, 0, 0, 0, 1e-6]], "caps"),
    ("temperature_c", 1e6, "temperature"), ("updates", 2 ** 60, "count"),
])
def test_poisoned_entry_is_dropped_once_and_never_written_back(tmp_path, good_entry, caplog, field, value, why):
    bad = copy.deepcopy(good_entry)
    bad[field] = value
    path = tmp_path / "estimator-state.json"
    write(path, {"0": good_entry, "3": bad})
    d = daemon(tmp_path)
    with caplog.at_level(logging.WARNING):
        d.restore()
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "injector 3" in warnings[0].getMessage() and why in warnings[0].getMessage()
    assert set(d.tracker.states) == {0}
    d.persist()
    saved = json.loads(path.read_text())["injectors"]
    assert set(saved) == {"0"}                                # never written back
    kept = json.loads((tmp_path / "estimator-state.json.rejected").read_text())["injectors"]
    assert set(kept) == {"0", "3"}                            # nothing lost for a post-mortem
    inj, _ = measured(17.2, 3.1, 600, window_s=100e-6)
    assert d.tracker.update(inj).status.value in ("ok", "unconfirmed", "uncertain")


def mutations(rng: random.Random, entry: dict) -> dict:
    """One to three random changes: a field's type, shape, value, or presence."""
    e = copy.deepcopy(entry)
    junk = [None, True, -1, 0, 1, 2 ** 63, 1e308, -1e308, float("nan"), float("inf"), "1", [], [1], [[1]], {},
            [1, 2], [1, 2, 3, 4], [[1, 2], [3, 4]], [[0.0] * 4] * 4, [[float("nan")] * 4] * 4]
    for _ in range(rng.randint(1, 3)):
        key = rng.choice(sorted(e))
        roll = rng.random()
        if roll < 0.15:
            del e[key]
        elif roll < 0.6:
            e[key] = rng.choice(junk)
        elif isinstance(e[key], list) and e[key]:
            flat = e[key] if not isinstance(e[key][0], list) else e[key][rng.randrange(len(e[key]))]
            flat[rng.randrange(len(flat))] = rng.choice([1e9, -1e9, float("nan"), 30.0, -30.0, "x", None])
        elif isinstance(e[key], (int, float)) and not isinstance(e[key], bool):
            e[key] = rng.choice([e[key] * 1e6, -e[key] - 1, float("inf")])
    return e


def test_state_file_fuzz(tmp_path, good_entry):
    """500 seeded mutations: load never raises; whatever is restored is physically possible and updates."""
    rng = random.Random(7)
    restored = dropped = 0
    inj, _ = measured(17.2, 3.1, 700, window_s=100e-6)
    for k in range(500):
        path = tmp_path / f"s{k}.json"
        write(path, {"0": mutations(rng, good_entry)})
        states, problem = load_states(path)
        t = Tracker(TrackerConfig())
        problems = t.restore(states)
        if t.states:
            restored += 1
            st = t.states[0]
            if st.initialized:
                assert 14.9 <= st.x[0] <= 21.1 and -2.0 <= st.x[1] <= 10.0
            res = t.update(inj)                       # the worker would run exactly this
            assert res.status is not None
        else:
            dropped += 1
            assert problem or problems
    assert dropped > 300 and restored > 10


def test_round_trip_of_a_good_file(tmp_path, good_entry):
    t = Tracker(TrackerConfig())
    states, _ = load_states(_saved(tmp_path, good_entry))
    assert t.restore(states) == [] and set(t.states) == {0, 5}


def test_a_state_beyond_the_tables_n_u_range_is_kept_for_an_injector_whose_model_allows_it(tmp_path, good_entry):
    """An injector learned hot has a model whose N_u range reaches beyond the tables' 21.1 N/V: its
    state at 22 N/V is physically possible with that model, and dropped only without it."""
    from dataclasses import replace

    from estimator.ident.tracking.tracker import TrackerState
    from estimator.model.parameters import load_nominal

    hot = copy.deepcopy(good_entry)
    hot["x"][0] = 22.0
    base = load_nominal()
    own = replace(base, psa=base.psa.with_nu_range(15.0, 23.1))
    assert Tracker(TrackerConfig()).restore({0: TrackerState.from_dict(hot)}) != []
    t = Tracker(TrackerConfig())
    assert t.restore({0: TrackerState.from_dict(hot)}, {0: own}) == [] and t.states[0].x[0] == 22.0


def _saved(tmp_path, entry):
    from estimator.ident.tracking.tracker import TrackerState
    path = tmp_path / "estimator-state.json"
    st = TrackerState.from_dict(entry)
    save_states(path, {0: st, 5: st})
    return path


def test_learned_drives_are_kept_and_a_bad_one_is_named_and_skipped(tmp_path, good_entry):
    """The standard drives learned per injector are saved beside the states; on load a record that is
    not a drive is dropped and named, the others kept."""
    import numpy as np

    from estimator.drive.standard import AmplifierDrive
    from estimator.ident.tracking.tracker import TrackerState
    from estimator.service.state_store import load_all

    path = tmp_path / "estimator-state.json"
    drive = AmplifierDrive(np.concatenate([np.linspace(0, 8, 40), np.full(200, 8.0), np.zeros(60)]), 0.5e-6, "learned")
    save_states(path, {0: TrackerState.from_dict(good_entry)}, drives={0: drive, 3: drive})
    states, _cals, _learning, drives, problems = load_all(path)
    assert set(states) == {0} and set(drives) == {0, 3} and problems == []
    assert np.allclose(drives[3].current_a, drive.current_a)
    doc = json.loads(path.read_text())
    doc["drives"]["3"]["current_a"] = "%%%"
    path.write_text(json.dumps(doc))
    _states, _cals, _learning, drives, problems = load_all(path)
    assert set(drives) == {0} and len(problems) == 1 and "standard drive of injector 3" in problems[0]


def test_the_daemon_restores_and_persists_the_learned_drives(tmp_path, good_entry):
    """A restarted daemon corrects an injector whose drive it had learned without learning it again,
    and writes the drive back with its state."""
    import numpy as np

    from estimator.drive.standard import AmplifierDrive
    from estimator.ident.tracking.tracker import TrackerState
    from estimator.service.state_store import load_all

    path = tmp_path / "estimator-state.json"
    drive = AmplifierDrive(np.concatenate([np.linspace(0, 8, 40), np.full(200, 8.0), np.zeros(60)]), 0.5e-6, "learned")
    save_states(path, {0: TrackerState.from_dict(good_entry)}, drives={3: drive})
    d = daemon(tmp_path)
    d.restore()
    comp = d.processor.compensator
    assert comp is not None and comp.drive_of(3) is not None and comp.drive_of(4) is None
    d.persist()
    assert set(load_all(path)[3]) == {3}
