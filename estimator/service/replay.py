"""Offline replay: any python-can log (candump -L included) through the daemon's own pipeline.

Frames are fed with their recorded timestamps as the clock (:class:`~estimator.codec.bus_clock.BusClock`,
as live), as fast as possible; at the end of the capture the silent-bus guard runs out, as it would
live. The outputs are the frames the daemon would have sent (as a candump -L log) and/or one JSON
line per injection. A line of a candump log that cannot be read is skipped, counted and reported
with its line number; the rest of the capture is replayed. The estimator's own output frames in a
capture are skipped (live, the daemon does not receive them).
"""

from __future__ import annotations

import csv
import io
import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import can

from estimator.codec.ingest import Counters
from estimator.pipeline import build_pipeline
from estimator.service.bus import to_frame, to_message
from estimator.service.config import DaemonConfig
from estimator.service.processor import ROW_FIELDS, Published

log = logging.getLogger(__name__)
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


@dataclass
class ReplayResult:
    """Counters, the number of injections published, and the capture lines that could not be read."""

    counters: Counters
    published: int
    frames_in: int
    bad_lines: list[tuple[int, str]] = field(default_factory=list)   # (line number, problem), at most 100 kept
    bad_line_count: int = 0


def read_capture(capture: Path, bad: ReplayResult | None = None) -> Iterator[can.Message]:
    """Messages of a capture. candump logs are read line by line (a bad line is skipped and recorded);
    other formats through :class:`can.LogReader` (an unreadable file raises ValueError/OSError)."""
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
                if bad is None:
                    continue
                bad.bad_line_count += 1
                if len(bad.bad_lines) < 100:
                    bad.bad_lines.append((no, f"{type(exc).__name__}: {exc}"[:120]))
                continue
            yield from msgs


def iter_capture(capture: Path, cfg: DaemonConfig, result: ReplayResult | None = None,
                 pipeline: tuple | None = None) -> Iterator[tuple[Published, float]]:
    """The daemon's pipeline over a capture: (published injection, its bus time in s), in order.

    ``result`` (optional) collects counters, frame counts and bad lines; ``pipeline`` is a
    :func:`build_pipeline` tuple to continue from (state carried across captures of one injector).
    Raises OSError/ValueError for unreadable files.
    """
    codec, ingest, processor, clock = pipeline or build_pipeline(cfg)
    if result is None:
        result = ReplayResult(ingest.counters, 0, 0)
    # live, the daemon does not receive its own frames: a capture's copies must not move the clock
    own = codec.output_ids()
    for msg in read_capture(capture, result):
        if msg.is_error_frame or msg.is_remote_frame or (msg.arbitration_id in own and not msg.is_extended_id):
            continue
        result.frames_in += 1
        fr = to_frame(msg)
        now = clock.on_frame(fr.timestamp)
        for pub in processor.handle(ingest.feed(fr, now)):
            result.published += 1
            yield pub, fr.timestamp
    processor.handle(ingest.poll(clock.end()))   # what the silent-bus guard does live


def replay(capture: Path, cfg: DaemonConfig, out_log: Path | None = None, out_json: TextIO | None = None,
           channel: str = "vcan0", out_csv: TextIO | None = None) -> ReplayResult:
    """Run the pipeline over a capture (any python-can format by suffix). ``out_log``: the output frames
    (format by suffix); ``out_json``: one JSON line per injection; ``out_csv``: one CSV row per injection.
    Raises OSError/ValueError for unreadable files."""
    pipeline = build_pipeline(cfg)
    result = ReplayResult(pipeline[1].counters, 0, 0)
    writer = open_writer(out_log, channel) if out_log else None
    csv_rows = None
    if out_csv is not None:
        csv_rows = csv.DictWriter(out_csv, fieldnames=ROW_FIELDS)
        csv_rows.writeheader()
    try:
        for pub, t in iter_capture(capture, cfg, result, pipeline):
            if writer is not None:
                for out in pub.frames:
                    writer.on_message_received(to_message(out, timestamp=t))
            if out_json is not None:
                out_json.write(json.dumps(pub.to_dict()) + "\n")
            if csv_rows is not None:
                csv_rows.writerow(pub.to_row(t))
    finally:
        if writer is not None:
            writer.stop()
    return result
