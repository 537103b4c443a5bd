"""[security]'s command gate (pure): may this incoming frame be acted on or forwarded?

Design (docs/security.md repeats it for users):

- Gate (`CommandGate`, in front of both cores): on the GCS side every message type except the
  read-only ones in UNSIGNED_OK is a command: velocity requests (SET_POSITION_TARGET_*,
  MANUAL_CONTROL), COMMAND_LONG / COMMAND_INT (arming, mode, the bridge's pose reset...), SET_MODE,
  RC_CHANNELS_OVERRIDE, PARAM_SET, MISSION_* writes, FILE_TRANSFER_PROTOCOL, SERIAL_CONTROL,
  SETUP_SIGNING, and any type unknown to us. Default-deny: a new message type is a command until
  someone decides it is harmless. With require_signed_commands, an unsigned command is rejected
  (`unsigned`); with a key, a frame whose signature fails is always rejected (`bad_signature`: a
  wrong key, a forgery or a replay), whatever its type. With allowed_sources, a command from any
  other source is rejected (`source_not_allowed`). Rejected frames are consumed: not acted on and
  not forwarded to the autopilot; each is counted (`rejected.<reason>`), reported by STATUSTEXT once
  per (reason, source) for the first MAX_REPORTED_SOURCES sources, and rate-limited by the Reporter.
  On the autopilot side only commands addressed to the bridge itself (COMMAND_LONG / COMMAND_INT to
  our component, e.g. a pose reset routed by the autopilot) are gated: that link is not signed, so
  with require_signed_commands they are rejected as unsigned.

Signatures themselves are checked by rover_bridge.mavlink.signing when a frame is read.
"""

from __future__ import annotations

from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.signing import carries_signature
from rover_bridge.mavlink.wire import Incoming, Link, Reaction
from rover_bridge.params import Profile, SecurityParams

# Reasons (counters "rejected.<reason>").
UNSIGNED = "unsigned"
BAD_SIGNATURE = "bad_signature"
SOURCE_NOT_ALLOWED = "source_not_allowed"

# GCS-side types that may come unsigned and from any source: heartbeats, link timing/quality and
# read-only requests. Everything else from a GCS is a command (default-deny). REQUEST_DATA_STREAM is
# deliberately NOT here: it changes the autopilot's stream rates, and an unauthenticated sender could
# turn off the WHEEL_DISTANCE stream the estimator depends on.
UNSIGNED_OK = frozenset({
    "HEARTBEAT", "TIMESYNC", "SYSTEM_TIME", "PING", "RADIO", "RADIO_STATUS",
    "PARAM_REQUEST_READ", "PARAM_REQUEST_LIST", "PARAM_EXT_REQUEST_READ", "PARAM_EXT_REQUEST_LIST",
    "MISSION_REQUEST_LIST", "MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK",
    "AUTOPILOT_VERSION_REQUEST", "LOG_REQUEST_LIST",
})
# Autopilot-side commands the bridge acts on when addressed to it (the estimator's pose reset).
BRIDGE_COMMANDS = frozenset({"COMMAND_LONG", "COMMAND_INT"})
# Report a rejection once per (reason, source) for at most this many sources; beyond it only count,
# so spoofed source ids cannot grow the table without bound.
MAX_REPORTED_SOURCES = 256



def parse_sources(entries: tuple[str, ...]) -> frozenset[tuple[int, int | None]]:
    """'sysid:compid' / 'sysid:*' (validated by params) -> (sysid, compid or None for any)."""
    out: set[tuple[int, int | None]] = set()
    for entry in entries:
        sys_text, _, comp_text = entry.partition(":")
        out.add((int(sys_text), None if comp_text == "*" else int(comp_text)))
    return frozenset(out)


class SecurityPolicy:
    """The pure decision: may this incoming message be acted on / forwarded? (see the module doc)."""

    def __init__(self, params: SecurityParams) -> None:
        self.require_signed = params.require_signed_commands
        self.have_key = bool(params.key_file)
        self.allowed = parse_sources(params.allowed_sources)
        self.active = self.require_signed or self.have_key or bool(self.allowed)  # fixed for the profile

    def is_command(self, inc: Incoming, identity: Identity) -> bool:
        kind = inc.msg.get_type()
        if inc.link is Link.GCS:
            return kind not in UNSIGNED_OK
        if kind not in BRIDGE_COMMANDS:
            return False
        try:
            return int(inc.msg.target_component) == identity.component_id
        except (AttributeError, TypeError, ValueError):
            return False

    def source_allowed(self, src_system: int, src_component: int) -> bool:
        return not self.allowed or (src_system, None) in self.allowed or (src_system, src_component) in self.allowed

    def reason(self, inc: Incoming, identity: Identity) -> str | None:
        """Why `inc` must be rejected, or None to let it through."""
        if not self.active:
            return None
        msg = inc.msg
        # A signature that fails is never "unsigned": it is a wrong key, a forgery or a replay.
        if self.have_key and inc.link is Link.GCS and carries_signature(msg) and not inc.signed_ok:
            return BAD_SIGNATURE
        if not self.is_command(inc, identity):
            return None
        if self.require_signed and not (inc.signed_ok and inc.link is Link.GCS and carries_signature(msg)):
            return UNSIGNED
        if not self.source_allowed(msg.get_srcSystem(), msg.get_srcComponent()):
            return SOURCE_NOT_ALLOWED
        return None


class CommandGate:
    """The policy in front of the cores: counts and reports what it rejects (pure: time is an argument)."""

    def __init__(self, profile: Profile, identity: Identity, reporter: Reporter) -> None:
        self.policy = SecurityPolicy(profile.security)
        self.identity = identity
        self.reporter = reporter
        self.counters: dict[str, int] = {}
        self._reported: set[tuple[str, int, int]] = set()

    def check(self, inc: Incoming, now_s: float) -> Reaction | None:
        """None to let `inc` through; otherwise the reaction for a rejected frame (consumed)."""
        reason = self.policy.reason(inc, self.identity)
        if reason is None:
            return None
        self.counters[f"rejected.{reason}"] = self.counters.get(f"rejected.{reason}", 0) + 1
        source = (inc.msg.get_srcSystem(), inc.msg.get_srcComponent())
        said = (reason, *source)
        if said in self._reported or len(self._reported) >= MAX_REPORTED_SOURCES:
            return Reaction(consumed=True)
        self._reported.add(said)
        # Source and reason first: STATUSTEXT carries 50 characters.
        text = f"RB: refused {source[0]}:{source[1]} {reason} {inc.msg.get_type()}"[:50]
        out = self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, text, now_s, key=f"security.{reason}")
        return Reaction(consumed=True, out=tuple(out))
