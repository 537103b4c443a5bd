"""Log rate limiting for the process's handlers: a flood of bad input must not become a flood of log lines.

`LogRateLimit` limits per logger, level and message template; suppressed counts are kept and the
next line that passes says how many were dropped.
"""

from __future__ import annotations

import logging

from rover_bridge.mavlink.ratelimit import RateLimiter


class LogRateLimit(logging.Filter):
    """Rate-limit log records per (logger, level, message template); count what is suppressed.

    Attach to handlers (a filter on a logger does not apply to its children's records). Time is the
    record's own `created`, so the filter stays pure given the records.
    """

    def __init__(self, rate_per_s: float = 2.0, burst: float = 10.0, max_keys: int = 1024) -> None:
        super().__init__()
        self.limiter = RateLimiter(rate_per_s=rate_per_s, burst=burst)
        self.max_keys = max_keys
        self._pending: dict[str, int] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        key = f"{record.name}|{record.levelno}|{record.msg}"
        if key not in self.limiter._last_s and len(self.limiter._last_s) >= self.max_keys:
            key = "overflow"  # never let distinct templates grow the table without bound
        if not self.limiter.allow(key, record.created):
            self._pending[key] = self._pending.get(key, 0) + 1
            return False
        dropped = self._pending.pop(key, 0)
        if dropped:
            record.msg = f"{record.msg} [{dropped} similar suppressed]"
        return True

    @property
    def suppressed(self) -> dict[str, int]:
        return dict(self.limiter.suppressed)


def install_log_rate_limit(logger: logging.Logger | None = None) -> LogRateLimit:
    """Attach one LogRateLimit to every handler of `logger` (the root logger by default)."""
    target = logger if logger is not None else logging.getLogger()
    flt = LogRateLimit()
    for handler in target.handlers:
        handler.addFilter(flt)
    return flt
