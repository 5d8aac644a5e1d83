"""Every injector learned for its whole life: the per-injector learning lifecycle.

An ECU adaptation learns by default, gated by conditions, reports its progress, raises a diagnostic
when a learned value is beyond its limits and learns again when the part is replaced. So does this
estimator, per injector id (states: :class:`~estimator.ident.status.Learning`):

``idle``
    The configured tables explain the injector. When its estimates go ``model_mismatch`` (the
    tracker's flag, with its hysteresis) it starts ``learning``.
``learning``
    Accepted injections are collected into a bounded window spanning the operating points
    (:class:`~estimator.ident.learning.selfcal.CalibrationWindow`; progress: ``batch`` and ``preload_span``).
    Should the tables explain the injector again before the window is ready, back to ``idle``.
``calibrating``
    The window was handed to the calibrator (in the daemon a low-priority process: never the
    real-time worker). It comes back ``adopted`` (the injector is re-acquired under its own model)
    or ``refused``.
``refused``
    The calibration did not explain the injector (or its held-out injections no better): the model
    in use keeps serving; a new window is started after ``retry_after`` injections, doubling with
    each refusal in a row (eight times at most), so that a part no parameter set explains does not
    keep the calibrator busy.
``adopted`` -> ``monitoring``
    The injector's own model serves; after ``confirm`` injections it is ``monitoring``. A model
    seeded from the injector's own end-of-line parameter file starts here too. A monitored model is
    refined over ``refine_window`` and then ``refine_again`` injections (the first window grows on
    from up to half its size of the injections the model was calibrated on, the second from the
    first's), and a refinement is adopted unless it explains the held-out
    injections worse than the model in use; one that fails at drive levels
    its correction leads to (failed probes) is refined over them as soon as its window holds
    :data:`PROBES_TO_REFINE` of them and ``window`` injections.
``relearning``
    The monitor is a one-sided cumulative sum over the injections' adequacy verdicts (each
    injection's own model-error test, not the tracker's smoothed flag): ``S <- max(0, S + m - k)``
    with ``m`` 1 for a mismatched injection, ``k = monitor_drift``. One mismatched injection among
    adequate ones (the test's false-alarm rate) never reaches the limit; a model that stopped
    explaining the injector (a swapped part, aging that moved the structure, a wrong parameter file)
    reaches ``monitor_limit`` within ``limit / (1 - k)`` injections. The injections seen while the sum
    grew are kept, and collection goes on while the old model keeps serving; the new calibration
    starts from the configured tables (a new part is a new draw of the lot) and from the model in use,
    the fit with the lower cost kept (a refinement too), and is adopted if it
    explains the held-out injections better than the model in use, or no worse while it moves their
    N_u beyond its uncertainty (a refinement: unless it explains them worse). A ``relearn`` command starts
    this state at once.

Every calibration compares each structural parameter with the part's tolerance
(``part_tolerance``, ``tolerance_sigmas``): ``out_of_tolerance`` names those beyond it, a diagnostic
for a tester; the model is adopted all the same (its estimates are better than the tables').
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any, NamedTuple

from estimator.ident.learning.selfcal import (
    CalibrationOutcome,
    CalibrationStatus,
    CalibrationWindow,
    Calibrator,
    InlineCalibrator,
    SelfCalConfig,
)
from estimator.ident.measurement import Injection
from estimator.ident.status import ESTIMATED, Learning, Status
from estimator.model.parameters import InjectorParameters

MAX_BACKOFF = 8      # a refused injector waits at most this many times retry_after
PROBES_TO_REFINE = 2  # failed probes in a model's refinement window that have it calibrated once it holds a
                      # learning window's worth of injections (the model has yet to learn those drive levels)


class Learner:
    """The learning lifecycle of every injector of one tracker (see the module docstring).

    ``base`` is the configured parameter set (the tables, the calibrations' prior); ``adopt`` the
    tracker's hook that swaps an injector's own model in (``None`` params: back to the tables; its
    last argument True for a refinement of the same part's model);
    ``current`` tells which parameter set an injector is estimated with now.
    """

    def __init__(self, config: SelfCalConfig, base: InjectorParameters, calibrator: Calibrator | None,
                 adopt: Callable[[int, InjectorParameters | None, Any, bool], None],
                 current: Callable[[int], InjectorParameters | None]) -> None:
        self.config = config
        self.base = base
        self.calibrator: Calibrator = calibrator if calibrator is not None else InlineCalibrator()
        self._adopt = adopt
        self._current = current
        self.status: dict[int, CalibrationStatus] = {}
        self._windows: dict[int, CalibrationWindow] = {}
        self._refine: dict[int, CalibrationWindow] = {}   # a monitored model's refinement window
        self._probes: dict[int, int] = {}   # the failed probes in it (:meth:`_probe`)
        self._running: dict[int, _Running] = {}   # each running calibration; an outcome without one is dropped
        self._basis: dict[int, CalibrationWindow] = {}   # the window the own model in use was calibrated on
        self._changed: set[int] = set()

    # ---- what the tracker calls -----------------------------------------------------------
    def collect(self) -> None:
        """Take the calibrator's finished calibrations (never waits for a running one)."""
        for out in self.calibrator.poll():
            self._finish(out)

    def admit(self, inj: Injection) -> None:
        """Before ``inj`` is estimated: a model learned over a narrow span of preload forces serves
        only that span. Carried elsewhere it was never checked and can be biased beyond its σ, so at
        a preload force beyond it the injector goes back on the tables, whose estimates say how
        little they know, and learns again from this injection on."""
        iid = inj.injector_id
        st = self.status.get(iid)
        if st is None or self._current(iid) is None or st.serves(inj.f_open_n, self.config):
            return
        self._drop_work(iid)      # a refinement running for the model too: its outcome is dropped
        self._adopt(iid, None, None, False)
        self._set(iid, replace(st, state=Learning.LEARNING, source="tables", evidence=0.0, served=0, batch=0,
                               preload_span=0.0, refined=False, refinements=0, learned_lo_n=0.0, learned_hi_n=0.0,
                               message=f"preload force {inj.f_open_n:.0f} N outside {st.learned_lo_n:.0f}-"
                                       f"{st.learned_hi_n:.0f} N, the span the model was learned over: back on "
                                       "the tables, learning again"))

    def observe(self, inj: Injection, nu: float, mismatch: bool, raw_mismatch: bool, status: Status,
                raw_status: Status, failed_probe: bool = False) -> None:
        """One update of ``inj.injector_id``: its raw N_u estimate (N/V), its tracker's model-mismatch
        flag (smoothed), its own injection's adequacy verdict, the published and the raw status.
        ``failed_probe``: rejected because the model failed at a drive level it was not checked at
        (:func:`_probe`)."""
        iid = inj.injector_id
        st = self.status.setdefault(iid, CalibrationStatus())
        if failed_probe and st.state != Learning.CALIBRATING:
            self._probe(iid, st, inj, nu)
            return
        if st.state == Learning.CALIBRATING or status == Status.REJECTED or raw_status not in ESTIMATED:
            return
        if st.state in (Learning.ADOPTED, Learning.MONITORING, Learning.RELEARNING):
            self._monitor(iid, st, inj, raw_mismatch, nu, status == Status.UNCERTAIN)
            return
        if st.state == Learning.REFUSED:
            if not mismatch:          # the model in use explains the injector again
                self._set(iid, replace(st, state=Learning.MONITORING if st.source != "tables" else Learning.IDLE,
                                       retry_in=0, batch=0, preload_span=0.0))
            elif st.retry_in > 1:
                self._set(iid, replace(st, retry_in=st.retry_in - 1))
            else:
                self._set(iid, replace(st, state=Learning.LEARNING, retry_in=0, batch=0, preload_span=0.0))
            return
        if not mismatch:
            if st.state == Learning.LEARNING:   # the tables explain this injector again
                self._windows.pop(iid, None)
                self._set(iid, replace(st, state=Learning.IDLE, batch=0, preload_span=0.0))
            return
        self._add(iid, inj, nu, Learning.LEARNING)

    def _monitor(self, iid: int, st: CalibrationStatus, inj: Injection, raw_mismatch: bool, nu: float,
                 uncertain: bool = False) -> None:
        """An own model in service: confirm it, watch it, collect while re-learning. ``uncertain``: the
        injection's published estimate is ``uncertain`` (σ(L_h) above the limit): the due refinement
        is collected from the model's adoption on and comes sooner (:meth:`_refined`)."""
        c = self.config
        evidence = max(0.0, st.evidence + (1.0 if raw_mismatch else 0.0) - c.monitor_drift)
        served = st.served + 1
        if st.state == Learning.RELEARNING:
            self._set(iid, replace(st, evidence=evidence, served=served), quiet=True)
            self._add(iid, inj, nu, Learning.RELEARNING)
            return
        state = Learning.MONITORING if st.state == Learning.ADOPTED and served >= c.confirm else st.state
        if raw_mismatch:     # keep what the sum grew on: the new window starts with it
            window = self._windows.setdefault(iid, CalibrationWindow(c.window))
            window.add(inj, nu)
        elif evidence == 0.0:
            self._windows.pop(iid, None)
            if (((state == Learning.MONITORING or uncertain) and _next_refinement(st, c)) or self._probes.get(iid)) \
                    and self._refined(iid, st, inj, nu, served, uncertain):
                return
        if evidence >= c.monitor_limit:
            self._refine.pop(iid, None)
            self._probes.pop(iid, None)
            self._set(iid, replace(st, state=Learning.RELEARNING, evidence=evidence, served=served,
                                   message=f"the model in use stopped explaining this injector (monitor "
                                           f"{evidence:.1f} >= {c.monitor_limit:g})"))
            self._add(iid, None, nu, Learning.RELEARNING)
            return
        self._set(iid, replace(st, state=state, evidence=evidence, served=served), quiet=state == st.state)

    def _probe(self, iid: int, st: CalibrationStatus, inj: Injection, nu: float) -> None:
        """An injection at a drive level the model in use failed at, never checked there: it is what
        the model has to learn, not evidence that the part changed (the monitor does not count it).
        It joins a re-learning window, or the model's refinement window, from its adoption on and
        whether or not a refinement is due. Once that window holds :data:`PROBES_TO_REFINE` of them it
        is calibrated at once together with the injections the model was calibrated on (without
        those, once it holds a learning window's worth; :meth:`_refined`): a model learned at the
        standard drive that fails where its correction leads learns those levels then, beside the
        ones it explains, not after its estimates have gone wrong there (a Prandtl–Ishlinskii part's
        first model failed at 1.05-1.15 times the standard drive, and waiting for twelve injections
        held it 24 injections from its target, against 7)."""
        if st.state == Learning.RELEARNING:
            self._add(iid, inj, nu, Learning.RELEARNING)
        elif st.state in (Learning.ADOPTED, Learning.MONITORING):
            self._probes[iid] = self._probes.get(iid, 0) + 1
            self._refined(iid, st, inj, nu, st.served + 1)

    def _refined(self, iid: int, st: CalibrationStatus, inj: Injection, nu: float, served: int,
                 uncertain: bool = False) -> bool:
        """Collect the refinement window of a monitored model; submit it once ready (True: submitted).
        A window of ten injections measures a stiffness to about 1 %; the refinement's larger window
        sharpens the model and its tolerance diagnostics, and is adopted unless it explains held-out
        injections worse than the model in use (:func:`~estimator.ident.learning.selfcal._adoptable`):
        twelve injections can leave a part's N_u scale several of its σ off. Each refinement's window
        grows on from injections already seen: the first from those the model was calibrated on (half
        its size at most, :func:`_grown_from`), the next from this one's. A Prandtl–Ishlinskii part
        refined over 24 injections still opened 0.35-0.5 µs late; refined over 60 that include them, 24
        injections sooner than over 60 new ones, it opened within 0.15 µs of its predicted instant. A
        swapped part's model, learned at its predecessor's correction, opened 0.5 µs early with σ 0.11
        µs after a refinement over 24 injections at its own correction; refined over 12 of each, 10
        injections sooner, 0.23 µs early with σ 0.13 µs.

        ``uncertain`` (the model's estimates are, :meth:`_monitor`): the window is submitted once it
        holds half a learning window of injections it was not started with. A model learned from
        twelve injections can state σ(L_h) above the limit by itself (its calibration's uncertainty,
        which averaging does not shrink): its estimates are then never ``ok`` and the part gets no
        correction until the refinement. A Prandtl–Ishlinskii part's first model stated 0.36 µm
        against 0.25; refined over 24 injections, at injection 51, 16 after the adoption, the part
        was on its target from 56; refined over 18, at 41, from 45."""
        size = _next_refinement(st, self.config) or self.config.refine_window or self.config.window
        c = replace(self.config, window=size)
        window = self._refine.get(iid)
        if window is None:
            window = self._refine[iid] = _grown_from(self._basis.get(iid), c.window)
        window.add(inj, nu)
        probed = self._probes.get(iid, 0) >= PROBES_TO_REFINE
        basis = self._basis.get(iid) if probed else None
        full = window.ready(c)
        if basis is not None:    # the levels it failed at beside those it was learned at: calibrated at once
            window = _joined(basis, window, max(size, self.config.window))
        elif not (full or (probed and window.ready(self.config)) or (uncertain and _half_fresh(window, self.config))):
            return False
        self._refine.pop(iid, None)
        after = 0 if probed else _next_refinement(replace(st, refinements=_refinements(st) + 1, refined=True),
                                                  self.config)
        if after > len(window.items):   # the next refinement's window grows on from this one's injections
            self._refine[iid] = CalibrationWindow(after, list(window.items))
        why = ("refining the model over the drive levels it failed at" if probed
               else "refining the model over a larger window" + ("" if full else ", sooner: its estimates are uncertain"))
        self._probes.pop(iid, None)
        self._set(iid, replace(st, state=Learning.CALIBRATING, served=served, evidence=0.0,
                               message=why + _narrow_note(window, c, "; ")))
        self._submit(iid, window, c, Learning.MONITORING, probed)
        return True

    def _submit(self, iid: int, window: CalibrationWindow, config: SelfCalConfig, purpose: Learning,
                probed: bool = False) -> None:
        """Hand ``window`` to the calibrator for ``purpose`` (:class:`_Running`); for ``monitoring``, as the
        refinement of the model in service it is (its adoption rule: ``CalibrationWindow.refining``)."""
        window = replace(window, refining=purpose == Learning.MONITORING, probed=probed)
        self._running[iid] = _Running(purpose, window)
        self.calibrator.submit(iid, window, self.base, config, self._current(iid))
        self.collect()

    def _add(self, iid: int, inj: Injection | None, nu: float, state: Learning) -> None:
        """Add ``inj`` to the injector's window (None: only check it); submit the window once it is ready."""
        c = self.config
        window = self._windows.setdefault(iid, CalibrationWindow(c.window))
        if inj is not None:
            window.add(inj, nu)
        st = self.status[iid]
        self._set(iid, replace(st, state=state, batch=len(window.items), preload_span=window.preload_spread()),
                  quiet=st.state == state)
        if not window.ready(c):
            return
        del self._windows[iid]
        st = self.status[iid]
        self._set(iid, replace(st, state=Learning.CALIBRATING, message=_narrow_note(window, c) or st.message))
        self._submit(iid, window, c, state)

    def _finish(self, out: CalibrationOutcome) -> None:
        iid = out.injector_id
        run = self._running.pop(iid, None)
        if run is None:   # the injector was reset while it ran: its outcome is not this injector's now
            return
        purpose = run.purpose
        before = self.status.get(iid, CalibrationStatus())
        relearning = purpose == Learning.RELEARNING
        own = self._current(iid) is not None
        calibrations = before.calibrations + 1
        new = replace(out.status, calibrations=calibrations, source=before.source)
        if out.params is None:     # the model in use, if any, goes on serving where it was learned
            new = replace(new, learned_lo_n=before.learned_lo_n, learned_hi_n=before.learned_hi_n)
        if purpose == Learning.MONITORING:
            self._finish_refinement(out, before, new, run)
            return
        if out.params is not None:
            self._adopt(iid, out.params, out.prepared, False)
            self._basis[iid] = run.window
            self._set(iid, replace(new, state=Learning.ADOPTED, source="learned", evidence=0.0, served=0,
                                   refusals=0, retry_in=0, batch=0, preload_span=0.0))
            return
        if relearning and math.isfinite(out.status.held_out_chi2):
            # an adequate calibration that explains the held-out injections no better than the model
            # in use: that model still serves (a passing disturbance, or a relearn of a good model)
            self._set(iid, replace(new, state=Learning.MONITORING if own else Learning.IDLE, evidence=0.0,
                                   batch=0, preload_span=0.0, refined=before.refined, refinements=before.refinements))
            return
        refusals = before.refusals + 1
        wait = self.config.retry_after * min(2 ** (refusals - 1), MAX_BACKOFF)
        self._set(iid, replace(new, state=Learning.REFUSED, refusals=refusals, retry_in=wait, batch=0,
                               preload_span=0.0, evidence=0.0))

    def _finish_refinement(self, out: CalibrationOutcome, before: CalibrationStatus, new: CalibrationStatus,
                           run: _Running) -> None:
        """A refinement never takes a working model away: adopted if better, else the model in use
        stays; its tolerance diagnostics replace the first calibration's where it explained its batch.
        One over failed probes leaves the regular refinements due as they were: it learned the levels
        the model failed at from a few injections there, and the levels the correction then settles
        at are learned by those (refined over the probes, a Prandtl–Ishlinskii part opened 0.3-0.45 µs
        late at 1.2-1.36 times the standard drive, beyond its σ, until its refinement over 60 there)."""
        iid = out.injector_id
        counted = int(not run.window.probed)
        refinements = _refinements(before) + counted
        refined = before.refined or bool(counted)
        if out.params is not None and self._current(iid) is not None:
            self._adopt(iid, out.params, out.prepared, True)
            self._basis[iid] = run.window
            self._set(iid, replace(new, state=Learning.ADOPTED, source="learned", evidence=0.0, served=0,
                                   refusals=0, retry_in=0, batch=0, preload_span=0.0, refined=refined,
                                   refinements=refinements))
            return
        if run.window.probed and self._current(iid) is not None:
            self._relearn_from_probes(iid, before, new, refinements, refined, out.status.message)
            return
        adequate = math.isfinite(out.status.held_out_chi2)
        self._set(iid, replace(before, state=Learning.MONITORING if self._current(iid) is not None else Learning.IDLE,
                               calibrations=new.calibrations, refined=refined, refinements=refinements, evidence=0.0,
                               out_of_tolerance=new.out_of_tolerance if adequate else before.out_of_tolerance,
                               message="refinement: " + out.status.message))

    def _relearn_from_probes(self, iid: int, before: CalibrationStatus, new: CalibrationStatus,
                             refinements: int, refined: bool, why: str) -> None:
        """A refinement over the model's own injections and the drive levels it failed at was refused:
        no one parameter set explains both, it explains the newest worse, or it leaves one of them
        another part's misfit (:data:`~estimator.ident.learning.selfcal.ANOTHER_PART_Z`). The failed probes are
        then not levels this part has yet to learn but another part, or one that changed: the model
        in use keeps serving while the injector re-learns from a new window (the refinement's window
        holds injections from before the change too: a part swapped at injection 40 failed as probes
        under its predecessor's correction; refined over both parts' injections, one such refinement
        was adopted, and the lot then spread 4.3 µm at p95 on the bus)."""
        self._windows.pop(iid, None)
        self._refine.pop(iid, None)
        self._set(iid, replace(before, state=Learning.RELEARNING, calibrations=new.calibrations, refined=refined,
                               refinements=refinements, evidence=0.0,
                               message="refinement over the drive levels the model failed at: " + why
                                       + "; learning again"))

    # ---- commands, seeds and persistence -----------------------------------------------------
    def forget(self, iid: int) -> None:
        """Forget the injector's learning (its own model goes back to the tables: ``reset``)."""
        self._drop_work(iid)
        if iid in self.status:
            self._set(iid, CalibrationStatus(calibrations=self.status[iid].calibrations))

    def _drop_work(self, iid: int) -> None:
        """Drop the injector's windows and the calibration running for it (its outcome is ignored)."""
        self._windows.pop(iid, None)
        self._refine.pop(iid, None)
        self._probes.pop(iid, None)
        self._running.pop(iid, None)
        self._basis.pop(iid, None)

    def relearn(self, iid: int) -> None:
        """Start a new learning cycle now; the model in use serves until a new one is adopted."""
        st = self.status.get(iid, CalibrationStatus())
        if st.state == Learning.CALIBRATING:
            return
        self._windows.pop(iid, None)
        self._set(iid, replace(st, state=Learning.RELEARNING, batch=0, preload_span=0.0, evidence=0.0,
                               retry_in=0, message="relearn command"))

    def seeded(self, iid: int) -> None:
        """The injector starts from its own (end-of-line) parameter set: monitored like a learned one."""
        self._set(iid, CalibrationStatus(Learning.MONITORING, source="seeded", message="seeded from its parameter file"))

    def adopted(self, iid: int, state: Learning = Learning.ADOPTED, source: str = "learned") -> None:
        """The injector's own model was put in place from outside (``adopted``: by the caller;
        ``monitoring``: restored from the state file)."""
        self._windows.pop(iid, None)
        self._basis.pop(iid, None)
        st = self.status.get(iid, CalibrationStatus())
        self._set(iid, replace(st, state=state, source=source, evidence=0.0, served=0, batch=0, preload_span=0.0,
                               learned_lo_n=0.0, learned_hi_n=0.0))

    def restore(self, iid: int, st: CalibrationStatus, has_model: bool) -> None:
        """A persisted status: its window is gone (collection starts again), a running calibration
        is lost (the injector collects again)."""
        state = st.state
        if state == Learning.CALIBRATING:
            state = Learning.RELEARNING if has_model else Learning.LEARNING
        if has_model and state in (Learning.IDLE, Learning.LEARNING):
            state = Learning.MONITORING
        if not has_model and state in (Learning.ADOPTED, Learning.MONITORING, Learning.RELEARNING):
            state = Learning.IDLE
        self._set(iid, replace(st, state=state, batch=0, preload_span=0.0,
                               source=st.source if has_model else "tables"), quiet=True)

    def carry(self, old: Learner) -> None:
        """Go on where ``old`` stands (a reloaded configuration): statuses, windows, running calibrations."""
        self.status, self._windows, self._refine, self._running = old.status, old._windows, old._refine, old._running
        self._probes, self._basis = old._probes, old._basis
        self._changed |= old._changed

    def take_changes(self) -> list[tuple[int, CalibrationStatus]]:
        """The injectors whose learning status changed since the last call, with that status."""
        changed = sorted(self._changed)
        self._changed.clear()
        return [(i, self.status[i]) for i in changed]

    def _set(self, iid: int, status: CalibrationStatus, quiet: bool = False) -> None:
        """Set a status; a change of state or progress is reported (``quiet``: the monitor's own
        bookkeeping is not a change anyone needs on the bus)."""
        old = self.status.get(iid)
        if (not quiet and old != status) or (old is not None and (old.state, old.batch) != (status.state, status.batch)):
            self._changed.add(iid)
        self.status[iid] = status

    def close(self) -> None:
        """Stop the calibrator."""
        self.calibrator.close()


class _Running(NamedTuple):
    """A calibration handed to the calibrator: what it is for (``LEARNING``, ``RELEARNING`` or
    ``MONITORING``: a refinement) and its window (the adopted model's basis; ``probed``: a refinement
    over failed probes, not counted among the regular ones)."""

    purpose: Learning
    window: CalibrationWindow


def _joined(basis: CalibrationWindow, new: CalibrationWindow, capacity: int) -> CalibrationWindow:
    """A window of ``new``'s injections after as many of ``basis``'s newest as ``capacity`` leaves room
    for (``new``'s newest stay the held-out ones); those of ``basis`` it holds already are not repeated."""
    held = {id(item) for item in new.items}
    old = [item for item in basis.items if id(item) not in held]
    keep = max(0, capacity - len(new.items))
    return CalibrationWindow(capacity, old[max(0, len(old) - keep):] + new.items)


def _half_fresh(window: CalibrationWindow, config: SelfCalConfig) -> bool:
    """``window`` holds half a learning window of injections it was not started with, over a wide enough
    range of preload forces (:meth:`CalibrationWindow.ready` at its present size)."""
    return window.added >= max(1, config.window // 2) and window.ready(replace(config, window=len(window.items)))


def _grown_from(basis: CalibrationWindow | None, capacity: int) -> CalibrationWindow:
    """A first refinement's window of ``capacity`` injections, started with the newest of ``basis``
    (the window the model in use was calibrated on; None: none known, e.g. a model restored from the
    state file), half ``capacity`` at most: the model's own injections, at the drive levels it was
    learned at (the standard drive, or a swapped part's predecessor's correction), beside those its
    correction leads to. The refinement comes sooner by as many injections and spans both."""
    keep = basis.items[max(0, len(basis.items) - capacity // 2):] if basis is not None else []
    return CalibrationWindow(capacity, list(keep))


def _narrow_note(window: CalibrationWindow, config: SelfCalConfig, lead: str = "") -> str:
    """What a window calibrated over a narrow range of preload forces says of itself ("" otherwise)."""
    narrow = window.narrow(config)
    return f"{lead}{narrow}: the model is checked as the rail pressure moves" if narrow else ""


def _refinements(st: CalibrationStatus) -> int:
    """The refinements the model in use has had (a status saved before they were counted: one if refined)."""
    return max(st.refinements, int(st.refined))


def _next_refinement(st: CalibrationStatus, config: SelfCalConfig) -> int:
    """The window of the monitored model's next refinement, 0 when none is due: ``refine_window``
    first, then ``refine_again``. The voltage tells least about the valve's motion: over 24 injections
    one lot's parts still opened from 0.35 µs before to 0.22 µs after the instants their models
    predicted, over 60 within 0.2 µs; the first, smaller window serves sooner."""
    done = _refinements(st)
    if done == 0:
        return config.refine_window
    return config.refine_again if done == 1 and config.refine_window else 0
