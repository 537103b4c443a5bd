"""Token-bucket rate limiting for STATUSTEXT and log lines (pure: time is an argument).

A flood of bad input must not become a flood of reports that drowns the radio link or
fills the disk; suppressed reports are counted so nothing is lost silently.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class RateLimiter:
    """Allow at most `burst` events at once and `rate_per_s` on average, per key."""

    rate_per_s: float = 1.0
    burst: float = 3.0
    _tokens: dict[str, float] = field(default_factory=dict)
    _last_s: dict[str, float] = field(default_factory=dict)
    suppressed: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.rate_per_s > 0 or not self.burst >= 1:
            raise ValueError("rate_per_s must be > 0 and burst >= 1")

    def allow(self, key: str, now_s: float) -> bool:
        """True if an event under `key` may be emitted at `now_s`; counts it if not."""
        last = self._last_s.get(key)
        tokens = self._tokens.get(key, self.burst)
        if last is not None and now_s > last:
            tokens = min(self.burst, tokens + (now_s - last) * self.rate_per_s)
        self._last_s[key] = now_s if last is None else max(last, now_s)
        if tokens >= 1.0:
            self._tokens[key] = tokens - 1.0
            return True
        self._tokens[key] = tokens
        self.suppressed[key] = self.suppressed.get(key, 0) + 1
        return False
