"""Offline replay: any python-can log (candump -L included) through the daemon's own pipeline.

Frames are fed with their recorded timestamps as the clock, as fast as possible; the outputs are
the frames the daemon would have sent (as a candump -L log) and/or one JSON line per injection.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import can

from estimator.codec.database import load_database
from estimator.codec.ingest import Counters, Ingest
from estimator.codec.records import Codec
from estimator.service.bus import to_frame, to_message
from estimator.service.config import DaemonConfig
from estimator.service.daemon import build_tracker
from estimator.service.processor import Processor

log = logging.getLogger(__name__)


@dataclass
class ReplayResult:
    """Counters and the number of injections published."""

    counters: Counters
    published: int
    frames_in: int


def replay(capture: Path, cfg: DaemonConfig, out_log: Path | None = None, out_json: TextIO | None = None,
           channel: str = "vcan0") -> ReplayResult:
    """Run the pipeline over a capture. Raises OSError/ValueError for unreadable files."""
    codec = Codec(load_database(cfg.dbc))
    ingest = Ingest(codec, cfg.assembly_timeout_ms * 1e-3, cfg.max_injectors)
    processor = Processor(codec, build_tracker(cfg), ingest.counters)
    writer = can.CanutilsLogWriter(str(out_log), channel=channel) if out_log else None
    published = frames = 0
    try:
        for msg in can.LogReader(str(capture)):
            if msg.is_error_frame or msg.is_remote_frame:
                continue
            frames += 1
            fr = to_frame(msg)
            for pub in processor.handle(ingest.feed(fr, fr.timestamp)):
                published += 1
                if writer is not None:
                    for out in pub.frames:
                        writer.on_message_received(to_message(out, timestamp=fr.timestamp))
                if out_json is not None:
                    out_json.write(json.dumps(pub.to_dict()) + "\n")
    finally:
        if writer is not None:
            writer.stop()
    return ReplayResult(ingest.counters, published, frames)
