"""Piezo injector estimator: identify N_u and L_h from amplifier current and voltage.

The names in :data:`__all__` are the public API, what a user scripts with::

    import estimator

    inj = estimator.injection_from_trace(estimator.read_trace("shot.csv"))
    print(estimator.identify(inj))                     # one injection, from a cold start

    tracker = estimator.Tracker()                      # many, recursively, per injector
    for inj in injections:
        res = tracker.update(inj)

    for row in estimator.iter_estimates("capture.blf"):   # a capture, as the daemon estimates it
        print(row["injector_id"], row["status"], row["lh_um"], row["drive_scale"])

    _, _, processor, _ = estimator.build_pipeline(estimator.EstimatorConfig())   # the closed loop
    pub = processor.estimate(inj, next_preload_n=120.0)   # the estimate and the drive correction for 120 N
    scale, offset_us = pub.correction.at(120.0)           # what the amplifier applies there

They are imported when first used (``import estimator`` itself loads nothing heavy). Every other
module may change without notice.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.3.0"

#: public name -> the module that defines it
_HOMES: dict[str, str] = {
    # one injection
    "identify": "estimator.ident.fit.idle_stroke",
    "Estimate": "estimator.ident.estimate",
    "Injection": "estimator.ident.measurement",
    "Status": "estimator.ident.status",
    "IdentConfig": "estimator.ident.config",
    # many injections
    "Tracker": "estimator.ident.tracking.tracker",
    "TrackResult": "estimator.ident.tracking.tracker",
    "TrackerConfig": "estimator.ident.config",
    # learning and calibration
    "Learning": "estimator.ident.status",
    "SelfCalConfig": "estimator.ident.learning.selfcal",
    "calibrate_electrical": "estimator.ident.learning.electrical",
    # the drive that opens every valve alike
    "DriveCompensator": "estimator.drive.correction",
    "DriveTarget": "estimator.drive.target",
    "Correction": "estimator.drive.correction",
    "correction_after": "estimator.drive.correction",
    "estimate_unchecked": "estimator.drive.correction",
    "AmplifierDrive": "estimator.drive.standard",
    # the model
    "InjectorParameters": "estimator.model.parameters",
    "load_parameters": "estimator.model.parameters",
    "load_nominal": "estimator.model.parameters",
    "MeasurementChain": "estimator.model.chain",
    "StandardDrive": "estimator.model.drive",
    "FastSimulator": "estimator.model.fast_sim",
    # files
    "read_trace": "estimator.io.traces",
    "write_trace": "estimator.io.traces",
    "injection_from_trace": "estimator.io.traces",
    "read_injections": "estimator.io.mdf",
    "read_capture": "estimator.io.captures",
    # the pipeline, as every entry point builds it, and its configuration
    "EstimatorConfig": "estimator.pipeline.config",
    "ConfigError": "estimator.pipeline.config",
    "build_pipeline": "estimator.pipeline.build",
    "Processor": "estimator.pipeline.processor",
    "Published": "estimator.pipeline.processor",
    "iter_estimates": "estimator.pipeline.estimates",
    "replay": "estimator.pipeline.replay",
    # the bus and the daemon's configuration (the estimator's, with the bus, state and service keys)
    "Codec": "estimator.codec.records",
    "DaemonConfig": "estimator.service.config",
    # errors
    "EstimatorError": "estimator.errors",
}

__all__ = sorted(_HOMES)


def __getattr__(name: str) -> Any:
    """Import a public name from its module when it is first used."""
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'estimator' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
