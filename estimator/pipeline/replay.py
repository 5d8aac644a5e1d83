"""Offline replay: any python-can log (candump -L included) through the daemon's own pipeline.

The capture's frames come from :mod:`estimator.io.captures`.

Frames are fed with their recorded timestamps as the clock (:class:`~estimator.codec.bus_clock.BusClock`,
as live), as fast as possible; at the end of the capture the silent-bus guard runs out, as it would
live. The outputs are the frames the daemon would have sent (as a candump -L log) and/or one JSON
line per injection. A line of a candump log that cannot be read is skipped, counted and reported
with its line number; the rest of the capture is replayed. The estimator's own output frames in a
capture are skipped (live, the daemon does not receive them).
"""

from __future__ import annotations

import csv
import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from estimator.codec.ingest import Counters
from estimator.io.captures import open_writer, read_capture, to_frame, to_message
from estimator.pipeline.build import Pipeline, build_pipeline
from estimator.pipeline.config import EstimatorConfig
from estimator.pipeline.processor import ROW_FIELDS, Published

log = logging.getLogger(__name__)
BAD_LINES_KEPT = 100


@dataclass
class ReplayResult:
    """Counters, the number of injections published, and the capture lines that could not be read."""

    counters: Counters
    published: int
    frames_in: int
    bad_lines: list[tuple[int, str]] = field(default_factory=list)   # (line number, problem), at most 100 kept
    bad_line_count: int = 0

    def note_bad(self, line: int, problem: str) -> None:
        """Count a capture line that could not be read (the first :data:`BAD_LINES_KEPT` kept)."""
        self.bad_line_count += 1
        if len(self.bad_lines) < BAD_LINES_KEPT:
            self.bad_lines.append((line, problem))


def iter_capture(capture: Path, cfg: EstimatorConfig, result: ReplayResult | None = None,
                 pipeline: Pipeline | None = None) -> Iterator[tuple[Published, float]]:
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
    for msg in read_capture(capture, result.note_bad):
        if msg.is_error_frame or msg.is_remote_frame or (msg.arbitration_id in own and not msg.is_extended_id):
            continue
        result.frames_in += 1
        fr = to_frame(msg)
        now = clock.on_frame(fr.timestamp)
        for pub in processor.handle(ingest.feed(fr, now)):
            result.published += 1
            yield pub, fr.timestamp
    processor.handle(ingest.poll(clock.end()))   # what the silent-bus guard does live


def replay(capture: Path, cfg: EstimatorConfig, out_log: Path | None = None, out_json: TextIO | None = None,
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
