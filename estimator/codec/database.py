"""The CAN database: loaded once with ``strict=True`` and checked against the contract at start-up."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cantools
from cantools.database.can import Database, Message

from estimator.errors import EstimatorError

DBC_RESOURCE = ("estimator.dbc", "injector.dbc")   # dbc/ of the checkout, installed as package data
SAMPLES_PER_BLOCK_MIN = 14
MAX_CURRENT_STEP_A = 0.001
MAX_VOLTAGE_STEP_V = 0.01

# The contract: message names and the signals each must have (issue #4).
CONTRACT: dict[str, tuple[str, ...]] = {
    "InjectionHeader": ("InjectorId", "InjectionCounter", "SamplePeriod", "SampleCount", "PreloadForce",
                        "FuelTemperature"),
    "InjectionSamples": ("InjectorId", "InjectionCounter", "BlockIndex"),
    "InjectionTrailer": ("InjectorId", "InjectionCounter", "Crc32"),
    "EstimateState": ("InjectorId", "InjectionCounter", "CouplingNu", "IdleStroke", "Status"),
    "EstimateQuality": ("InjectorId", "InjectionCounter", "Cost", "SigmaNu", "SigmaIdleStroke", "Evaluations"),
    "ValvePrediction": ("InjectorId", "InjectionCounter", "ContactTime", "OpeningTime", "PlungerStroke"),
    "EstimatorStatus": ("InjectionsAccepted", "RejectedCrc", "RejectedMissing", "RejectedTimeout", "RejectedInvalid",
                        "RejectedOutlier", "FramesDropped", "FramesMalformed", "QueueDepth", "LatencyP99", "Uptime"),
    "EstimatorCommand": ("InjectorId", "Command", "PriorNu", "PriorIdleStroke"),
    "SimTruth": ("InjectorId", "InjectionCounter", "TrueNu", "TrueIdleStroke", "TrueOpeningTime", "TrueStroke",
                 "Temperature"),
}
CLASSIC = ("EstimateState",)   # must fit a classic 8-byte frame


class ContractError(EstimatorError):
    """The DBC does not satisfy the contract (missing message/signal, wrong frame format, resolution)."""


def default_dbc_path() -> Path:
    """The packaged ``dbc/injector.dbc`` (``estimator.dbc`` in an installed wheel, ``dbc/`` in a checkout)."""
    from importlib.resources import files

    try:
        res = files(DBC_RESOURCE[0]) / DBC_RESOURCE[1]
    except ModuleNotFoundError:   # running from a checkout that was never installed
        return Path(__file__).resolve().parents[2] / "dbc" / DBC_RESOURCE[1]
    return Path(str(res))


def check_contract(db: Database) -> list[str]:
    """All violations of the contract (empty when the DBC is fine)."""
    problems = []
    bus_type = getattr(getattr(db, "dbc", None), "attributes", {}).get("BusType")
    if bus_type is None or bus_type.value != "CAN FD":
        problems.append('database attribute BusType is not "CAN FD"')
    for name, signals in CONTRACT.items():
        try:
            msg = db.get_message_by_name(name)
        except KeyError:
            problems.append(f"message {name} missing")
            continue
        have = {s.name for s in msg.signals}
        for s in signals:
            if s not in have:
                problems.append(f"{name}: signal {s} missing")
        if "VFrameFormat" not in (msg.dbc.attributes if msg.dbc else {}):
            problems.append(f"{name}: no VFrameFormat attribute")
        if name in CLASSIC and (msg.is_fd or msg.length > 8):
            problems.append(f"{name}: must be a classic frame of at most 8 bytes")
        if msg.length > 8 and not msg.is_fd:
            problems.append(f"{name}: {msg.length} bytes need a CAN FD frame")
    try:
        msg = db.get_message_by_name("InjectionSamples")
        pairs = sample_pairs(msg)
        if len(pairs) < SAMPLES_PER_BLOCK_MIN:
            problems.append(f"InjectionSamples: {len(pairs)} sample pairs < {SAMPLES_PER_BLOCK_MIN}")
        if msg.length != 64 or not msg.is_fd:
            problems.append("InjectionSamples: must be a 64-byte CAN FD frame")
        for cur, volt in pairs:
            if cur.scale > MAX_CURRENT_STEP_A + 1e-12 or volt.scale > MAX_VOLTAGE_STEP_V + 1e-12:
                problems.append(f"InjectionSamples: resolution of {cur.name}/{volt.name} too coarse")
                break
    except KeyError:
        pass
    return problems


def sample_pairs(msg: Message) -> list:
    """The (Current_k, Voltage_k) signal pairs of the samples message, k = 0, 1, ... in order."""
    by_name = {s.name: s for s in msg.signals}
    pairs = []
    k = 0
    while f"Current_{k}" in by_name and f"Voltage_{k}" in by_name:
        pairs.append((by_name[f"Current_{k}"], by_name[f"Voltage_{k}"]))
        k += 1
    return pairs


def load_database(path: str | Path | None = None) -> Database:
    """Load the DBC strictly and check the contract; raises :class:`ContractError` with every problem."""
    p = Path(path) if path else default_dbc_path()
    try:
        db = cantools.database.load_file(str(p), strict=True)
    except FileNotFoundError:
        raise ContractError(f"DBC not found: {p}") from None
    except Exception as exc:   # cantools raises several parse error types
        raise ContractError(f"cannot load DBC {p}: {exc}") from None
    problems = check_contract(db)
    if problems:
        raise ContractError(f"{p} violates the contract: " + "; ".join(problems))
    return db


@dataclass(frozen=True)
class Messages:
    """The contract's messages, resolved once at start-up."""

    header: Message
    samples: Message
    trailer: Message
    state: Message
    quality: Message
    prediction: Message
    status: Message
    command: Message
    truth: Message

    @classmethod
    def from_db(cls, db: Database) -> "Messages":
        g = db.get_message_by_name
        return cls(g("InjectionHeader"), g("InjectionSamples"), g("InjectionTrailer"), g("EstimateState"),
                   g("EstimateQuality"), g("ValvePrediction"), g("EstimatorStatus"), g("EstimatorCommand"),
                   g("SimTruth"))
