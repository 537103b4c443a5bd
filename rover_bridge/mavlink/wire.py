"""Value types that cross the boundary between the pure core and the I/O shell.

The core returns `Outgoing` values; the shell packs each with the given source ids and
writes it to the links named by `dest`. Frames the core does not consume are forwarded by
the shell byte for byte (source ids and signatures intact), so they never appear here.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from rover_bridge.mavlink.dialect import MAVLinkMessage


class Link(enum.Enum):
    """Which side of the bridge a message came from or goes to."""

    AUTOPILOT = "autopilot"
    GCS = "gcs"


@dataclass(frozen=True, slots=True)
class Outgoing:
    """One message the core wants sent.

    `src_system` / `src_component` are the MAVLink source ids to pack it with: the bridge's
    own heartbeat uses the vehicle's system id, but RC_CHANNELS_OVERRIDE must come from the
    GCS system id (ArduPilot's MAV_GCS_SYSID) or ArduPilot silently ignores it.
    """

    dest: Link
    msg: MAVLinkMessage
    src_system: int
    src_component: int


@dataclass(frozen=True, slots=True)
class Incoming:
    """One decoded message as the core sees it: where it came from and whether it was signed.

    `signed_ok` is True only when the frame carried a MAVLink 2 signature that the shell
    verified against the link's key (see [security]); False for unsigned frames.
    """

    link: Link
    msg: MAVLinkMessage
    signed_ok: bool = False


@dataclass(frozen=True, slots=True)
class Reaction:
    """What a core did with one incoming message.

    `consumed` frames are not forwarded to the other side (e.g. a velocity request meant for
    the bridge); everything else is forwarded unchanged by the shell.
    """

    consumed: bool = False
    out: tuple[Outgoing, ...] = ()


NOTHING = Reaction()


# ---------------------------------------------------------------- wire types of values from outside
# Every field the bridge packs from a value that came from outside (an autopilot stamp, an estimate
# fed by its telemetry) goes through one of these first: pymavlink's struct packing raises on an
# out-of-range integer or a float beyond float32, and that would escape the loop.

FLOAT32_MAX = 3.4028234663852886e38


def f32(value: float) -> float:
    """A float that packs as float32: finite values clamped to +-FLT_MAX (NaN and inf pack as they are)."""
    v = float(value)
    if math.isfinite(v) and abs(v) > FLOAT32_MAX:
        return math.copysign(FLOAT32_MAX, v)
    return v


def uint(value: float, bits: int) -> int:
    """A whole number clamped to an unsigned field of `bits` bits (NaN -> 0)."""
    v = float(value)
    if not v > 0.0:
        return 0
    top = (1 << bits) - 1
    return top if v >= top else int(v)
