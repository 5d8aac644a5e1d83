"""The per-injector bank of the recursive estimator (:class:`Tracker`): one state per injector id
(:mod:`estimator.ident.tracking.tracker_state`), each updated by the algorithm of
:mod:`estimator.ident.tracking.recursive`; simulators from a bounded pool; and, with learning on, each
injector's lifecycle (:class:`~estimator.ident.learning.learning.Learner`) with its own model once it has one."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from estimator.choices import ColdStart
from estimator.ident.config import TrackerConfig
from estimator.ident.estimate import rejected
from estimator.ident.fit.cost import plain_model_error
from estimator.ident.fit.idle_stroke import (
    identify,
    screen,
)
from estimator.ident.fit.search import Box
from estimator.ident.learning.electrical import beyond_bounds
from estimator.ident.learning.learning import Learner
from estimator.ident.learning.selfcal import CalibrationStatus, Calibrator, SelfCalConfig
from estimator.ident.measurement import Injection
from estimator.ident.simulators import SimulatorPool
from estimator.ident.status import Learning, Status
from estimator.ident.tracking.recursive import TrackResult, publish, update
from estimator.ident.tracking.tracker_state import TrackerState, carried_over, physical_problem
from estimator.model.drive import SAMPLE_PERIOD_S
from estimator.model.fast_sim import FastSimulator
from estimator.model.parameters import InjectorParameters

__all__ = ["TrackResult", "Tracker", "TrackerState"]


class Tracker:
    """The per-injector bank: one :class:`TrackerState` per injector id, simulators from a bounded
    pool, and (with ``self_calibration``) each injector's learning lifecycle
    (:class:`~estimator.ident.learning.learning.Learner`) with the injector's own model once it has one."""

    def __init__(self, config: TrackerConfig | None = None, sim: FastSimulator | None = None,
                 pool: SimulatorPool | None = None, self_calibration: SelfCalConfig | None = None,
                 calibrator: Calibrator | None = None, temperature_range_c: tuple[float, float] | None = None) -> None:
        self.config = config or TrackerConfig()
        #: the fuel temperatures a restored state may hold (degC; the bus contract's range, given by the
        #: pipeline; None: any finite one)
        self.temperature_range_c = temperature_range_c
        self.pool = pool if pool is not None else SimulatorPool(sim.params if sim is not None else None)
        if sim is not None:
            self.pool.add(sim)
        self.states: dict[int, TrackerState] = {}
        # learning (None: off): per injector its lifecycle and, once it has one, its own model's pool
        self.self_calibration = self_calibration
        self.own_pools: dict[int, SimulatorPool] = {}
        self.learning: Learner | None = None
        if self_calibration is not None:
            self.learning = Learner(self_calibration, self.pool.params, calibrator, self._use_model,
                                    self._model_of)
            if self.learning.calibrator.prepare is None:
                self.learning.calibrator.prepare = self.own_pool

    @property
    def calibrator(self) -> Calibrator | None:
        """Where calibrations run (None: learning is off)."""
        return self.learning.calibrator if self.learning is not None else None

    @property
    def calibration(self) -> dict[int, CalibrationStatus]:
        """Each injector's learning status (empty with learning off)."""
        return self.learning.status if self.learning is not None else {}

    @property
    def params(self) -> InjectorParameters:
        """The model parameters of every simulator."""
        return self.pool.params

    def simulator(self, dt_s: float) -> FastSimulator:
        """The fast simulator for a sample period in s (from the pool, built on first use)."""
        return self.pool.get(dt_s)

    def update(self, inj: Injection, unchecked_drive: bool = False) -> TrackResult:
        """Feed one injection of ``inj.injector_id``; returns the result. ``unchecked_drive``: it was
        driven beyond the levels the injector's model was checked at (a drive correction's probe:
        :meth:`~estimator.drive.correction.DriveCompensator.unchecked`), where a model that fails is
        rejected for that injection rather than the injector found mismatched.

        A sample period the pool refuses gives a ``rejected`` result and leaves the state alone.
        """
        if self.learning is not None:
            self.learning.collect()
            self.learning.admit(inj)
        state = self.states.get(inj.injector_id)
        if state is None:
            state = TrackerState()
        pool = self.own_pools.get(inj.injector_id, self.pool)
        refusal = pool.refusal(inj.dt_s)   # the configured periods (no build budget without a time)
        if refusal is None and not pool.has(inj.dt_s):
            # a new sample period: what needs no simulation first (nothing is built for garbage), then the budget
            refusal = screen(inj, self.config.ident) or pool.refusal(inj.dt_s, inj.time_s)
        if refusal is not None:
            return publish(None, rejected(refusal), Status.REJECTED, refusal, None, inj, False)
        new_state, result = update(state, inj, pool.get(inj.dt_s), self.config, unchecked_drive)
        self.states[inj.injector_id] = new_state
        if self.learning is not None:
            self.learning.observe(inj, result.raw.nu_n_per_v, new_state.mismatch, result.raw.mismatch,
                                  result.status, result.raw.status, result.failed_probe)
        return result

    def model_simulator(self, injector_id: int, dt_s: float) -> FastSimulator | None:
        """The simulator ``injector_id`` is estimated with at the sample period ``dt_s`` (s): its own
        model's once learned or seeded, else the configured one's; None if none is built for it."""
        return self.own_pools.get(injector_id, self.pool).built_for(dt_s)

    def nominal_simulator(self, dt_s: float) -> FastSimulator | None:
        """The configured parameters' simulator at ``dt_s`` (s), None if none is built for it."""
        return self.pool.built_for(dt_s)

    def _model_of(self, injector_id: int) -> InjectorParameters | None:
        """The injector's own parameter set, None while it is estimated with the configured one."""
        pool = self.own_pools.get(injector_id)
        return pool.params if pool is not None else None

    def _use_model(self, injector_id: int, params: InjectorParameters | None, pool: Any = None,
                   refined: bool = False) -> None:
        """Estimate ``injector_id`` with ``params`` (None: the configured ones) from now on, re-acquired
        from a cold start; ``refined``: a refinement of the same part's model, which keeps what the
        filter learned of the part (:func:`carried_over`)."""
        if params is None:
            self.own_pools.pop(injector_id, None)
        else:
            self.own_pools[injector_id] = pool if isinstance(pool, SimulatorPool) else SimulatorPool(
                params, self.pool.max_size, self.pool.periods_ns)
        old = self.states.pop(injector_id, None)
        if refined:
            self.states[injector_id] = carried_over(old)

    def own_pool(self, params: InjectorParameters, tables: dict[float, np.ndarray] | None = None) -> SimulatorPool:
        """A simulator pool for an injector's own ``params`` with its simulators' tables: those in
        ``tables`` (sample period s -> :meth:`FastSimulator.transition_table`, built elsewhere), else
        the default sample period's built here."""
        pool = SimulatorPool(params, self.pool.max_size, self.pool.periods_ns)
        for dt, table in (tables or {}).items():
            sim = FastSimulator(params, dt)
            sim.use_table(table)
            sim.kernel_handle()
            pool.add(sim)
        if not tables:
            pool.get(SAMPLE_PERIOD_S).kernel_handle()
        return pool

    def adopt(self, injector_id: int, params: InjectorParameters, pool: SimulatorPool | None = None,
              refined: bool = False) -> None:
        """Estimate ``injector_id`` with its own ``params`` from now on (re-acquired from a cold start;
        ``refined``: a refinement of the same part's model, whose temperature slope and wear rate the
        filter keeps)."""
        self._use_model(injector_id, params, pool, refined)
        if self.learning is not None:
            self.learning.adopted(injector_id)

    def seed(self, injector_id: int, params: InjectorParameters) -> None:
        """Start ``injector_id`` from its own (end-of-line) parameter set, monitored like a learned one."""
        self._use_model(injector_id, params)
        if self.learning is not None:
            self.learning.seeded(injector_id)

    def relearn(self, injector_id: int) -> None:
        """Learn the injector's model again (a new part), keeping its estimates and the model in use
        until a new one is adopted; nothing with learning off."""
        if self.learning is not None:
            self.learning.relearn(injector_id)

    def take_calibration_changes(self) -> list[tuple[int, CalibrationStatus]]:
        """The injectors whose learning status changed since the last call, with that status."""
        return self.learning.take_changes() if self.learning is not None else []

    def own_parameters(self) -> dict[int, InjectorParameters]:
        """The parameter sets adopted per injector (to persist)."""
        return {i: p.params for i, p in self.own_pools.items()}

    def restore_calibrations(self, params: dict[int, InjectorParameters],
                             statuses: dict[int, CalibrationStatus] | None = None) -> list[str]:
        """Adopt persisted parameter sets that are a calibration of this estimator's parameters (every
        structural parameter within the calibration's bounds of the base value), and the persisted
        learning statuses; one line per set dropped (that injector is learned again)."""
        problems = []
        tol = (self.self_calibration or SelfCalConfig()).tolerance
        restored = []
        for iid, p in params.items():
            far = beyond_bounds(p, self.pool.params, tol)
            if far:
                problems.append(f"injector {iid}: parameter set is not a calibration of the configured one "
                                f"({', '.join(far[:3])} beyond its bounds); it is learned again")
                continue
            self._use_model(iid, p)
            restored.append(iid)
        if self.learning is not None:
            for iid in restored:
                self.learning.adopted(iid, Learning.MONITORING)
            for iid, st in (statuses or {}).items():
                self.learning.restore(iid, st, iid in self.own_pools)
        return problems

    def restore(self, states: dict[int, TrackerState],
                own: dict[int, InjectorParameters] | None = None) -> list[str]:
        """Take restored states that are physically possible for this estimator (for an injector with
        its own parameter set in ``own``, for that set: a learned model's N_u range can be wider than
        the tables'); returns one line per state dropped (the dropped ones are gone: the next save
        will not contain them)."""
        problems = []
        for inj_id, st in states.items():
            box = self._box((own or {}).get(inj_id, self.params))
            why = physical_problem(st, self.config, box, self.temperature_range_c)
            if why is None:
                self.states[inj_id] = st
            else:
                problems.append(f"injector {inj_id}: {why}")
        return problems

    def _box(self, params: InjectorParameters) -> Box:
        """The (N_u N/V, L_h m) box an estimate with ``params`` can lie in."""
        ident = self.config.ident
        nu, lh = ident.nu_range(params), ident.lh_range(params)
        sim_lo, sim_hi = params.psa.simulation_nu_range      # what its simulators accept
        return Box(np.array([max(nu[0], sim_lo), lh[0]]), np.array([min(nu[1], sim_hi), lh[1]]))

    def warm_up(self, cold_start: bool = True) -> None:
        """Load (or compile) every compiled function an update uses, and the N_u table of the default
        sample period: a cold start and two warm updates of a simulated injection on a scratch tracker
        that shares this one's simulators (this tracker's states are not touched), and a cold start
        with the global search (what a local-first cold start falls back to). ``cold_start=False``:
        the scratch tracker starts from a prior, so the local-first cold start's fits are left out
        (another process compiles them: :mod:`estimator.pipeline.precompile`)."""
        from estimator.model.drive import SAMPLE_PERIOD_S, StandardDrive

        sim = self.simulator(SAMPLE_PERIOD_S)
        cur = StandardDrive().samples(100e-6, SAMPLE_PERIOD_S)
        res = sim.simulate(cur, np.array([16.0, 17.0, 18.0]), np.array([-0.5e-6, 2e-6, 6e-6]))
        scratch = Tracker(self.config, pool=self.pool, self_calibration=None)
        if not cold_start:
            scratch.set_prior(0, 17.0, 2.0)   # N/V, µm: the injection's own values
        for k in range(3):
            scratch.update(Injection(cur, res.voltage_v[1], SAMPLE_PERIOD_S, counter=k, time_s=0.04 * k))
        # a local-first cold start passes its check on this clean trace: load the global search's too
        identify(Injection(cur, res.voltage_v[2], SAMPLE_PERIOD_S), sim, replace(self.config.ident, cold_start=ColdStart.GLOBAL))
        # and the test of the plain model a warm update of a mismatched injector runs
        plain_model_error(res.voltage_v[0] - res.voltage_v[1], cur, SAMPLE_PERIOD_S, 0.1)

    def reset(self, injector_id: int) -> None:
        """Forget everything about one injector, its own (learned or seeded) model included: it is
        estimated with the configured model and learned again."""
        self.states.pop(injector_id, None)
        self.own_pools.pop(injector_id, None)
        if self.learning is not None:
            self.learning.forget(injector_id)

    def set_prior(self, injector_id: int, nu_n_per_v: float, lh_um: float) -> None:
        """Start one injector from a prior (N/V, µm)."""
        c = self.config
        self.states[injector_id] = TrackerState().with_prior(nu_n_per_v, lh_um, slope=c.slope_n_per_v_degc,
                                                             slope_sigma=c.slope_sigma)
