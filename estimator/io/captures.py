"""Bus captures: any log python-can reads or writes (candump -L, ASC, BLF, TRC, CSV, MDF4), as
messages, and the conversion between python-can's messages and the codec's frames.

As :mod:`can.io` is python-can's, this is where a capture file becomes frames: the pipeline
(:mod:`estimator.pipeline.replay`) turns them into injections and estimates. A line of a candump log
that cannot be read is skipped and reported to the caller (``on_bad``) with its line number.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Iterator
from pathlib import Path

import can

from estimator.codec.frame import Frame

CANDUMP_SUFFIXES = (".log",)
CAPTURE_SUFFIXES = (".log", ".asc", ".blf", ".trc", ".csv", ".mf4")   # python-can's readers (.mf4: asammdf)
# python-can's TRC writer cannot write CAN FD frames, and the sample frames are CAN FD
OUTPUT_SUFFIXES = tuple(s for s in CAPTURE_SUFFIXES if s != ".trc")


def check_capture_suffix(path: Path, what: str) -> None:
    """Refuse a capture file name whose suffix python-can cannot read (``capture``) or write (``output``)."""
    allowed = CAPTURE_SUFFIXES if what == "capture" else OUTPUT_SUFFIXES
    if path.suffix.lower() not in allowed:
        why = " (python-can's TRC writer has no CAN FD)" if path.suffix.lower() == ".trc" else ""
        raise ValueError(f"{what} {path}: unknown suffix {path.suffix!r}{why}; one of {', '.join(allowed)}")


def open_writer(path: Path, channel: str = "vcan0") -> can.io.generic.MessageWriter:
    """A python-can writer chosen by suffix (candump -L for .log)."""
    check_capture_suffix(path, "output")
    if path.suffix.lower() == ".log":
        return can.CanutilsLogWriter(str(path), channel=channel)
    try:
        return can.Logger(str(path))
    except ImportError as exc:
        raise ValueError(f"output {path}: {exc} (MDF4 needs asammdf: pip install '.[mdf]')") from None


def read_capture(capture: Path, on_bad: Callable[[int, str], None] | None = None) -> Iterator[can.Message]:
    """Messages of a capture. candump logs are read line by line (a bad line is skipped and passed to
    ``on_bad`` as (line number, problem)); other formats through :class:`can.LogReader` (an unreadable
    file raises ValueError/OSError)."""
    check_capture_suffix(capture, "capture")
    if capture.suffix.lower() not in CANDUMP_SUFFIXES:
        try:
            reader = can.LogReader(str(capture))
        except ImportError as exc:
            raise ValueError(f"capture {capture}: {exc} (MDF4 needs asammdf: pip install '.[mdf]')") from None
        with reader:
            for msg in reader:
                if len(msg.data) > 8 and not msg.is_fd:   # python-can's CSV has no FD flag: > 8 bytes is FD
                    msg.is_fd = True
                yield msg
        return
    with open(capture, "rb") as f:
        for no, raw in enumerate(f, start=1):
            try:
                line = raw.decode("ascii")
                if not line.strip():
                    continue
                msgs = list(can.CanutilsLogReader(io.StringIO(line)))
            except (ValueError, IndexError, UnicodeDecodeError) as exc:
                if on_bad is not None:
                    on_bad(no, f"{type(exc).__name__}: {exc}"[:120])
                continue
            yield from msgs


def to_frame(msg: can.Message) -> Frame:
    """python-can message -> codec frame (timestamp: the bus's receive time in s)."""
    return Frame(msg.arbitration_id, bytes(msg.data), bool(msg.is_fd), float(msg.timestamp), bool(msg.is_extended_id))


def to_message(frame: Frame, timestamp: float = 0.0) -> can.Message:
    """Codec frame -> python-can message (CAN FD frames with bit-rate switch)."""
    return can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_fd=frame.is_fd,
                       bitrate_switch=frame.is_fd, is_extended_id=frame.is_extended_id, timestamp=timestamp)
