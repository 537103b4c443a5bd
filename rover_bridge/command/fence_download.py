"""The autopilot's fence, downloaded with the mission protocol (pure: time is an argument).

MAVLink's mission protocol for mission type FENCE (ArduPilot: libraries/GCS_MAVLink/MissionItemProtocol.cpp,
MissionItemProtocol_Fence.cpp), as a ground station downloads it: MISSION_REQUEST_LIST, the MISSION_COUNT answer,
MISSION_REQUEST_INT for each item in turn, MISSION_ITEM_INT back, and a MISSION_ACK (ACCEPTED) at the end. A step
unanswered for RESEND_S is asked again; after ATTEMPTS unanswered asks (or an error ACK: the autopilot is busy
receiving someone's upload, DENIED) the download is abandoned and begun afresh RETRY_S later. The last complete
fence stays in use until a new one is complete: a half-read fence is never used.

Only answers addressed to the bridge (its system and component) and of mission type FENCE are taken; the caller
consumes them so that a ground station never sees another client's transfer.
"""

from __future__ import annotations

from dataclasses import dataclass

from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink

TYPE_FENCE = int(mavlink.MAV_MISSION_TYPE_FENCE)
RESEND_S = 1.0
ATTEMPTS = 5
RETRY_S = 5.0
MAX_ITEMS = 500  # more than any autopilot stores (ArduPilot: ~ 84 on a 4 kB board); a larger count is refused
ACCEPTED = int(mavlink.MAV_MISSION_ACCEPTED)


@dataclass(frozen=True, slots=True)
class FenceItem:
    """One stored fence item: a MAV_CMD_NAV_FENCE_* command, its param1 (vertex count or radius m), lat/lon 1e7."""

    command: int
    param1: float
    lat_e7: int
    lon_e7: int


class FenceDownload:
    """One download at a time of the autopilot's fence (module doc)."""

    def __init__(self) -> None:
        self.items: tuple[FenceItem, ...] | None = None  # the last complete download
        self.version = 0  # counts complete downloads
        self.done_s: float | None = None  # when the last one completed
        self._count: int | None = None  # items announced by MISSION_COUNT (None: asking for the list)
        self._got: list[FenceItem] = []
        self._running = False
        self._next_s: float | None = None
        self._asks = 0

    @property
    def running(self) -> bool:
        return self._running

    def start(self, now_s: float) -> None:
        """Begin (again) from the list: the fence may have changed. The last complete fence stays in use."""
        self._running, self._count, self._got, self._asks, self._next_s = True, None, [], 0, now_s

    def due(self, now_s: float) -> bool:
        return self._next_s is not None and now_s >= self._next_s

    def requests(self, now_s: float, target: tuple[int, int]) -> list[MAVLinkMessage]:
        """The step to ask for now (first time or again), or nothing when given up (begun again RETRY_S later)."""
        if self._asks >= ATTEMPTS:
            self._give_up(now_s)
            return []
        self._asks += 1
        self._next_s = now_s + RESEND_S
        return [self._ask(target)]

    def on_message(self, msg: MAVLinkMessage, now_s: float, target: tuple[int, int]) -> list[MAVLinkMessage]:
        """MISSION_COUNT, MISSION_ITEM_INT or MISSION_ACK of type FENCE addressed to us: the next step's message."""
        if not self._running:
            return []
        kind = msg.get_type()
        if kind == "MISSION_ACK":
            self._give_up(now_s)  # an error (DENIED while someone uploads, ...): begin again later
            return []
        if kind == "MISSION_COUNT" and self._count is None:
            count = int(msg.count)
            if count > MAX_ITEMS:
                self._give_up(now_s)
                return []
            self._count = count
        elif kind == "MISSION_ITEM_INT" and self._count is not None and int(msg.seq) == len(self._got):
            self._got.append(FenceItem(int(msg.command), float(msg.param1), int(msg.x), int(msg.y)))
        else:
            return []  # a repeat or out of turn: the resend asks again
        if self._count is not None and len(self._got) >= self._count:
            self.items, self.version, self.done_s = tuple(self._got), self.version + 1, now_s
            self._running, self._next_s = False, None
            return [mavlink.MAVLink_mission_ack_message(target[0], target[1], ACCEPTED, TYPE_FENCE)]
        self._asks, self._next_s = 1, now_s + RESEND_S
        return [self._ask(target)]

    def _ask(self, target: tuple[int, int]) -> MAVLinkMessage:
        if self._count is None:
            return mavlink.MAVLink_mission_request_list_message(target[0], target[1], TYPE_FENCE)
        return mavlink.MAVLink_mission_request_int_message(target[0], target[1], len(self._got), TYPE_FENCE)

    def _give_up(self, now_s: float) -> None:
        self._running, self._count, self._got, self._asks = True, None, [], 0
        self._next_s = now_s + RETRY_S
