"""The one place that builds the estimation pipeline from a configuration.

The live daemon, ``replay``, the library's :func:`~estimator.pipeline.estimates.iter_estimates`, the
fleet's workers, the benches and ``estimator compile`` all build codec, simulator pool, tracker and
the rest here from an :class:`~estimator.pipeline.config.EstimatorConfig`, so that they estimate alike.
"""

from __future__ import annotations

from estimator.codec.bus_clock import BusClock
from estimator.codec.ingest import Ingest
from estimator.codec.records import Codec, InjectionHeader, load_database
from estimator.drive.correction import DriveCompensator
from estimator.ident.learning.selfcal import Calibrator
from estimator.ident.simulators import SimulatorPool
from estimator.ident.tracking.tracker import Tracker
from estimator.pipeline.config import EstimatorConfig, load_amplifier_drive
from estimator.pipeline.processor import Processor

SILENT_BUS_S = 1.0   # s: the bus clock's guard unless the daemon's configuration says otherwise
Pipeline = tuple[Codec, Ingest, Processor, BusClock]   # what build_pipeline returns


def build_pool(cfg: EstimatorConfig) -> SimulatorPool:
    """The bounded simulator pool as configured (parameters from ``cfg.params`` or Tables 1-2)."""
    from estimator.model.parameters import load_parameters

    return SimulatorPool(load_parameters(cfg.params), cfg.max_sample_periods, cfg.sample_periods_ns)


def build_tracker(cfg: EstimatorConfig, pool: SimulatorPool | None = None,
                  calibrator: Calibrator | None = None, codec: Codec | None = None) -> Tracker:
    """The recursive estimator as configured (on ``pool`` if given: its simulators' tables are built
    once), each injector with a configured parameter file of its own starting from it. With learning
    on, calibrations run on ``calibrator`` (default: at once, in the caller's thread, as an offline
    replay wants; the daemon passes its background calibrator)."""
    from estimator.model.parameters import load_parameters

    codec = codec or build_codec(cfg)
    tracker = Tracker(cfg.tracker_config(), pool=pool if pool is not None else build_pool(cfg),
                      self_calibration=cfg.self_calibration_config(), calibrator=calibrator,
                      temperature_range_c=codec.signal_range(InjectionHeader, "fuel_temperature_c"))
    for iid, path in sorted(cfg.injector_params.items()):   # end-of-line calibrations: each injector's start
        tracker.seed(iid, load_parameters(path))
    return tracker


def build_codec(cfg: EstimatorConfig) -> Codec:
    """The codec of the configured DBC (``cfg.dbc``, else the packaged one)."""
    return Codec(load_database(cfg.dbc))


def build_compensator(cfg: EstimatorConfig, deferred: bool = False) -> DriveCompensator | None:
    """The drive compensator as configured (None: off), with the amplifier's standard drive read from
    its current table when one is configured; ``deferred``: its tables and derivative refreshes wait
    for the worker's idle time (the pipeline's)."""
    t = cfg.drive_correction
    if t is None:
        return None
    return DriveCompensator(t, standard=load_amplifier_drive(t.drive_file) if t.drive_file is not None else None,
                            deferred=deferred)


def build_pipeline(cfg: EstimatorConfig, pool: SimulatorPool | None = None, codec: Codec | None = None,
                   calibrator: Calibrator | None = None,
                   silent_bus_s: float = SILENT_BUS_S, deferred: bool = False) -> Pipeline:
    """Codec, ingest, processor and bus clock: the same in the live daemon and in the replay. ``pool``
    and ``codec`` (built from ``cfg`` when not given) hold no state of a run: a fleet worker shares them
    between its inputs (the simulator tables and the DBC parse cost ≈ 35 ms each). ``silent_bus_s``:
    the live daemon's wall-clock guard (its configuration's); a replay's capture ends it.
    ``deferred``: the drive correction's tables and derivative refreshes wait for the processor's
    :meth:`~estimator.pipeline.processor.Processor.background` (the live daemon's idle worker runs it);
    without it every published correction is complete, as a replay's is."""
    codec = codec or build_codec(cfg)
    ingest = Ingest(codec, cfg.assembly_timeout_ms * 1e-3, cfg.max_injectors)
    compensator = build_compensator(cfg, deferred)
    processor = Processor(codec, build_tracker(cfg, pool, calibrator, codec), ingest.counters, cfg.commands,
                          compensator)
    return codec, ingest, processor, BusClock(silent_bus_s)
