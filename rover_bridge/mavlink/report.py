"""STATUSTEXT and log reports from the core, rate-limited per key (pure: time is an argument)."""

from __future__ import annotations

import logging

from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.ratelimit import RateLimiter
from rover_bridge.mavlink.wire import Link, Outgoing

log = logging.getLogger("rover_bridge")

_LOG_LEVEL = {
    mavlink.MAV_SEVERITY_EMERGENCY: logging.CRITICAL, mavlink.MAV_SEVERITY_ALERT: logging.CRITICAL,
    mavlink.MAV_SEVERITY_CRITICAL: logging.CRITICAL, mavlink.MAV_SEVERITY_ERROR: logging.ERROR,
    mavlink.MAV_SEVERITY_WARNING: logging.WARNING, mavlink.MAV_SEVERITY_NOTICE: logging.INFO,
    mavlink.MAV_SEVERITY_INFO: logging.INFO, mavlink.MAV_SEVERITY_DEBUG: logging.DEBUG,
}


class Reporter:
    """Turns events into STATUSTEXT to the ground stations plus a log line, at most ~1/s per key."""

    def __init__(self, identity: Identity, limiter: RateLimiter | None = None) -> None:
        self.identity = identity
        self.limiter = limiter if limiter is not None else RateLimiter(rate_per_s=1.0, burst=3.0)
        self.sent: list[tuple[float, int, str]] = []  # recent history for tests and `status`

    def statustext(self, severity: int, text: str, now_s: float, key: str | None = None) -> list[Outgoing]:
        """Report `text`; returns the STATUSTEXT to send, or [] when rate-limited (counted)."""
        if not self.limiter.allow(key or text, now_s):
            return []
        log.log(_LOG_LEVEL.get(severity, logging.INFO), "%s", text)
        self.sent.append((now_s, severity, text))
        del self.sent[:-100]
        # STATUSTEXT.text is 50 bytes on the wire; keep it readable rather than cut mid-word by the packer.
        msg = mavlink.MAVLink_statustext_message(severity=severity, text=text[:50].encode("ascii", "replace"))
        return [Outgoing(Link.GCS, msg, self.identity.own_system_id, self.identity.component_id)]
