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
    STALE = "stale"                  # the daemon published it later than stale_after_ms after the injection's
                                     # last frame (a backed-up queue): never ok, whatever the estimate

    def __str__(self) -> str:
        return self.value


class Learning(str, Enum):
    """Where an injector's learning of its own model stands (the words of ``ModelCalibration.State``;
    their codes are the DBC's, ``VAL_ 515 State``). See :mod:`estimator.ident.learning.learning`."""

    IDLE = "idle"                    # the configured tables explain this injector: nothing to learn
    LEARNING = "learning"            # collecting injections over operating points (progress: batch, preload span)
    CALIBRATING = "calibrating"      # a calibration of the collected window runs (in the background in the daemon)
    ADOPTED = "adopted"              # the injector's own parameter set was just adopted; being confirmed
    REFUSED = "refused"              # the calibration did not explain the injector: tried again later
    MONITORING = "monitoring"        # the injector's own (learned or seeded) model is in use and watched
    RELEARNING = "relearning"        # the model in use stopped explaining the injector (or a relearn command):
                                     # collecting again while it keeps serving

    def __str__(self) -> str:
        return self.value


#: the words of the learning states, in the order of their bus codes
CALIBRATION_STATES = tuple(s.value for s in Learning)

#: statuses whose published (N_u, L_h) is an estimate of this injection (not the previous one held)
ESTIMATED = frozenset({Status.OK, Status.AT_BOUND, Status.NOT_CONVERGED, Status.UNCERTAIN, Status.UNCONFIRMED,
                       Status.MODEL_MISMATCH, Status.STALE})
ESTIMATED_WORDS = frozenset(s.value for s in ESTIMATED)   # the same, as the words of JSON and CSV rows
