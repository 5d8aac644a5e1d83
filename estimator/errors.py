"""Exception hierarchy of the estimator: one root, specific subclasses."""


class EstimatorError(Exception):
    """Root of all errors raised by this package."""


class ParameterError(EstimatorError, ValueError):
    """A physical parameter is missing, not finite, or out of its admissible range."""


class TraceError(EstimatorError, ValueError):
    """A measured trace cannot be used (NaN samples, too short, irregular sampling, ...)."""


class InfeasibleError(EstimatorError):
    """The hybrid model has no valid initial state for the requested parameters."""
