"""MAVLink 2 signing for the ground-station links: keys and the signature check (I/O edge, pure functions).

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

What a signed or unsigned frame may do is rover_bridge.mavlink.gate's decision.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import stat
import struct
from collections.abc import Callable

from rover_bridge.errors import ConfigError
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink

KEY_BYTES = 32
# MAVLink signing timestamps count 10 us units since 2015-01-01 00:00 UTC.
SIGNING_EPOCH_S = 1420070400
NEW_STREAM_MAX_AGE = 60 * 100_000  # one minute, in 10 us units (MAVLink's rule, as pymavlink)



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
    try:
        passphrase = text.decode("utf-8", "strict")
    except UnicodeDecodeError:
        passphrase = ""  # binary, and not 32 bytes: no kind of key
    if not passphrase or "\n" in passphrase or "\0" in passphrase:
        raise ConfigError([f"security.key_file {origin!r}: expected 32 raw bytes, 64 hex characters or a "
                           "one-line passphrase"])
    return passphrase_key(passphrase)


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
