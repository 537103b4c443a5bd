"""[security]: MAVLink 2 signing keys, signature checks, the command gate, log rate limiting.

Design (the README repeats it for users):

- Key file (`security.key_file`): exactly 32 raw bytes, or 64 hexadecimal characters (whitespace
  around them ignored), or else a passphrase (one line of text, surrounding whitespace stripped) hashed
  with SHA-256, which is what MAVProxy's `signing setup PASSPHRASE` does, so the same passphrase
  works on both ends. A passphrase that happens to be 64 hex digits is read as hex. The file must be
  readable and must not be readable or writable by group or others (mode 600 or 400): otherwise the
  program refuses to start (ConfigError, exit 2).
- Signature check (`SignatureVerifier`, installed on every GCS link, shared by all of them): the
  HMAC (SHA-256 of key + frame, first 6 bytes) is checked FIRST, and only a frame whose signature
  is right may advance its stream's timestamp. pymavlink's own check_signature records the
  timestamp before it compares the signature, so one forged frame with a far-future timestamp would
  lock a real ground station out for good; and one table for all GCS links means a frame signed for
  one link cannot be replayed on another. A timestamp not newer than the last one of its stream
  (link id, system id, component id) is a replay; a stream seen for the first time must not be more
  than a minute older than our own timestamp (MAVLink's rule), which starts at the wall clock.
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
- Logs: `LogRateLimit` is a logging filter for the handlers, so a flood of bad frames cannot become a
  flood of log lines (per logger, level and message template; suppressed counts are kept and the next
  line that passes says how many were dropped).
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import stat
import struct
from collections.abc import Callable

from rover_bridge.errors import ConfigError
from rover_bridge.identity import Identity
from rover_bridge.mav import MAVLinkMessage, mavlink
from rover_bridge.params import Profile, SecurityParams
from rover_bridge.ratelimit import RateLimiter
from rover_bridge.report import Reporter
from rover_bridge.wire import Incoming, Link, Reaction

KEY_BYTES = 32
# MAVLink signing timestamps count 10 us units since 2015-01-01 00:00 UTC.
SIGNING_EPOCH_S = 1420070400
NEW_STREAM_MAX_AGE = 60 * 100_000  # one minute, in 10 us units (MAVLink's rule, as pymavlink)

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


# ------------------------------------------------------------------------------------------ keys

def load_key(path: str) -> bytes:
    """The 32-byte signing secret in `path` (see the module doc); ConfigError if unusable or exposed."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise ConfigError([f"security.key_file {path!r}: cannot read ({exc.strerror or exc})"]) from exc
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError([f"security.key_file {path!r}: not a regular file"])
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError([f"security.key_file {path!r}: mode {stat.S_IMODE(st.st_mode):03o} lets group/others "
                           "read or change the signing key; chmod 600 it"])
    try:
        with open(path, "rb") as f:
            data = f.read(4096)
    except OSError as exc:
        raise ConfigError([f"security.key_file {path!r}: cannot read ({exc.strerror or exc})"]) from exc
    return key_from_bytes(data, path)


def key_from_bytes(data: bytes, origin: str = "key") -> bytes:
    if len(data) == KEY_BYTES:
        return bytes(data)
    text = data.strip()
    if len(text) == 2 * KEY_BYTES:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    if not text or b"\n" in text or b"\0" in text:
        raise ConfigError([f"security.key_file {origin!r}: expected 32 raw bytes, 64 hex characters or a "
                           "one-line passphrase"])
    return passphrase_key(text.decode("utf-8", "strict"))


def passphrase_key(passphrase: str) -> bytes:
    """MAVProxy's `signing setup PASSPHRASE`: the key is SHA-256 of the passphrase."""
    return hashlib.sha256(passphrase.encode("utf-8")).digest()


def signing_timestamp(wall_s: float) -> int:
    """MAVLink signing timestamp (10 us units since 2015-01-01) for a wall-clock time."""
    return int(max(0.0, wall_s - SIGNING_EPOCH_S) * 100_000)


# ------------------------------------------------------------------------------------ signatures

class SignatureVerifier:
    """Checks MAVLink 2 signatures; drop-in for pymavlink's `MAVLink.check_signature` (see module doc).

    One instance is shared by every GCS link. `timestamp` is the newest signing timestamp seen (in
    10 us units); new streams must not be older than it by more than a minute.
    """

    def __init__(self, key: bytes, initial_timestamp: int) -> None:
        if len(key) != KEY_BYTES:
            raise ValueError("signing key must be 32 bytes")
        self._key = key
        self.timestamp = initial_timestamp
        self.streams: dict[tuple[int, int, int], int] = {}
        self.counters: dict[str, int] = {"good": 0, "bad_signature": 0, "replayed": 0, "stale_new_stream": 0,
                                         "malformed": 0}

    def check(self, msgbuf: bytes | bytearray, src_system: int, src_component: int) -> bool:
        if len(msgbuf) < 10 + 2 + 13:
            self.counters["malformed"] += 1
            return False
        link_id = msgbuf[-13]
        tlow, thigh = struct.unpack("<IH", bytes(msgbuf[-12:-6]))
        timestamp = tlow + (thigh << 32)
        expected = hashlib.sha256(self._key + bytes(msgbuf[:-6])).digest()[:6]
        if not hmac.compare_digest(expected, bytes(msgbuf[-6:])):
            self.counters["bad_signature"] += 1
            return False
        key = (link_id, src_system, src_component)
        last = self.streams.get(key)
        if last is not None and timestamp <= last:
            self.counters["replayed"] += 1
            return False
        if last is None and timestamp + NEW_STREAM_MAX_AGE < self.timestamp:
            self.counters["stale_new_stream"] += 1
            return False
        # Only a verified frame moves time forward (streams are created by key holders only, so the
        # table is bounded by the honest senders).
        self.streams[key] = timestamp
        self.timestamp = max(self.timestamp, timestamp)
        self.counters["good"] += 1
        return True

    def install(self, mav: mavlink.MAVLink) -> None:
        """Make `mav` (a pymavlink parser) verify with this verifier instead of its own check."""
        checker: Callable[[bytearray, int, int], bool] = self.check
        mav.check_signature = checker  # type: ignore[method-assign]


def carries_signature(msg: MAVLinkMessage) -> bool:
    """True when the frame had MAVLink 2's signed flag (whether or not the signature was right)."""
    header = msg.get_header()
    return bool(int(getattr(header, "incompat_flags", 0)) & mavlink.MAVLINK_IFLAG_SIGNED)


# ------------------------------------------------------------------------------------------ gate

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

    @property
    def active(self) -> bool:
        return self.require_signed or self.have_key or bool(self.allowed)

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


# ------------------------------------------------------------------------------------------ logs

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
