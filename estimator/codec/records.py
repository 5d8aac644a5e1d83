"""Typed records of the contract's messages and their conversion to and from frames (cantools).

The record classes are the codec's registry (:data:`REGISTRY`): each names its DBC message and maps
its fields to signals, and from them come the contract the DBC is checked against
(:data:`CONTRACT`), the message lookup and the frame-identifier dispatch of :class:`Codec`.
Adding a message means adding it to the DBC and writing one class here (see "Extending" in docs/design.md).

Encoding is strict (cantools ``strict=True``, or :mod:`estimator.codec.packer`, which writes the
same bytes); values outside a signal's range are saturated to the range first, so a publisher never fails on an extreme value (a cost above 6553.5 µV·s is sent
as 6553.5). NaN has no wire form: ``ValvePrediction`` carries validity bits, the others send 0 with
a status that says there is no estimate. Decoding range-checks every value against the DBC.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from enum import IntEnum
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from cantools.database.can import Database, Message

from estimator.codec import database
from estimator.codec.database import MessageSpec
from estimator.codec.errors import ContractError, MalformedFrame
from estimator.codec.frame import Frame
from estimator.codec.packer import packer_for
from estimator.codec.samples import SampleLayout
from estimator.ident.status import CALIBRATION_STATES, Status


class Command(IntEnum):
    """``EstimatorCommand.Command`` (VAL_ table of the DBC)."""

    NONE = 0
    RESET = 1
    SET_PRIOR = 2
    RELEARN = 3


@dataclass(frozen=True)
class Record:
    """Base of the typed records.

    ``MESSAGE`` names the DBC message, ``SIGNALS`` maps field -> signal; ``CODEC_SIGNALS`` are further
    signals the class fills and reads itself (:meth:`extra_signals`, :meth:`from_signals`);
    ``CLASSIC``: the message must fit a classic 8-byte frame; ``OUTPUT``: the estimator publishes it.
    ``UNMEASURED_AT_MINIMUM``: float fields whose signal minimum on the wire means "not measured": NaN
    in the record (the DBC's minimum, whatever it is, is the one source of that convention).
    """

    MESSAGE: ClassVar[str] = ""
    SIGNALS: ClassVar[dict[str, str]] = {}
    CODEC_SIGNALS: ClassVar[tuple[str, ...]] = ()
    UNMEASURED_AT_MINIMUM: ClassVar[frozenset[str]] = frozenset()
    CLASSIC: ClassVar[bool] = False
    OUTPUT: ClassVar[bool] = False

    def extra_signals(self) -> dict[str, int]:
        """Values of ``CODEC_SIGNALS`` for encoding."""
        return {}

    def from_signals(self, values: dict[str, Any]) -> Record:
        """The record after decoding, given all decoded signal values (default: itself)."""
        return self


def counter() -> Any:
    """A rolling counter field of the heartbeat (0 at start; wraps at its signal's width)."""
    return field(default=0, metadata={"counter": True})


@dataclass(frozen=True)
class InjectionHeader(Record):
    injector_id: int
    counter: int
    sample_period_ns: int
    sample_count: int
    preload_force_n: float
    fuel_temperature_c: float
    MESSAGE: ClassVar[str] = "InjectionHeader"
    SIGNALS: ClassVar[dict[str, str]] = {
        "injector_id": "InjectorId", "counter": "InjectionCounter", "sample_period_ns": "SamplePeriod",
        "sample_count": "SampleCount", "preload_force_n": "PreloadForce", "fuel_temperature_c": "FuelTemperature"}
    UNMEASURED_AT_MINIMUM: ClassVar[frozenset[str]] = frozenset({"fuel_temperature_c"})   # NaN: not measured


@dataclass(frozen=True)
class InjectionTrailer(Record):
    injector_id: int
    counter: int
    crc32: int
    MESSAGE: ClassVar[str] = "InjectionTrailer"
    SIGNALS: ClassVar[dict[str, str]] = {"injector_id": "InjectorId", "counter": "InjectionCounter", "crc32": "Crc32"}


@dataclass(frozen=True)
class EstimateState(Record):
    injector_id: int
    counter: int
    nu_n_per_v: float
    lh_um: float
    status: int
    MESSAGE: ClassVar[str] = "EstimateState"
    CLASSIC: ClassVar[bool] = True
    OUTPUT: ClassVar[bool] = True
    SIGNALS: ClassVar[dict[str, str]] = {"injector_id": "InjectorId", "counter": "InjectionCounter",
                                         "nu_n_per_v": "CouplingNu", "lh_um": "IdleStroke", "status": "Status"}


@dataclass(frozen=True)
class EstimateQuality(Record):
    injector_id: int
    counter: int
    cost_uvs: float
    sigma_nu_n_per_v: float
    sigma_lh_um: float
    evaluations: int
    robust: int
    MESSAGE: ClassVar[str] = "EstimateQuality"
    OUTPUT: ClassVar[bool] = True
    SIGNALS: ClassVar[dict[str, str]] = {
        "injector_id": "InjectorId", "counter": "InjectionCounter", "cost_uvs": "Cost",
        "sigma_nu_n_per_v": "SigmaNu", "sigma_lh_um": "SigmaIdleStroke", "evaluations": "Evaluations",
        "robust": "Robust"}


@dataclass(frozen=True)
class ValvePrediction(Record):
    injector_id: int
    counter: int
    contact_us: float
    opening_us: float
    stroke_um: float
    MESSAGE: ClassVar[str] = "ValvePrediction"
    SIGNALS: ClassVar[dict[str, str]] = {"injector_id": "InjectorId", "counter": "InjectionCounter",
                                         "contact_us": "ContactTime", "opening_us": "OpeningTime",
                                         "stroke_um": "PlungerStroke"}
    CODEC_SIGNALS: ClassVar[tuple[str, ...]] = ("Valid",)
    OUTPUT: ClassVar[bool] = True
    _VALID_BITS: ClassVar[tuple[tuple[str, int], ...]] = (("contact_us", 1), ("opening_us", 2), ("stroke_um", 4))

    def extra_signals(self) -> dict[str, int]:
        """``Valid``: one bit per finite value (NaN has no wire form)."""
        return {"Valid": sum(bit for name, bit in self._VALID_BITS if math.isfinite(getattr(self, name)))}

    def from_signals(self, values: dict[str, Any]) -> ValvePrediction:
        """NaN for the values whose ``Valid`` bit is clear."""
        valid = int(values["Valid"])
        return ValvePrediction(self.injector_id, self.counter,
                               *(getattr(self, n) if valid & b else float("nan") for n, b in self._VALID_BITS))


@dataclass(frozen=True)
class ModelCalibration(Record):
    """Where one injector's learning stands (``state``: the code of a
    :class:`~estimator.ident.status.Learning` word, the DBC's VAL_ table; ``preload_span`` the
    learning's progress, relative; ``out_of_tolerance`` how many structural parameters the last
    calibration found beyond the part's tolerance)."""

    injector_id: int
    state: int
    batch: int
    rms_before_v: float
    rms_after_v: float
    calibrations: int
    preload_span: float = 0.0
    out_of_tolerance: int = 0
    MESSAGE: ClassVar[str] = "ModelCalibration"
    CLASSIC: ClassVar[bool] = True
    OUTPUT: ClassVar[bool] = True
    SIGNALS: ClassVar[dict[str, str]] = {"injector_id": "InjectorId", "state": "State", "batch": "Batch",
                                         "rms_before_v": "RmsBefore", "rms_after_v": "RmsAfter",
                                         "calibrations": "Calibrations", "preload_span": "PreloadSpan",
                                         "out_of_tolerance": "OutOfTolerance"}


@dataclass(frozen=True)
class DriveCorrection(Record):
    """One injector's drive correction after an injection (``state``: 0 none, 1 valid, 2 held; see
    :class:`estimator.drive.correction.Correction`)."""

    injector_id: int
    counter: int
    scale: float
    offset_us: float
    stroke_um: float
    sigma_stroke_um: float
    opening_us: float
    sigma_opening_us: float
    scale_per_kn: float
    offset_per_kn_us: float
    preload_n: float
    state: int
    at_limit: int
    trust_limited: int
    MESSAGE: ClassVar[str] = "DriveCorrection"
    OUTPUT: ClassVar[bool] = True
    SIGNALS: ClassVar[dict[str, str]] = {
        "injector_id": "InjectorId", "counter": "InjectionCounter", "scale": "Scale", "offset_us": "Offset",
        "stroke_um": "Stroke", "sigma_stroke_um": "SigmaStroke", "opening_us": "Opening",
        "sigma_opening_us": "SigmaOpening", "scale_per_kn": "ScalePerKn", "offset_per_kn_us": "OffsetPerKn",
        "preload_n": "Preload", "state": "State", "at_limit": "AtLimit",
        "trust_limited": "TrustLimited"}


@dataclass(frozen=True)
class DriveCorrectionRow(Record):
    """One row of an injector's drive-correction table: ``scale`` and ``offset_us`` at ``preload_n``,
    and the σ of the stroke (µm) and the opening instant (µs) they give there (row ``row`` of ``rows``;
    see :meth:`estimator.drive.correction.Correction.at` and ``sigma_at``)."""

    injector_id: int
    counter: int
    row: int
    rows: int
    preload_n: float
    scale: float
    offset_us: float
    sigma_stroke_um: float = 0.0
    sigma_opening_us: float = 0.0
    MESSAGE: ClassVar[str] = "DriveCorrectionTable"
    OUTPUT: ClassVar[bool] = True
    SIGNALS: ClassVar[dict[str, str]] = {
        "injector_id": "InjectorId", "counter": "InjectionCounter", "row": "Row", "rows": "Rows",
        "preload_n": "Preload", "scale": "Scale", "offset_us": "Offset", "sigma_stroke_um": "SigmaStroke",
        "sigma_opening_us": "SigmaOpening"}


@dataclass(frozen=True)
class EstimatorStatus(Record):
    """The heartbeat. Fields made with :func:`counter` are the rolling counters (:data:`HEARTBEAT_COUNTERS`),
    which ``ingest.Counters`` keeps under the same names; the others are gauges."""

    accepted: int = counter()
    rejected_crc: int = counter()
    rejected_missing: int = counter()
    rejected_timeout: int = counter()
    rejected_invalid: int = counter()
    rejected_outlier: int = counter()
    frames_dropped: int = counter()
    frames_malformed: int = counter()
    queue_depth: int = 0
    latency_p99_ms: float = 0.0
    uptime_s: int = 0
    bus_errors: int = counter()
    commands_refused: int = counter()
    commands_unknown: int = counter()
    queue_p99_ms: float = 0.0
    assembly_p99_ms: float = 0.0
    estimation_p99_ms: float = 0.0
    send_p99_ms: float = 0.0
    MESSAGE: ClassVar[str] = "EstimatorStatus"
    OUTPUT: ClassVar[bool] = True
    SIGNALS: ClassVar[dict[str, str]] = {
        "accepted": "InjectionsAccepted", "rejected_crc": "RejectedCrc", "rejected_missing": "RejectedMissing",
        "rejected_timeout": "RejectedTimeout", "rejected_invalid": "RejectedInvalid",
        "rejected_outlier": "RejectedOutlier", "frames_dropped": "FramesDropped",
        "frames_malformed": "FramesMalformed", "queue_depth": "QueueDepth", "latency_p99_ms": "LatencyP99",
        "uptime_s": "Uptime", "bus_errors": "BusErrors", "commands_refused": "CommandsRefused",
        "commands_unknown": "CommandsUnknown", "queue_p99_ms": "QueueP99", "assembly_p99_ms": "AssemblyP99",
        "estimation_p99_ms": "EstimationP99", "send_p99_ms": "SendP99"}


@dataclass(frozen=True)
class EstimatorHealth(Record):
    """Health counters sent with each heartbeat: the worker's overload defences and what they cost.
    Counter fields are rolling (they wrap at 32 bits); ``pending_injections`` and ``injectors`` are gauges."""

    commands_applied: int = 0
    stale: int = 0
    injections_shed: int = 0
    simulators_built: int = 0
    simulators_evicted: int = 0
    builds_refused: int = 0
    worker_errors: int = 0
    pending_injections: int = 0
    injectors: int = 0
    xcp_writes: int = 0
    MESSAGE: ClassVar[str] = "EstimatorHealth"
    OUTPUT: ClassVar[bool] = True
    SIGNALS: ClassVar[dict[str, str]] = {
        "commands_applied": "CommandsApplied", "stale": "EstimatesStale", "injections_shed": "InjectionsShed",
        "simulators_built": "SimulatorsBuilt", "simulators_evicted": "SimulatorsEvicted",
        "builds_refused": "BuildsRefused", "worker_errors": "WorkerErrors",
        "pending_injections": "PendingInjections", "injectors": "InjectorsTracked", "xcp_writes": "XcpWrites"}


#: the heartbeat's rolling counters, in DBC order: the one list of them (``ingest.Counters`` is built from it)
HEARTBEAT_COUNTERS: tuple[str, ...] = tuple(f.name for f in fields(EstimatorStatus) if f.metadata.get("counter"))


@dataclass(frozen=True)
class EstimatorCommand(Record):
    injector_id: int
    command: int                 # a Command code; undefined codes arrive as they are and are counted
    prior_nu_n_per_v: float = 0.0
    prior_lh_um: float = 0.0
    MESSAGE: ClassVar[str] = "EstimatorCommand"
    SIGNALS: ClassVar[dict[str, str]] = {"injector_id": "InjectorId", "command": "Command",
                                         "prior_nu_n_per_v": "PriorNu", "prior_lh_um": "PriorIdleStroke"}


@dataclass(frozen=True)
class SimTruth(Record):
    injector_id: int
    counter: int
    nu_n_per_v: float
    lh_um: float
    contact_us: float
    opening_us: float
    stroke_um: float
    temperature_c: float
    preload_force_n: float
    MESSAGE: ClassVar[str] = "SimTruth"
    SIGNALS: ClassVar[dict[str, str]] = {
        "injector_id": "InjectorId", "counter": "InjectionCounter", "nu_n_per_v": "TrueNu",
        "lh_um": "TrueIdleStroke", "contact_us": "TrueContactTime", "opening_us": "TrueOpeningTime",
        "stroke_um": "TrueStroke", "temperature_c": "Temperature", "preload_force_n": "TruePreloadForce"}


@dataclass(frozen=True)
class SampleBlock(Record):
    """One InjectionSamples frame: raw int16 current/voltage of up to ``per_block`` samples.

    Only the identification prefix is listed in ``SIGNALS``: the sample pairs are the
    ``Current_k``/``Voltage_k`` signals, read with numpy (:class:`samples.SampleLayout`).
    """

    injector_id: int
    counter: int
    block_index: int
    current_raw: np.ndarray
    voltage_raw: np.ndarray
    MESSAGE: ClassVar[str] = "InjectionSamples"
    SIGNALS: ClassVar[dict[str, str]] = {"injector_id": "InjectorId", "counter": "InjectionCounter",
                                         "block_index": "BlockIndex"}


#: every message of the contract, by record class
REGISTRY: tuple[type[Record], ...] = (InjectionHeader, SampleBlock, InjectionTrailer, EstimateState, EstimateQuality,
                                      ValvePrediction, ModelCalibration, DriveCorrection, DriveCorrectionRow, EstimatorStatus,
                                      EstimatorHealth,
                                      EstimatorCommand,
                                      SimTruth)


def contract_of(registry: tuple[type[Record], ...]) -> dict[str, MessageSpec]:
    """What a DBC must provide for the record classes of ``registry``: {message name: spec}."""
    return {rt.MESSAGE: MessageSpec(tuple(rt.SIGNALS.values()) + rt.CODEC_SIGNALS, rt.CLASSIC) for rt in registry}


#: what the DBC must provide, derived from the registry
CONTRACT: dict[str, MessageSpec] = contract_of(REGISTRY)


def load_database(path: str | Path | None = None) -> Database:
    """The DBC (default: the packaged one), loaded strictly and checked against :data:`CONTRACT`."""
    return database.load_database(path, CONTRACT)


def _signal_values(rec: Record, minimum: Callable[[str], Any]) -> dict[str, Any]:
    """The record's field values by signal name, an unmeasured one (None or not finite) at its signal's
    ``minimum`` (the wire's "not measured")."""
    out: dict[str, Any] = {}
    for fname, sname in rec.SIGNALS.items():
        v = getattr(rec, fname)
        if fname in rec.UNMEASURED_AT_MINIMUM and not (v is not None and math.isfinite(v)):
            v = minimum(sname)
        out[sname] = v
    return out


class Codec:
    """Typed records <-> frames for the contract's messages, resolved once from the DBC."""

    def __init__(self, db: Database | None = None, registry: tuple[type[Record], ...] = REGISTRY) -> None:
        self.db = db or load_database()
        if registry is not REGISTRY:   # the default contract was checked when the DBC was loaded
            problems = database.check_contract(self.db, contract_of(registry))
            if problems:
                raise ContractError("the DBC violates the contract: " + "; ".join(problems))
        #: the DBC message of every record class
        self.messages: dict[type[Record], Message] = {rt: self.db.get_message_by_name(rt.MESSAGE) for rt in registry}
        samples = self.messages[SampleBlock]
        self.layout = SampleLayout.from_message(samples)
        self._by_id: dict[int, tuple[Message, type[Record]]] = {m.frame_id: (m, rt) for rt, m in self.messages.items()}
        self._packers = {rt: packer_for(m) for rt, m in self.messages.items()}   # None: cantools encodes it
        self._prefix_signals = [samples.get_signal_by_name(SampleBlock.SIGNALS[n])
                                for n in ("injector_id", "counter", "block_index")]
        self._prefix_fields = [(sig.start, (1 << sig.length) - 1) for sig in self._prefix_signals]
        self._max_block = self._prefix_signals[2].maximum or 255   # BlockIndex
        for sig in self._prefix_signals:   # the numpy packer/decoder assume this (checked, not hoped)
            if sig.byte_order != "little_endian" or sig.start + sig.length > 8 * self.layout.current_offset \
                    or sig.scale != 1 or sig.offset != 0:
                raise ContractError(f"InjectionSamples.{sig.name}: must be a little-endian integer in the "
                                    f"first {self.layout.current_offset} bytes")

        #: the words of the DBC's value tables and their codes on the bus (one source: the DBC)
        self._status_codes = self._value_table(EstimateState, "status", [s.value for s in Status])
        self._calibration_codes = self._value_table(ModelCalibration, "state", list(CALIBRATION_STATES))
        self._status_words = {code: word for word, code in self._status_codes.items()}
        self._calibration_words = {code: word for word, code in self._calibration_codes.items()}

    def _value_table(self, record_type: type[Record], field: str, words: list[str]) -> dict[str, int]:
        """The DBC's value table of a record's field as {word: code}; every one of ``words`` must be in it."""
        name = record_type.SIGNALS[field]
        sig = self.messages[record_type].get_signal_by_name(name)
        table = {str(word): int(code) for code, word in (sig.choices or {}).items()}
        missing = [w for w in words if w not in table]
        if missing:
            raise ContractError(f"{record_type.MESSAGE}.{name}: no code for {', '.join(missing)} in the DBC's value table")
        return table

    def signal_range(self, record_type: type[Record], field: str) -> tuple[float, float]:
        """The physical range of a record's field on the wire (the DBC's minimum and maximum)."""
        sig = self.messages[record_type].get_signal_by_name(record_type.SIGNALS[field])
        return (float(sig.minimum) if sig.minimum is not None else -math.inf,
                float(sig.maximum) if sig.maximum is not None else math.inf)

    def status_code(self, status: Status | str) -> int:
        """The bus code of an estimate's status (``EstimateState.Status``)."""
        return self._status_codes[str(status)]

    def status_of(self, code: int) -> Status | None:
        """The status a decoded ``EstimateState.Status`` code stands for; None for a code the DBC does not name."""
        word = self._status_words.get(int(code))
        return Status(word) if word in Status._value2member_map_ else None

    def calibration_code(self, state: str) -> int:
        """The bus code of a self-calibration state (``ModelCalibration.State``)."""
        return self._calibration_codes[state]

    def calibration_state(self, code: int) -> str | None:
        """The self-calibration state a decoded ``ModelCalibration.State`` code stands for."""
        return self._calibration_words.get(int(code))

    def frame_id(self, record_type: type[Record]) -> int:
        """The arbitration id of a record class's message."""
        result: int = self.messages[record_type].frame_id
        return result

    def output_ids(self) -> set[int]:
        """Arbitration ids of the messages the estimator publishes."""
        return {m.frame_id for rt, m in self.messages.items() if rt.OUTPUT}

    # ---- encode ---------------------------------------------------------------------------
    def encode(self, rec: Record) -> Frame:
        """The frame of a record (saturating values to the signal ranges)."""
        msg = self.messages[type(rec)]
        packer = self._packers[type(rec)]
        if packer is not None:
            raw = _signal_values(rec, packer.minimum.__getitem__)
            raw.update(rec.extra_signals())
            return Frame(msg.frame_id, packer.pack_saturated(raw), msg.is_fd)
        return self.encode_with_cantools(rec)

    def encode_with_cantools(self, rec: Record) -> Frame:
        """:meth:`encode` by cantools' strict encoder: for a message the packer does not cover, and the
        reference the packer is tested against."""
        msg = self.messages[type(rec)]
        values: dict[str, Any] = {sname: self._wire_value(msg, sname, v) for sname, v in
                                  _signal_values(rec, lambda sname: msg.get_signal_by_name(sname).minimum).items()}
        values.update(rec.extra_signals())
        for s in msg.signals:   # signals the record does not carry (none today) go out as their minimum
            values.setdefault(s.name, s.minimum if s.minimum is not None else 0)
        data = msg.encode(values, strict=True)
        return Frame(msg.frame_id, bytes(data), msg.is_fd)

    @staticmethod
    def _wire_value(msg: Message, sname: str, value: float) -> float | int:
        sig = msg.get_signal_by_name(sname)
        v = float(value) if value is not None else float("nan")
        if not math.isfinite(v):
            v = 0.0
        lo = sig.minimum if sig.minimum is not None else -math.inf
        hi = sig.maximum if sig.maximum is not None else math.inf
        v = min(max(v, lo), hi)
        if sig.scale == 1 and sig.offset == 0:
            return int(round(v))
        # round to the wire grid so that strict encoding never sees an off-grid value
        result: float | int = round((v - sig.offset) / sig.scale) * sig.scale + sig.offset
        return result

    def encode_samples(self, injector_id: int, counter: int, block_index: int, current_raw: np.ndarray,
                       voltage_raw: np.ndarray) -> Frame:
        """One InjectionSamples frame from raw int16 pairs (numpy packing; layout from the DBC)."""
        msg = self.messages[SampleBlock]
        word = 0
        for sig, v in zip(self._prefix_signals, (injector_id, counter, block_index)):
            if not (sig.minimum <= v <= sig.maximum):
                raise ValueError(f"InjectionSamples.{sig.name} = {v} outside [{sig.minimum}, {sig.maximum}]")
            word |= int(v) << sig.start
        prefix = word.to_bytes(4, "little")
        return Frame(msg.frame_id, self.layout.encode(prefix, current_raw, voltage_raw), True)

    # ---- decode ---------------------------------------------------------------------------
    def is_known(self, arbitration_id: int) -> bool:
        """True for identifiers of the contract."""
        return arbitration_id in self._by_id

    def decode(self, frame: Frame) -> Record | SampleBlock | None:
        """The record of a frame; None for unknown identifiers; MalformedFrame if it cannot be decoded."""
        entry = self._by_id.get(frame.arbitration_id)
        if entry is None or frame.is_extended_id:
            return None
        msg, rt = entry
        if len(frame.data) != msg.length:
            raise MalformedFrame(f"{msg.name}: {len(frame.data)} bytes, expected {msg.length}")
        if msg.is_fd and not frame.is_fd:
            raise MalformedFrame(f"{msg.name}: expected a CAN FD frame")
        if rt is SampleBlock:
            return self.decode_samples(frame.data)
        try:
            values = msg.decode(frame.data, decode_choices=False, scaling=True)
        except Exception as exc:   # cantools raises DecodeError and ValueError subclasses
            raise MalformedFrame(f"{msg.name}: {exc}") from None
        for s in msg.signals:
            v = values[s.name]
            if (s.minimum is not None and v < s.minimum - 1e-9) or (s.maximum is not None and v > s.maximum + 1e-9):
                raise MalformedFrame(f"{msg.name}.{s.name} = {v} outside [{s.minimum}, {s.maximum}]")
        kw = {}
        for f in fields(rt):
            sname = rt.SIGNALS[f.name]
            v = values[sname]
            kw[f.name] = int(v) if f.type in ("int", int) else float(v)
            if f.name in rt.UNMEASURED_AT_MINIMUM:
                sig = msg.get_signal_by_name(sname)
                if sig.minimum is not None and v <= sig.minimum + 0.5 * sig.scale:
                    kw[f.name] = math.nan
        return rt(**kw).from_signals(values)

    def decode_samples(self, data: bytes) -> SampleBlock:
        """An InjectionSamples payload with numpy (identification fields with cantools' start bits)."""
        head = int.from_bytes(data[:4], "little")
        (s0, m0), (s1, m1), (s2, m2) = self._prefix_fields
        block = (head >> s2) & m2
        if block > self._max_block:
            raise MalformedFrame(f"InjectionSamples.BlockIndex = {block} out of range")
        cur, vol = self.layout.raw_pairs(data)
        return SampleBlock((head >> s0) & m0, (head >> s1) & m1, block, cur, vol)
