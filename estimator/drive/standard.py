"""The amplifier's own standard drive: the current it delivers at scale 1 and offset 0, as a table on
the sample grid, and the check of each injection's measured current against it.

A drive correction is a scale of this current and a shift of its start; its predicted stroke and
opening instant are simulated with it. The built-in trapezoid (:class:`~estimator.model.drive.StandardDrive`)
is one amplifier's drive among many: another amplifier delivers the same charge in another shape
(a shorter plateau at a higher current, a current controller's overshoot and ripple), and a
correction simulated with the wrong shape opens the valve a few µs off while its σ says 0.1 µs.
So the drive is either **configured** (a current table, e.g. written by ``python -m estimator
drive-table`` from a trace recorded at the standard drive) or **learned** from the measured current
of each injector's first injections, the ones the amplifier drives with its standard drive because no
valid correction has been published for that injector yet (:class:`DriveLearner`).

Either way every later injection's measured current is checked against it (:meth:`AmplifierDrive.check`):
the least-squares scale of the standard drive that best explains the measured current, and what that
scaled drive leaves unexplained relative to the current itself. A disagreement beyond the tolerance
(the amplifier changed its shape, a channel was swapped, the configured table is not this
amplifier's) holds the correction; it is never a silent bias. Pure: arrays in, arrays out.
"""

from __future__ import annotations

import base64
import math
from typing import Any, NamedTuple

import numpy as np

from estimator.model.chain import MeasurementChain
from estimator.model.drive import SAMPLE_PERIOD_S, Drive, StandardDrive, TableDrive, same_grid, sample_times

LEARN_INJECTIONS = 4          # injections at the standard drive averaged into a learned drive
SHAPE_TOLERANCE = 0.10        # RMS of the unexplained current / RMS of the current that still agrees
AMPLITUDE_TOLERANCE = 0.02    # a learned drive's injections agree in amplitude (least-squares scale) this well:
                              # the standard drive repeats to 0.2 %, an amplifier still applying the correction
                              # of a daemon that restarted does not
MIN_PEAK_A = 0.2              # a measured current whose peak is below this drives nothing: not checked
MAX_LENGTH_S = 2e-3           # a drive table longer than this (s) is refused (an injection lasts < 1 ms)
MAX_GRIDS = 16                # sampled grids (period, length) and chains a drive keeps


class DriveCheck(NamedTuple):
    """One injection's measured current against the standard drive: ``scale`` (the least-squares
    factor of the standard drive, relative), ``residual_rel`` (RMS of what the scaled standard drive
    leaves unexplained over the RMS of the measured current), ``agrees`` (within the tolerance)."""

    scale: float
    residual_rel: float
    agrees: bool


class AmplifierDrive:
    """The amplifier's standard drive as a current table: ``current_a`` (A) sampled every ``dt_s`` (s)
    from the start of charging, zero after its last sample (the amplifier holding the charge).
    ``source`` says where it came from (``trapezoid``, ``learned``, a file name). ``measured``: the
    table is the current as the amplifier's current channel records it (learned, or a recorded trace),
    so a model's measurement chain (its current filter and skew) is undone on it before it drives that
    model (:meth:`actuator_samples`), as on every injection's samples; False for a designed current
    (the built-in trapezoid)."""

    def __init__(self, current_a: np.ndarray, dt_s: float, source: str, measured: bool = True) -> None:
        cur = np.asarray(current_a, dtype=float)
        if cur.ndim != 1 or cur.size < 2 or not np.all(np.isfinite(cur)):
            raise ValueError("a standard drive needs at least two finite current samples")
        if not (math.isfinite(dt_s) and dt_s > 0 and cur.size * dt_s <= MAX_LENGTH_S):
            raise ValueError(f"standard drive: sample period {dt_s!r} s and {cur.size} samples must span "
                             f"at most {MAX_LENGTH_S * 1e3:g} ms")
        if float(np.max(np.abs(cur))) < MIN_PEAK_A:
            raise ValueError(f"standard drive: peak current {float(np.max(np.abs(cur))):.3f} A drives nothing")
        self.current_a = cur
        self.dt_s = float(dt_s)
        self.source = source
        self.measured = measured
        self._grids: dict[tuple[float, int], np.ndarray] = {}
        self._references: dict[tuple[float, int], tuple[np.ndarray, float]] = {}
        self._actuator: dict[tuple[float, int, MeasurementChain], np.ndarray] = {}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the sample period (s), where it came from, whether it was measured, and the
        current (A) as little-endian float32 in base64 (about 11 kB for 1 ms at 0.5 µs)."""
        return {"dt_s": self.dt_s, "source": self.source, "measured": self.measured,
                "current_a": base64.b64encode(self.current_a.astype("<f4").tobytes()).decode("ascii")}

    @classmethod
    def from_dict(cls, d: Any) -> AmplifierDrive:
        """The inverse of :meth:`to_dict`, validated as a drive; ValueError for anything else."""
        if not isinstance(d, dict) or not isinstance(d.get("current_a"), str) or not isinstance(d.get("source"), str):
            raise ValueError("a standard drive needs current_a (base64) and source")
        try:
            raw = base64.b64decode(d["current_a"].encode("ascii"), validate=True)
        except (ValueError, UnicodeEncodeError) as exc:
            raise ValueError(f"a standard drive's current_a is not base64: {exc}") from None
        if len(raw) % 4:
            raise ValueError("a standard drive's current_a is not float32 samples")
        dt = d.get("dt_s")
        if isinstance(dt, bool) or not isinstance(dt, (int, float)):
            raise ValueError(f"a standard drive's dt_s {dt!r} is not a number")
        return cls(np.frombuffer(raw, dtype="<f4").astype(float), float(dt), d["source"], bool(d.get("measured", True)))

    @classmethod
    def trapezoid(cls, dt_s: float = SAMPLE_PERIOD_S, t_end_s: float = 700e-6) -> AmplifierDrive:
        """The built-in trapezoid (:class:`~estimator.model.drive.StandardDrive`) as a table."""
        return cls(StandardDrive().samples(t_end_s, dt_s), dt_s, "trapezoid", measured=False)

    @classmethod
    def from_table(cls, t_s: np.ndarray, current_a: np.ndarray, source: str) -> AmplifierDrive:
        """A drive given at increasing times from the start of charging (a recorded or designed current,
        s and A), resampled to 0.5 µs; ValueError (or TraceError) for a table that is not one."""
        drive = TableDrive.from_table(t_s, current_a)
        if drive.t_s[0] < 0 or drive.t_s[-1] > MAX_LENGTH_S:
            raise ValueError(f"standard drive {source}: times must lie in [0, {MAX_LENGTH_S * 1e3:g}] ms")
        return cls(drive.samples(float(drive.t_s[-1]), SAMPLE_PERIOD_S), SAMPLE_PERIOD_S, source)

    def as_drive(self) -> Drive:
        """The table as a :class:`~estimator.model.drive.Drive` (zero after its last sample)."""
        return TableDrive.sampled(self.current_a, self.dt_s)

    def samples(self, dt_s: float, t_end_s: float) -> np.ndarray:
        """Unit-scale current (A) on the grid 0, dt, ..., t_end (s); cached per grid (do not modify)."""
        key = (float(dt_s), int(round(t_end_s / dt_s)))
        got = self._grids.get(key)
        if got is None:
            if same_grid(self.dt_s, dt_s):
                got = np.zeros(key[1] + 1)
                k = min(got.size, self.current_a.size)
                got[:k] = self.current_a[:k]
            else:
                got = self.as_drive().current(sample_times(t_end_s, dt_s))
            got.setflags(write=False)
            if len(self._grids) >= MAX_GRIDS:   # every injection's length can differ: the cache stays bounded
                self._grids.clear()
            self._grids[key] = got
        return got

    def actuator_samples(self, dt_s: float, t_end_s: float, chain: MeasurementChain) -> np.ndarray:
        """Unit-scale current (A) in the actuator on the grid 0, dt, ..., t_end (s) as a model with the
        measurement ``chain`` sees it: :meth:`samples` with the chain's current filter and skew undone
        when the table is a measured one; cached per grid and chain (do not modify)."""
        raw = self.samples(dt_s, t_end_s)
        if not self.measured or chain.identity:
            return raw
        key = (float(dt_s), raw.size, chain)
        got = self._actuator.get(key)
        if got is None:
            got = chain.actuator_current(raw, dt_s)
            got.setflags(write=False)
            if len(self._actuator) >= MAX_GRIDS:   # a chain per learned model: a few at most
                self._actuator.clear()
            self._actuator[key] = got
        return got

    def check(self, current_a: np.ndarray, dt_s: float, tolerance: float = SHAPE_TOLERANCE) -> DriveCheck:
        """The measured current of one injection (A, sampled every ``dt_s`` s from the start of
        charging) against this drive over the measured window (:class:`DriveCheck`)."""
        cur = np.asarray(current_a, dtype=float)
        ref, den = self._reference(dt_s, cur.size)
        cross, norm2 = float(np.dot(ref, cur)), float(np.dot(cur, cur))
        if den <= 0 or not (math.isfinite(cross) and math.isfinite(norm2)):
            return DriveCheck(math.nan, math.inf, False)
        scale = cross / den
        # |cur - scale ref|² = |cur|² - scale (ref·cur), without the residual's array (every injection)
        rel = math.sqrt(max(norm2 - scale * cross, 0.0) / norm2) if norm2 > 0 else math.inf
        return DriveCheck(scale, rel, bool(rel <= tolerance and scale > 0))

    def _reference(self, dt_s: float, size: int) -> tuple[np.ndarray, float]:
        """:meth:`samples` for ``size`` samples every ``dt_s`` s and its squared norm (A²), cached per grid
        (every injection is checked: the norm is not taken again)."""
        key = (float(dt_s), size)
        got = self._references.get(key)
        if got is None:
            ref = self.samples(dt_s, (size - 1) * dt_s)
            got = (ref, float(np.dot(ref, ref)))
            if len(self._references) >= MAX_GRIDS:
                self._references.clear()
            self._references[key] = got
        return got


class DriveLearner:
    """The standard drive learned from the measured current of injections the amplifier drove with it:
    the mean of ``needed`` of them (their noise and chopper ripple average out), each checked against the
    mean so far, in shape and in amplitude (``AMPLITUDE_TOLERANCE``), so that one odd injection does not
    become the drive: an amplifier may still apply the last correction of a daemon that restarted until
    the new one publishes ``State`` none."""

    def __init__(self, needed: int = LEARN_INJECTIONS, tolerance: float = SHAPE_TOLERANCE) -> None:
        self.needed = needed
        self.tolerance = tolerance
        self._sum: np.ndarray | None = None
        self._dt_s = math.nan
        self.count = 0
        self.drive: AmplifierDrive | None = None

    @classmethod
    def learned(cls, drive: AmplifierDrive, needed: int = LEARN_INJECTIONS,
                tolerance: float = SHAPE_TOLERANCE) -> DriveLearner:
        """A learner that has learned ``drive`` already (one restored from the daemon's state)."""
        out = cls(needed, tolerance)
        out.drive, out.count = drive, needed
        return out

    def add(self, current_a: np.ndarray, dt_s: float) -> bool:
        """Add one injection at the standard drive; False when it was not added to the ones before (not a
        drive, or another grid, length or shape: the learning starts again from it)."""
        cur = np.asarray(current_a, dtype=float)
        if self.drive is not None or not np.all(np.isfinite(cur)) or float(np.max(np.abs(cur), initial=0.0)) < MIN_PEAK_A:
            return False
        same = (self._sum is not None and self._sum.size == cur.size and same_grid(self._dt_s, dt_s))
        if same:
            assert self._sum is not None
            mean = AmplifierDrive(self._sum / self.count, self._dt_s, "learned")
            check = mean.check(cur, dt_s, self.tolerance)
            if not (check.agrees and abs(check.scale - 1.0) <= AMPLITUDE_TOLERANCE):
                same = False
        first = self._sum is None
        if not same:
            self._sum, self._dt_s, self.count = cur.copy(), float(dt_s), 1
        else:
            assert self._sum is not None
            self._sum += cur
            self.count += 1
        if self.count >= self.needed:
            self.drive = AmplifierDrive(self._sum / self.count, self._dt_s, "learned")
        return same or first


def from_recordings(currents: list[np.ndarray], dt_s: float, source: str,
                    tolerance: float = SHAPE_TOLERANCE) -> tuple[AmplifierDrive, list[int]]:
    """The standard drive from currents recorded at it (A, each sampled every ``dt_s`` s from the start
    of charging; cut to the shortest): their mean, without the recordings it does not explain (their
    indices, returned; at least half must agree). ValueError when none can serve."""
    if not currents:
        raise ValueError("no recorded current")
    n = min(c.size for c in currents)
    stack = np.array([np.asarray(c, dtype=float)[:n] for c in currents])
    if not np.all(np.isfinite(stack)):
        raise ValueError("a recorded current holds NaN or infinite samples")
    median = AmplifierDrive(np.median(stack, axis=0), dt_s, source)   # robust to an odd recording
    odd = [i for i, c in enumerate(stack) if not median.check(c, dt_s, tolerance).agrees]
    if 2 * len(odd) > len(currents):
        raise ValueError(f"{len(odd)} of {len(currents)} recordings disagree with their median: not one drive")
    keep = [i for i in range(len(currents)) if i not in odd]
    return AmplifierDrive(stack[keep].mean(axis=0), dt_s, source), odd
