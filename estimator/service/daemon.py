"""The estimator daemon: bus -> Notifier -> bounded queue -> worker (estimator) -> bus.

Lifecycle, in order (python-can ``notifier.py``; issues #1526, #1667): the bus is opened first and
shut last; the Notifier runs inside it and is stopped first; one worker thread does everything
else. Signal handlers only set an Event. sd_notify: READY=1 once running, WATCHDOG=1 only while
the worker makes progress, STOPPING=1 at shutdown.

Signals: SIGTERM and SIGINT stop the daemon (state saved, exit 0). SIGHUP reloads the configuration
file (``systemctl reload``): the state is saved first, then everything but the bus, the DBC, the
state directory, the queue size and ``max_injectors`` takes effect at once (those need a restart
and say so in the log); a file that does not validate is reported and the running configuration
kept. Time in the pipeline is the bus's (see :mod:`estimator.codec.bus_clock`).
"""

from __future__ import annotations

import collections
import gc
import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import can

from estimator import __version__
from estimator.codec.assembler import Completed
from estimator.codec.frame import Frame
from estimator.errors import EstimatorError
from estimator.ident.tracking.tracker import Tracker
from estimator.io.captures import to_frame, to_message
from estimator.model.drive import SAMPLE_PERIOD_S
from estimator.pipeline import build_pipeline, build_pool, build_tracker
from estimator.pipeline.build import build_compensator
from estimator.pipeline.ratelimit import RateLimitedLog
from estimator.service.bus import open_bus, resolve
from estimator.service.calibration_worker import BackgroundCalibrator
from estimator.service.config import ConfigError, DaemonConfig
from estimator.service.fair_queue import FairQueue
from estimator.service.latency import Stats
from estimator.service.sdnotify import SdNotify
from estimator.service.state_store import keep_rejected, load_all, lock_state_dir, save_states
from estimator.service.xcp.a2l import NAME as A2L_NAME
from estimator.service.xcp.a2l import a2l_bytes
from estimator.service.xcp.daq_lists import EVENT_10HZ
from estimator.service.xcp.slave import XcpSlave
from estimator.units import US_PER_S

log = logging.getLogger(__name__)
STATE_FILE = "estimator-state.json"
STATUS_LINE_PERIOD_S = 5.0   # sd_notify STATUS= with live counters (systemctl status)


class QueueListener(can.Listener):  # type: ignore[misc]  # python-can is not followed: its Listener is Any here
    """Notifier callback: frames into a bounded deque (drop-oldest, counted); errors handled here.

    Each entry is (frame, monotonic arrival time). ``on_error`` counts the error, logs it rate-limited
    and backs off (so a dead interface does not spin the receive thread), then lets the Notifier go on.
    """

    def __init__(self, maxlen: int) -> None:
        self.queue: collections.deque[tuple[Frame, float]] = collections.deque(maxlen=maxlen)
        self.ready = threading.Event()
        self.dropped = 0
        self.errors = 0
        self._backoff = 0.01
        self.rlog = RateLimitedLog(log)

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame:
            return
        if len(self.queue) == self.queue.maxlen:
            self.dropped += 1
        self.queue.append((to_frame(msg), time.monotonic()))
        self._backoff = 0.01
        self.ready.set()

    def on_error(self, exc: Exception) -> None:
        self.errors += 1
        self.rlog.log(logging.ERROR, "rx", "bus receive error: %s; retrying in %.2f s", exc, self._backoff)
        time.sleep(self._backoff)
        self._backoff = min(self._backoff * 2, 1.0)

    def get(self, timeout: float) -> tuple[Frame, float] | None:
        try:
            return self.queue.popleft()
        except IndexError:
            self.ready.clear()
            if self.queue:
                return self.queue.popleft()
            self.ready.wait(timeout)
            try:
                return self.queue.popleft()
            except IndexError:
                return None


# keys a SIGHUP cannot change (they shape the bus connection and the memory already allocated)
RELOAD_MIN_S = 0.5   # the worker applies a reloaded configuration at most this often
INGEST_BATCH = 256   # frames the worker assembles between two identifications (≈ 1.3 ms at most)
ESTABLISHED_AFTER = 10   # injections accepted since its last reset: the worker serves such an injector first
DEFER_CORRECTION_WORK = True   # the drive correction's tables and derivative refreshes wait for the idle worker
RESTART_KEYS = ("bus", "bitrate", "data_bitrate", "fd", "bus_options", "dbc", "state_dir", "queue_frames",
                "max_injectors", "xcp")


@dataclass(frozen=True)
class _Reload:
    """A reloaded configuration and what the main thread built for it, ready to swap in."""

    cfg: DaemonConfig
    tracker: Tracker
    same_pool: bool                     # the simulators' parameters stayed: the injectors' own models carry over
    calibrator: BackgroundCalibrator | None


@dataclass(frozen=True)
class _Pending:
    reload: _Reload | None              # None: the configuration file did not change anything


class Daemon:
    """One estimator instance on one bus."""

    def __init__(self, cfg: DaemonConfig, loader: Callable[[], DaemonConfig] | None = None) -> None:
        self.cfg = cfg
        self.loader = loader
        # self-calibrations run in a low-priority process of their own, never on the injection worker
        self.calibrator = BackgroundCalibrator() if cfg.self_calibration is not None else None
        self.codec, self.ingest, self.processor, self.clock = build_pipeline(cfg, calibrator=self.calibrator,
                                                                                 silent_bus_s=cfg.silent_bus_s,
                                                                                 deferred=DEFER_CORRECTION_WORK)
        self.stop = threading.Event()
        self.reload_requested = threading.Event()
        self._send_lock = threading.Lock()
        self._wake = threading.Event()      # main loop: a signal arrived
        self._pending_cfg: _Pending | None = None   # a reload prepared by the main thread, for the worker
        self._reload_lock = threading.Lock()
        self._notices: collections.deque[str] = collections.deque(maxlen=64)   # worker -> main thread -> systemd
        self.bus_name = str(cfg.bus or "python-can configuration")
        self.notify = SdNotify()
        self.stats = Stats()
        self.progress = time.monotonic()
        self.rlog = RateLimitedLog(log)
        self.started = time.monotonic()
        self._bus: can.BusABC | None = None
        self._listener: QueueListener | None = None
        self.state_path = cfg.state_dir / STATE_FILE if cfg.state_dir else None
        self._dirty = False
        self._lock_fd: int | None = None   # the state directory's lock, held until the process ends
        # complete injections waiting for the worker, estimated by fair share between injectors
        self.waiting: FairQueue[tuple[Completed, float, float]] = FairQueue(deadline_s=cfg.shed_after_ms * 1e-3)
        self.xcp: XcpSlave | None = None    # the calibration tool's view (bound in _serve)

    @property
    def tracker(self) -> Tracker:
        """The recursive estimator (the processor's: a reload swaps it there)."""
        return self.processor.tracker

    # ---- state ------------------------------------------------------------------------------
    def restore(self) -> None:
        """Load persisted per-injector state (a bad file is reported and ignored)."""
        if self.state_path is None:
            return
        states, calibrations, learning, drives, problems = load_all(self.state_path)
        problems += self.tracker.restore(states, calibrations) + self.tracker.restore_calibrations(calibrations, learning)
        if self.processor.compensator is not None:
            self.processor.compensator.restore_drives(drives)
        if problems:
            kept = keep_rejected(self.state_path)
            log.warning("state file %s: dropped (starting those injectors cold; %s): %s", self.state_path,
                        f"the original kept as {kept.name}" if kept else "the original could not be kept",
                        "; ".join(problems))
        if self.tracker.states:
            log.info("restored the state of %d injector(s) from %s", len(self.tracker.states), self.state_path)

    def persist(self) -> None:
        """Write the state now (atomic); errors are logged, not fatal."""
        if self.state_path is None:
            return
        try:
            comp = self.processor.compensator
            save_states(self.state_path, dict(self.tracker.states), self.tracker.own_parameters(),
                        dict(self.tracker.calibration), comp.learned_drives() if comp is not None else None)
            self._dirty = False
        except OSError as exc:
            self.rlog.log(logging.ERROR, "persist", "cannot write state %s: %s", self.state_path, exc)

    # ---- bus output -------------------------------------------------------------------------
    def send(self, frames: list[Frame]) -> None:
        """Send frames; a failed send (ENOBUFS, interface down) is retried with backoff, then dropped.

        Called by the worker (estimates) and the heartbeat thread; one lock keeps their frames whole on
        interfaces whose send is not thread-safe (the websocket of the loopback hub).
        """
        assert self._bus is not None
        with self._send_lock:
            self._send(frames)

    def _send(self, frames: list[Frame]) -> None:
        assert self._bus is not None
        xcp = self.xcp
        for fr in frames:
            if xcp is not None:
                xcp.store(fr.arbitration_id, fr.data)
            delay = 0.001
            for attempt in range(4):
                try:
                    self._bus.send(to_message(fr), timeout=0.05)
                    break
                except (can.CanError, OSError) as exc:
                    self.ingest.counters.bus_errors += 1
                    self.rlog.log(logging.ERROR, "tx", "bus send error: %s (attempt %d)", exc, attempt + 1)
                    if self.stop.wait(delay):
                        return
                    delay *= 4

    # ---- worker -----------------------------------------------------------------------------
    def _worker(self) -> None:
        assert self._listener is not None
        lst = self._listener
        next_persist = time.monotonic() + self.cfg.persist_period_s
        next_reload = 0.0
        while not self.stop.is_set():
            if self._pending_cfg is not None and time.monotonic() >= next_reload:
                # a burst of SIGHUPs is coalesced: the newest configuration, at most every RELOAD_MIN_S
                next_reload = time.monotonic() + RELOAD_MIN_S
                with self._reload_lock:
                    pending, self._pending_cfg = self._pending_cfg, None
                if pending is not None:
                    self._apply(pending.reload)
                next_persist = time.monotonic()
            self.progress = time.monotonic()
            try:
                ingested = self._ingest_frames(lst, wait=not self.waiting and not self.processor.has_background)
                taken = self.waiting.take(time.monotonic())
                self._count_expired()
                if taken is not None:
                    self._estimate(*taken)
                elif not ingested:
                    self.processor.background()     # the drive correction's deferred work, while idle
                    t_idle = self.clock.idle(time.monotonic())     # the silent-bus guard (wall clock)
                    if t_idle is not None:
                        self.processor.handle(self.ingest.poll(t_idle))
                self.ingest.counters.frames_dropped = lst.dropped
                mono = time.monotonic()
                if mono >= next_persist:
                    next_persist = mono + self.cfg.persist_period_s
                    if self._dirty:
                        self.persist()
            except Exception:   # a bug must not kill the service silently: log it, keep serving
                self.ingest.counters.worker_errors += 1
                self.rlog.log(logging.ERROR, "worker", "worker error (continuing)", exc_info=True)

    def _ingest_frames(self, lst: QueueListener, wait: bool) -> int:
        """Decode and assemble the frames that have arrived (at most ``INGEST_BATCH``; waiting up to
        10 ms for the first only when ``wait``): complete injections join :attr:`waiting`, everything
        else (rejections, commands) is handled at once. Returns the number of frames taken."""
        n = 0
        while n < INGEST_BATCH:
            item = lst.get(timeout=0.01 if wait and n == 0 else 0.0)
            if item is None:
                break
            n += 1
            frame, arrived = item
            t0 = time.monotonic()
            now = self.clock.on_frame(frame.timestamp, arrived)   # bus time, as in a replay
            events = self.ingest.feed(frame, now)
            assembled = time.monotonic() - t0
            rest = []
            for e in events:
                if isinstance(e, Completed):
                    iid = e.header.injector_id
                    st = self.tracker.states.get(iid)
                    known = st is not None and st.accepted >= ESTABLISHED_AFTER
                    shed = self.waiting.put(iid, (e, arrived, assembled), known, arrived)
                    if shed is not None:
                        self.ingest.counters.injections_shed += 1
                        self.rlog.log(logging.WARNING, "shed", "injector %d counter %d shed unestimated: the worker "
                                      "is behind and this injector used more than its share of it",
                                      shed[0].header.injector_id, shed[0].header.counter)
                else:
                    rest.append(e)
            if rest:
                self.processor.handle(rest)
        return n

    def _count_expired(self) -> None:
        """Count and log (rate-limited) the injections the worker shed because they waited longer than
        ``shed_after_ms``: above capacity it estimates fewer injections, never later ones."""
        while self.waiting.expired:
            _, (e, arrived, _) = self.waiting.expired.popleft()
            self.ingest.counters.injections_shed += 1
            self.rlog.log(logging.WARNING, "late", "injector %d counter %d shed unestimated: it waited %.1f ms for "
                          "the worker (shed_after_ms %.1f): the daemon is above its capacity", e.header.injector_id,
                          e.header.counter, (time.monotonic() - arrived) * 1e3, self.cfg.shed_after_ms)

    def _estimate(self, injector: int, waiting: tuple[Completed, float, float]) -> None:
        """Estimate one complete injection, publish it (``stale`` when it is later than
        ``stale_after_ms`` after its last frame) and book the worker time to its injector."""
        e, arrived, assembled = waiting
        t_prev = time.monotonic()
        queued = t_prev - arrived - assembled   # the input queue and the wait for the worker's turn
        for pub in self.processor.handle([e]):
            t_est = time.monotonic()
            if t_est - arrived > self.cfg.stale_after_ms * 1e-3:   # behind: never published as ok
                pub = pub.stale(t_est - arrived)
                self.ingest.counters.stale += 1
                self.rlog.log(logging.WARNING, "stale", "injector %d counter %d published %.0f ms after its last "
                              "frame (stale)", pub.injector_id, pub.counter, (t_est - arrived) * 1e3)
            self.send(pub.frames[:1])
            t_sent = time.monotonic()
            self.stats.add(t_prev, t_sent - arrived, (queued, assembled, t_est - t_prev, t_sent - t_est))
            self.send(pub.frames[1:])
            self._dirty = True
            if self.xcp is not None:
                self.xcp.injection(pub.injector_id)
        self.waiting.charge(injector, time.monotonic() - t_prev)

    def _heartbeat(self) -> None:
        """EstimatorStatus and EstimatorHealth every ``status_period_s``, from its own thread: a long identification (a
        cold start on a loaded machine, a new sample period) does not silence it. The worker's own
        liveness is what the systemd watchdog checks."""
        assert self._listener is not None
        while not self.stop.is_set():
            try:
                total, stages = self.stats.p99s_ms()
                self.send([self.processor.status_frame(len(self._listener.queue), total,
                                                       time.monotonic() - self.started, stages),
                           self.processor.health_frame(len(self.waiting))])
                if self.xcp is not None:
                    self.xcp.event(EVENT_10HZ)
            except Exception:   # never let the heartbeat die with a traceback per tick
                self.rlog.log(logging.ERROR, "heartbeat", "heartbeat error (continuing)", exc_info=True)
            self.stop.wait(self.cfg.status_period_s)

    # ---- reload (SIGHUP) --------------------------------------------------------------------
    def request_reload(self) -> None:
        """Main thread: read and validate the configuration again; the worker applies it."""
        self.notify.notify(f"RELOADING=1\nMONOTONIC_USEC={time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000}")
        if self.loader is None:
            log.warning("SIGHUP: no configuration file to reload; running configuration kept")
            self.notify.notify("READY=1\nSTATUS=reload skipped: no configuration file")
            return
        try:
            new = self.loader()   # validates every key and loads the parameter file
        except (ConfigError, EstimatorError, OSError) as exc:
            log.error("SIGHUP: configuration not reloaded, running configuration kept: %s", exc)
            self.notify.notify(f"READY=1\nSTATUS=reload failed: {exc}")
            return
        fixed = [k for k in RESTART_KEYS if getattr(new, k) != getattr(self.cfg, k)]
        if fixed:
            log.warning("SIGHUP: %s changed; that takes effect at the next restart", ", ".join(fixed))
        try:
            prepared = self._prepare(new)
        except (EstimatorError, OSError) as exc:   # e.g. a parameter file that went away
            log.error("SIGHUP: configuration not applied, running configuration kept: %s", exc)
            self.notify.notify(f"READY=1\nSTATUS=reload failed: {exc}")
            return
        self._hand_over(prepared)
        if self.xcp is not None:
            self.xcp.reload(new)   # the calibration tool's pages start from the file again

    def calibrate(self, new: DaemonConfig) -> None:
        """XCP thread: a configuration a calibration tool wrote (the working page), checked and built off
        the real-time path like a reload; the worker takes it between two injections, all at once. (Its
        keys passed the configuration's own checks when it was built.)"""
        self._hand_over(self._prepare(new))
        self.ingest.counters.xcp_writes += 1

    def _hand_over(self, prepared: _Reload | None) -> None:
        """A prepared configuration for the worker (a newer one supersedes one it has not taken yet)."""
        with self._reload_lock:
            superseded, self._pending_cfg = self._pending_cfg, _Pending(prepared)
        gone = superseded.reload.calibrator if superseded is not None and superseded.reload is not None else None
        if gone is not None and gone is not self.calibrator and (prepared is None or gone is not prepared.calibrator):
            gone.close()   # a calibration process started for a configuration that never took effect

    def _prepare(self, new: DaemonConfig) -> _Reload | None:
        """Main thread: everything a reload needs built off the real-time path (the tracker on the
        running or a new simulator pool, a calibration process when learning is turned on); None when
        ``new`` equals the running configuration (a burst of SIGHUPs costs no rebuild)."""
        new = replace(new, **{k: getattr(self.cfg, k) for k in RESTART_KEYS})
        if new == self.cfg:
            return None
        same_pool = all(getattr(new, k) == getattr(self.cfg, k) for k in ("params", "max_sample_periods",
                                                                          "sample_periods_ns"))
        calibrator = self.calibrator
        if new.self_calibration is not None and calibrator is None:
            calibrator = BackgroundCalibrator()
        tracker = build_tracker(new, self.tracker.pool if same_pool else build_pool(new),
                                calibrator if new.self_calibration is not None else None, self.codec)
        return _Reload(new, tracker, same_pool, calibrator if new.self_calibration is not None else None)

    def _apply(self, reload: _Reload | None) -> None:
        """Worker thread: persist, then swap the prepared tracker in (the injectors' states, and their own
        models when the simulators' parameters stayed, carried over). Costs the worker about 1 ms."""
        if reload is None:
            log.info("configuration reloaded: unchanged")
            self._tell(f"READY=1\nSTATUS=running on {self.bus_name} (configuration unchanged)")
            return
        new, tracker = reload.cfg, reload.tracker
        if self._dirty:
            self.persist()
        old = self.tracker
        tracker.states = old.states
        if reload.same_pool:   # the injectors' own models are calibrations of these parameters
            tracker.own_pools = old.own_pools
            if tracker.learning is not None and old.learning is not None:
                tracker.learning.carry(old.learning)
        if self.calibrator is not None and reload.calibrator is not self.calibrator:
            self.calibrator.close()    # learning turned off: the calibration process ends
        self.calibrator = reload.calibrator
        self.processor.tracker = tracker
        self.processor.commands = new.commands
        if new.drive_correction != self.cfg.drive_correction:   # a new target: corrections start again
            old_comp = self.processor.compensator
            self.processor.compensator = build_compensator(new, DEFER_CORRECTION_WORK)
            if old_comp is not None and self.processor.compensator is not None:   # the amplifiers are the same
                self.processor.compensator.restore_drives(old_comp.learned_drives())
        self.ingest.assembler.timeout_s = new.assembly_timeout_ms * 1e-3
        self.waiting.deadline_s = new.shed_after_ms * 1e-3
        self.clock.silent_bus_s = new.silent_bus_s
        logging.getLogger().setLevel(new.log_level_number)
        self.cfg = new
        log.info("configuration reloaded (commands %s, window %.0f µs, log level %s)", new.commands,
                 new.ident.window_s * US_PER_S, new.log_level)
        self._tell(f"READY=1\nSTATUS=running on {self.bus_name} (configuration reloaded)")

    def _tell(self, state: str) -> None:
        """Worker thread: have the main thread send ``state`` to systemd (a notification may wait up to
        0.5 s for room in a slow receiver's queue: never on the real-time path)."""
        self._notices.append(state)
        self._wake.set()

    # ---- lifecycle --------------------------------------------------------------------------
    def install_signal_handlers(self) -> None:
        """SIGTERM/SIGINT set the stop Event, SIGHUP the reload Event; nothing else runs in a handler."""
        def on_stop(*_: object) -> None:
            self.stop.set()
            self._wake.set()

        def on_hup(*_: object) -> None:
            self.reload_requested.set()
            self._wake.set()
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, on_stop)
        signal.signal(signal.SIGHUP, on_hup)

    def warm_up(self) -> None:
        """Load the compiled kernels and the N_u table before READY, so the first injection is not late
        (:meth:`Tracker.warm_up`: the daemon's own states are not touched)."""
        self.tracker.warm_up()
        if self.processor.compensator is not None:
            sim = self.tracker.nominal_simulator(SAMPLE_PERIOD_S)
            if sim is not None:
                self.processor.compensator.warm_up(sim)

    def run(self, freeze_heap: bool = False) -> int:
        """Run until stopped; returns the exit code. One estimator per state directory: a second one
        raises :class:`~estimator.service.state_store.StateDirectoryBusy` before touching anything.
        A stop requested while starting is honoured before the bus is opened. ``freeze_heap`` (the
        daemon's own process): after the warm-up, the objects built so far leave the garbage
        collector's generations (:func:`gc.freeze`): they live as long as the process, and a full
        collection walked all of them on the worker's time (14 ms, measured, where 1 ms remains)."""
        try:
            if self.cfg.state_dir is not None and self._lock_fd is None:
                self._lock_fd = lock_state_dir(self.cfg.state_dir)
            self.restore()
            if not self.stop.is_set():
                self.warm_up()
            if freeze_heap:
                gc.collect()
                gc.freeze()
            if self.stop.is_set():
                self._release()
                return 0
        except BaseException:
            self._release()
            raise
        try:
            return self._serve()
        finally:
            self._release()

    def _release(self) -> None:
        """Give the state directory and the calibration process up (the end of a run)."""
        if self.calibrator is not None:
            self.calibrator.close()
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def _serve(self) -> int:
        """The bus, the worker and the heartbeat until stopped."""
        spec = resolve(self.cfg.bus_spec())
        self.bus_name = str(spec)
        if self.cfg.xcp is not None:
            self.xcp = self._xcp_slave()
            self.xcp.start()
        with open_bus(spec) as bus:
            self._bus = bus
            self._listener = QueueListener(self.cfg.queue_frames)
            notifier = can.Notifier(bus, [self._listener], timeout=0.05)
            self.started = time.monotonic()      # uptime counts from the open bus (the first heartbeat says 0)
            worker = threading.Thread(target=self._worker, name="estimator-worker", daemon=True)
            worker.start()
            beat = threading.Thread(target=self._heartbeat, name="estimator-heartbeat", daemon=True)
            beat.start()
            log.info("estimator running on %s (state %s)", self.bus_name, self.state_path or "not persisted")
            self.notify.notify("READY=1")
            self.notify.notify(f"STATUS=running on {self.bus_name}")
            ping = SdNotify.watchdog_interval_s()
            next_status_line = time.monotonic() + STATUS_LINE_PERIOD_S
            try:
                while not self.stop.is_set():
                    self._wake.wait(ping or 0.5)
                    self._wake.clear()
                    while self._notices:
                        self.notify.notify(self._notices.popleft())
                    if self.reload_requested.is_set() and not self.stop.is_set():
                        self.reload_requested.clear()
                        self.request_reload()
                    if time.monotonic() >= next_status_line:
                        next_status_line = time.monotonic() + STATUS_LINE_PERIOD_S
                        self.notify.notify(f"STATUS={self.status_line()}")
                    if ping and time.monotonic() - self.progress < 2 * ping:
                        self.notify.notify("WATCHDOG=1")
                    self.ingest.counters.bus_errors += self._listener.errors
                    self._listener.errors = 0
            finally:
                self.notify.notify("STOPPING=1")
                notifier.stop(timeout=0.5)
                self.stop.set()
                worker.join(timeout=1.0)
                beat.join(timeout=1.0)
                if self.xcp is not None:
                    self.xcp.close()
                self.persist()
                log.info("estimator stopped: %s", self.summary())
        return 0

    def _xcp_slave(self) -> XcpSlave:
        """The XCP slave on ``[estimator.xcp]``'s address, its A2L written from this DBC and configuration."""
        assert self.cfg.xcp is not None
        x = self.cfg.xcp
        try:
            slave = XcpSlave(self.codec.db, lambda: self.cfg, self.cfg, self.calibrate,
                             lambda address: a2l_bytes(self.codec.db, __version__, address, x.writes),
                             x.host, x.port, x.writes,
                             ident=f"{A2L_NAME} {__version__}", name=A2L_NAME)
        except OSError as exc:
            raise ConfigError(f"[estimator.xcp] {x.host}:{x.port}: cannot listen there: {exc}") from None
        log.info("XCP on UDP %s:%d (writes %s)", *slave.address, "allowed" if x.writes else "refused")
        return slave

    def status_line(self) -> str:
        """``systemctl status`` line: bus and the counters that matter at a glance."""
        c = self.ingest.counters
        rejected = c.rejected_crc + c.rejected_missing + c.rejected_timeout + c.rejected_invalid
        return (f"running on {self.bus_name}: {c.accepted} estimated, {rejected} rejected, {c.rejected_outlier} "
                f"outliers, {c.frames_dropped} frames dropped, {len(self.tracker.states)} injector(s), "
                f"p99 {self.stats.p99_ms():.1f} ms")

    def summary(self) -> str:
        """The counters in one line."""
        c = self.ingest.counters
        return (f"accepted {c.accepted}, rejected crc {c.rejected_crc} missing {c.rejected_missing} timeout "
                f"{c.rejected_timeout} invalid {c.rejected_invalid} outlier {c.rejected_outlier}, frames dropped "
                f"{c.frames_dropped} malformed {c.frames_malformed}, bus errors {c.bus_errors}, commands applied "
                f"{c.commands_applied} refused {c.commands_refused} unknown {c.commands_unknown}, stale {c.stale}, "
                f"simulators built {self.tracker.pool.built} (kept {len(self.tracker.pool)}, refused by the build "
                f"budget {self.tracker.pool.over_budget}), "
                f"worker errors "
                f"{c.worker_errors}")
