"""Rate-limited logging: the first occurrence of a kind of problem is logged, repeats are summarised."""

from __future__ import annotations

import logging
import time


class RateLimitedLog:
    """Logs a message per ``key`` at most once per ``interval_s``, with the number suppressed meanwhile."""

    def __init__(self, logger: logging.Logger, interval_s: float = 10.0) -> None:
        self.logger = logger
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def log(self, level: int, key: str, msg: str, *args: object, exc_info: bool = False) -> None:
        """Log now if ``key`` was quiet for ``interval_s``, else count it."""
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < self.interval_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        n = self._suppressed.pop(key, 0)
        self._last[key] = now
        suffix = f" ({n} more since the last report)" if n else ""
        self.logger.log(level, msg + suffix, *args, exc_info=exc_info)
