"""Log output that fits where it goes: journald priorities, JSON lines, or plain text (stdlib only).

Under systemd (``JOURNAL_STREAM`` names the stderr we write to) each line starts with ``<N>``, the
syslog priority, so ``journalctl -p warning`` filters and the journal adds its own timestamp.
``--log-format json`` writes one JSON object per line (time, level, logger, message, exception).
"""

from __future__ import annotations

import json
import logging
import os
import sys
from typing import TextIO

# logging level -> syslog priority (sd-daemon(3): <3> error, <4> warning, <6> info, <7> debug)
PRIORITY = {logging.CRITICAL: 2, logging.ERROR: 3, logging.WARNING: 4, logging.INFO: 6, logging.DEBUG: 7}
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def priority(levelno: int) -> int:
    """The syslog priority of a logging level (levels between the named ones round down in severity)."""
    for level in (logging.CRITICAL, logging.ERROR, logging.WARNING, logging.INFO):
        if levelno >= level:
            return PRIORITY[level]
    return PRIORITY[logging.DEBUG]


class JournalFormatter(logging.Formatter):
    """``<N>logger: message`` lines; a traceback continues on the following lines (same priority)."""

    def __init__(self) -> None:
        super().__init__("%(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines() or [""])


class JsonFormatter(logging.Formatter):
    """One JSON object per record: ``time`` (epoch s), ``level``, ``priority``, ``logger``, ``message``,
    ``exception`` when there is one."""

    def format(self, record: logging.LogRecord) -> str:
        doc = {"time": round(record.created, 6), "level": record.levelname, "priority": priority(record.levelno),
               "logger": record.name, "message": record.getMessage()}
        if record.exc_info:
            doc["exception"] = self.formatException(record.exc_info)
        return json.dumps(doc, ensure_ascii=False)


def under_journal(stream: TextIO) -> bool:
    """True when ``stream`` is the journal stream systemd connected (``JOURNAL_STREAM=dev:inode``)."""
    value = os.environ.get("JOURNAL_STREAM", "")
    try:
        dev, ino = (int(x) for x in value.split(":"))
        st = os.fstat(stream.fileno())
    except (ValueError, OSError, AttributeError):
        return False
    return (st.st_dev, st.st_ino) == (dev, ino)


def configure(level: int, fmt: str = "auto", stream: TextIO | None = None) -> None:
    """Root logging to ``stream`` (stderr): ``fmt`` auto (journal prefixes under systemd, else text),
    text, journal or json."""
    stream = stream or sys.stderr
    if fmt == "auto":
        fmt = "journal" if under_journal(stream) else "text"
    handler = logging.StreamHandler(stream)
    handler.setFormatter({"journal": JournalFormatter(), "json": JsonFormatter()}.get(fmt)
                         or logging.Formatter(TEXT_FORMAT))
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(level)
