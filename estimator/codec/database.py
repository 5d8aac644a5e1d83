"""The CAN database: loaded once with ``strict=True`` and checked against a contract at start-up.

The contract itself (which messages and signals) is defined by the record classes of
:mod:`estimator.codec.records`; this module only knows how to load and check.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import cantools
from cantools.database.can import Database

from estimator.codec.errors import ContractError
from estimator.codec.samples import sample_pairs

DBC_RESOURCE = ("estimator.dbc", "injector.dbc")   # dbc/ of the checkout, installed as package data
SAMPLES_PER_BLOCK_MIN = 14
MAX_CURRENT_STEP_A = 0.001
MAX_VOLTAGE_STEP_V = 0.01


def default_dbc_path() -> Path:
    """The packaged ``dbc/injector.dbc`` (``estimator.dbc`` in an installed wheel, ``dbc/`` in a checkout)."""
    from importlib.resources import files

    try:
        res = files(DBC_RESOURCE[0]) / DBC_RESOURCE[1]
    except ModuleNotFoundError:   # running from a checkout that was never installed
        return Path(__file__).resolve().parents[2] / "dbc" / DBC_RESOURCE[1]
    return Path(str(res))


@dataclass(frozen=True)
class MessageSpec:
    """What the contract requires of one message: its signals, and whether it must be a classic frame."""

    signals: tuple[str, ...]
    classic: bool = False


def check_contract(db: Database, contract: Mapping[str, MessageSpec]) -> list[str]:
    """All violations of ``contract`` ({message name: spec}, see ``records.CONTRACT``); empty when fine."""
    problems = []
    bus_type = getattr(getattr(db, "dbc", None), "attributes", {}).get("BusType")
    if bus_type is None or bus_type.value != "CAN FD":
        problems.append('database attribute BusType is not "CAN FD"')
    for name, spec in contract.items():
        try:
            msg = db.get_message_by_name(name)
        except KeyError:
            problems.append(f"message {name} missing")
            continue
        have = {s.name for s in msg.signals}
        for s in spec.signals:
            if s not in have:
                problems.append(f"{name}: signal {s} missing")
        if "VFrameFormat" not in (msg.dbc.attributes if msg.dbc else {}):
            problems.append(f"{name}: no VFrameFormat attribute")
        if spec.classic and (msg.is_fd or msg.length > 8):
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


def load_database(path: str | Path | None, contract: Mapping[str, MessageSpec]) -> Database:
    """Load the DBC strictly and check ``contract``; raises :class:`ContractError` with every problem.

    Callers use ``records.load_database``, which passes the contract the record classes define.
    """
    p = Path(path) if path else default_dbc_path()
    try:
        db = cantools.database.load_file(str(p), strict=True)
    except FileNotFoundError:
        raise ContractError(f"DBC not found: {p}") from None
    except Exception as exc:   # cantools raises several parse error types
        raise ContractError(f"cannot load DBC {p}: {exc}") from None
    problems = check_contract(db, contract)
    if problems:
        raise ContractError(f"{p} violates the contract: " + "; ".join(problems))
    return db
