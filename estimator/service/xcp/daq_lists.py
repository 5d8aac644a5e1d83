"""What the XCP slave's DAQ offers, described once for the slave and the A2L: its event channels and
its predefined (static) DAQ lists.

* **Events.** 0 ``injection``: after every estimate the daemon publishes; 1 ``10 Hz``: with the
  heartbeat; 2 + k ``injection k``: after each estimate of injector k (0-7). An injector's event fires
  when all of that estimate's frames are in the measurement image, so a DAQ list on it samples one
  injection's values, never two injections' halves.
* **Predefined lists** (``MIN_DAQ`` of them, numbered first): list k (0-7) holds injector k's output
  messages (every per-injector message of the DBC but the drive-correction table) on event
  ``injection k``; the last one holds the daemon's status, its health and the slave's counters on the
  ``10 Hz`` event. Each is one ODT of whole frames in entries of at most 8 bytes: a calibration tool
  starts it without configuring anything (its event is fixed, its mode and prescaler are the
  master's). Lists a master allocates itself (dynamic DAQ) are numbered after them.
"""

from __future__ import annotations

from dataclasses import dataclass

from cantools.database import Database

from estimator.service.xcp.memory import (
    INJECTOR_SLOTS,
    SLAVE_COUNTERS,
    STATS_BASE,
    output_messages,
    slot_layout,
)

EVENT_INJECTION, EVENT_10HZ, FIRST_INJECTOR_EVENT = 0, 1, 2   # injector k's event: FIRST_INJECTOR_EVENT + k
MAX_ENTRY_BYTES = 8                       # the largest ODT entry (A2L: MAX_ODT_ENTRY_SIZE_DAQ)
MAX_DYNAMIC_LISTS, MAX_ODTS, MAX_ENTRIES = 16, 64, 64   # what a master may allocate (bounded memory)
UNPUBLISHED = ("DriveCorrectionTable",)   # per-injector messages whose rows a DAQ list of one frame cannot hold


@dataclass(frozen=True)
class Event:
    """One event channel: ``name`` (at most 100 characters), ``short`` (at most 8), ``cycle`` in
    ``unit`` (XCP time unit code: 6 is 1 ms; a cycle of 0 is a sporadic event)."""

    name: str
    short: str
    cycle: int
    unit: int


EVENTS: tuple[Event, ...] = (Event("injection", "inj", 0, 0), Event("10 Hz", "10Hz", 100, 6),
                             *(Event(f"injection {k}", f"inj{k}", 0, 0) for k in range(INJECTOR_SLOTS)))


def injector_event(injector: int) -> int | None:
    """The event channel of injector ``injector``'s estimates (None beyond the DBC's eight)."""
    return FIRST_INJECTOR_EVENT + injector if 0 <= injector < INJECTOR_SLOTS else None


@dataclass(frozen=True)
class PredefinedList:
    """A predefined DAQ list: ``name``, its fixed ``event`` and its one ODT's ``entries`` (address, bytes)."""

    name: str
    event: int
    entries: tuple[tuple[int, int], ...]


def _entries(address: int, size: int) -> list[tuple[int, int]]:
    """``size`` bytes from ``address`` as ODT entries of at most :data:`MAX_ENTRY_BYTES`."""
    return [(address + k, min(MAX_ENTRY_BYTES, size - k)) for k in range(0, size, MAX_ENTRY_BYTES)]


def predefined_lists(db: Database) -> list[PredefinedList]:
    """The predefined DAQ lists of the DBC ``db``: one per injector slot, then the daemon's."""
    layout = slot_layout(db)
    messages = output_messages(db)
    out = []
    for k in range(INJECTOR_SLOTS):
        entries = [e for m in messages if m.is_multiplexed() and m.name not in UNPUBLISHED
                   for e in _entries(layout[(m.frame_id, k)], m.length)]
        out.append(PredefinedList(f"injector_{k}", FIRST_INJECTOR_EVENT + k, tuple(entries)))
    daemon = [e for m in messages if not m.is_multiplexed() for e in _entries(layout[(m.frame_id, None)], m.length)]
    daemon += _entries(STATS_BASE, 4 * len(SLAVE_COUNTERS))
    out.append(PredefinedList("daemon", EVENT_10HZ, tuple(daemon)))
    return out


__all__ = ["EVENTS", "EVENT_10HZ", "EVENT_INJECTION", "MAX_DYNAMIC_LISTS", "MAX_ENTRIES", "MAX_ENTRY_BYTES", "MAX_ODTS", "Event", "PredefinedList",
           "injector_event", "predefined_lists"]
