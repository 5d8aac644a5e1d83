"""The estimation pipeline, as every entry point builds it: the estimator's configuration
(:mod:`.config`), the builders (:mod:`.build`), the per-injection processing (:mod:`.processor`), the
offline runs over captures and traces (:mod:`.replay`, :mod:`.estimates`) and the compile step
(:mod:`.precompile`).

The layer above the numerical core, the codec and the file formats (:mod:`estimator.io`), below the
daemon (:mod:`estimator.service`), the fleet and the command lines; it imports none of those.
"""

from estimator.pipeline.build import SILENT_BUS_S, build_codec, build_pipeline, build_pool, build_tracker
from estimator.pipeline.config import ConfigError, EstimatorConfig

__all__ = ["SILENT_BUS_S", "ConfigError", "EstimatorConfig", "build_codec", "build_pipeline", "build_pool",
           "build_tracker"]
