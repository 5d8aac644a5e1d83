"""The codec's exceptions (one module): a DBC that breaks the contract, a frame that cannot be decoded."""

from __future__ import annotations

from estimator.errors import EstimatorError


class ContractError(EstimatorError):
    """The DBC does not satisfy the contract (missing message/signal, wrong frame format, resolution)."""


class MalformedFrame(EstimatorError):
    """A frame with a known identifier that cannot be decoded (length, format, value range)."""
