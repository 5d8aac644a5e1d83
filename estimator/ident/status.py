"""The status of an estimate, from the identification kernel to the outputs (one enum).

The value is the word used in JSON, CLIs and logs. Its code on the bus is the DBC's
(``VAL_ 512 Status`` in ``dbc/injector.dbc``), which the codec maps (:meth:`Codec.status_code`).
"""

from __future__ import annotations

from enum import Enum


class Status(str, Enum):
    """Outcome of one injection. A ``str`` so that JSON and comparisons with words keep working."""

    OK = "ok"                        # filtered estimate, converged, sigma within the configured limit
    AT_BOUND = "at_bound"            # the estimate lies on a search bound (truth may be outside the range)
    NOT_CONVERGED = "not_converged"  # the line searches ran out of cycles
    REJECTED = "rejected"            # invalid trace or a rejected outlier: the published estimate is the old one
    NO_ESTIMATE = "no_estimate"      # nothing known about this injector yet
    UNCERTAIN = "uncertain"          # estimated, but sigma(L_h) above the configured limit
    UNCONFIRMED = "unconfirmed"      # this injection disagrees with the filter (a step, a fast drift, or a glitch):
                                     # its own estimate (far off) or the filter updated by it (marginal), until
                                     # the next injection confirms or discards it
    MODEL_MISMATCH = "model_mismatch"  # estimated, but the model cannot explain this injector's samples: the
                                       # estimate is biased by an unknown amount; sigma is widened to cover it
                                       # (calibrate the injector's own model)

    def __str__(self) -> str:
        return self.value


#: where an injector's self-calibration stands (the words of ``ModelCalibration.State``)
CALIBRATION_STATES = ("idle", "collecting", "calibrating", "adopted", "rejected")

#: statuses whose published (N_u, L_h) is an estimate of this injection (not the previous one held)
ESTIMATED = frozenset({Status.OK, Status.AT_BOUND, Status.NOT_CONVERGED, Status.UNCERTAIN, Status.UNCONFIRMED,
                       Status.MODEL_MISMATCH})
ESTIMATED_WORDS = frozenset(s.value for s in ESTIMATED)   # the same, as the words of JSON and CSV rows
