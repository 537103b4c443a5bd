"""The mission protocol for mission type FENCE (1): upload, download and clear of the polygon fence.

Read in ArduPilot (4.7): libraries/GCS_MAVLink/MissionItemProtocol.cpp (the transfer, shared by every
mission type), MissionItemProtocol_Fence.cpp (items, complete, timeout). What is kept:

- Upload: MISSION_COUNT (type FENCE; more than MAX_ITEMS: MAV_MISSION_NO_SPACE), then each item asked
  for with MISSION_REQUEST (type FENCE), again after 1 s without an answer; 8 s without one cancels
  ("Fence upload timeout", MAV_MISSION_OPERATION_CANCELLED). Items: MISSION_ITEM_INT (or MISSION_ITEM,
  lat/lon scaled by 1e7) with a global frame (else MAV_MISSION_UNSUPPORTED_FRAME) and one of the five
  fence commands (else MAV_MISSION_UNSUPPORTED); out of sequence: MAV_MISSION_INVALID_SEQUENCE. After the
  last, the whole fence is written at once if it is valid (sitl/fence_store.py; else MAV_MISSION_ERROR
  and the old fence stays): MAV_MISSION_ACCEPTED, no STATUSTEXT (the waypoint protocol's "Flight plan
  received" is its own). MISSION_COUNT 0 clears. A second uploader meanwhile: DENIED.
- Download: MISSION_REQUEST_LIST -> MISSION_COUNT (type FENCE, no home item), MISSION_REQUEST_INT n ->
  MISSION_ITEM_INT n (frame GLOBAL, param1 = vertex count or radius, z 0); past the end:
  MAV_MISSION_INVALID_SEQUENCE. MISSION_CLEAR_ALL (type FENCE): the fence is emptied, ACCEPTED.
"""

from __future__ import annotations

from collections.abc import Callable

from sitl.fence_store import FENCE_COMMANDS, MAX_ITEMS, FenceItem, FenceStore
from sitl.mav import MAVLinkMessage, mavlink

_P = mavlink
TYPE_FENCE: int = _P.MAV_MISSION_TYPE_FENCE
GLOBAL_FRAMES = (0, 3, 5, 6, 10, 11)  # GLOBAL, GLOBAL_RELATIVE_ALT, their _INT, and TERRAIN_ALT(_INT)
UPLOAD_TIMEOUT_MS = 8000
RESEND_MS = 1000


def item_from_message(msg: MAVLinkMessage) -> FenceItem | int:
    """The stored item from MISSION_ITEM(_INT), or the MAV_MISSION_RESULT refusing it."""
    if int(msg.frame) not in GLOBAL_FRAMES:
        return int(_P.MAV_MISSION_UNSUPPORTED_FRAME)
    if int(msg.command) not in FENCE_COMMANDS:
        return int(_P.MAV_MISSION_UNSUPPORTED)
    legacy = msg.get_msgId() == _P.MAVLINK_MSG_ID_MISSION_ITEM
    x, y = (round(msg.x * 1e7), round(msg.y * 1e7)) if legacy else (int(msg.x), int(msg.y))
    return FenceItem(int(msg.command), float(msg.param1), x, y)


class FenceProtocol:
    """One autopilot's fence transfers (see the module docstring)."""

    def __init__(self, store: FenceStore, mav: mavlink.MAVLink, send: Callable[[MAVLinkMessage], None],
                 say: Callable[[int, str], None]) -> None:
        self.store = store
        self.mav = mav
        self._send = send
        self._say = say
        self.receiving = False
        self._new: list[FenceItem] = []
        self._count = 0
        self._dest = (0, 0)
        self._last_receive_ms = self._last_request_ms = 0

    def _ack(self, to: tuple[int, int], result: int) -> None:
        self._send(self.mav.mission_ack_encode(to[0], to[1], result, TYPE_FENCE))

    def _request(self, now_ms: int) -> None:
        self._send(self.mav.mission_request_encode(self._dest[0], self._dest[1], len(self._new), TYPE_FENCE))
        self._last_request_ms = now_ms

    def handle(self, msg: MAVLinkMessage, now_ms: int) -> None:
        """One mission message of type FENCE addressed to us."""
        mid, sender = msg.get_msgId(), (msg.get_srcSystem(), msg.get_srcComponent())
        if mid == _P.MAVLINK_MSG_ID_MISSION_COUNT:
            self._start(int(msg.count), sender, now_ms)
        elif mid in (_P.MAVLINK_MSG_ID_MISSION_ITEM, _P.MAVLINK_MSG_ID_MISSION_ITEM_INT):
            self._item(msg, sender, now_ms)
        elif mid == _P.MAVLINK_MSG_ID_MISSION_REQUEST_LIST:
            if self.receiving:
                self._ack(sender, _P.MAV_MISSION_DENIED)
            else:
                self._send(self.mav.mission_count_encode(sender[0], sender[1], len(self.store.items), TYPE_FENCE))
        elif mid in (_P.MAVLINK_MSG_ID_MISSION_REQUEST_INT, _P.MAVLINK_MSG_ID_MISSION_REQUEST):
            self._download(int(msg.seq), sender)
        elif mid == _P.MAVLINK_MSG_ID_MISSION_CLEAR_ALL:
            if self.receiving and sender != self._dest:
                self._ack(sender, _P.MAV_MISSION_DENIED)
                return
            self.receiving = False
            self.store.write(())
            self._ack(sender, _P.MAV_MISSION_ACCEPTED)

    def _start(self, count: int, sender: tuple[int, int], now_ms: int) -> None:
        if self.receiving and sender != self._dest:
            self._ack(sender, _P.MAV_MISSION_DENIED)
            return
        if count > MAX_ITEMS:
            self.receiving = False
            self._ack(sender, _P.MAV_MISSION_NO_SPACE)
            return
        if count == 0:
            self.receiving = False
            self.store.write(())
            self._ack(sender, _P.MAV_MISSION_ACCEPTED)
            return
        self.receiving, self._dest, self._count, self._new = True, sender, count, []
        self._last_receive_ms = now_ms
        self._request(now_ms)

    def _item(self, msg: MAVLinkMessage, sender: tuple[int, int], now_ms: int) -> None:
        if not self.receiving:
            self._ack(sender, _P.MAV_MISSION_ERROR)
            return
        if sender != self._dest:
            self._ack(sender, _P.MAV_MISSION_DENIED)
            return
        if int(msg.seq) != len(self._new):
            self._ack(sender, _P.MAV_MISSION_INVALID_SEQUENCE)
            return
        parsed = item_from_message(msg)
        if isinstance(parsed, int):
            self.receiving = False
            self._ack(sender, parsed)
            return
        self._new.append(parsed)
        self._last_receive_ms = now_ms
        if len(self._new) < self._count:
            self._request(now_ms)
            return
        self.receiving = False
        ok = self.store.write(tuple(self._new))
        self._ack(sender, _P.MAV_MISSION_ACCEPTED if ok else _P.MAV_MISSION_ERROR)

    def _download(self, seq: int, sender: tuple[int, int]) -> None:
        if self.receiving:
            self._ack(sender, _P.MAV_MISSION_DENIED)
            return
        if not 0 <= seq < len(self.store.items):
            self._ack(sender, _P.MAV_MISSION_INVALID_SEQUENCE)
            return
        item = self.store.items[seq]
        self._send(self.mav.mission_item_int_encode(sender[0], sender[1], seq, _P.MAV_FRAME_GLOBAL, item.command, 0, 0,
                                                    item.param1, 0.0, 0.0, 0.0, item.x, item.y, 0.0, TYPE_FENCE))

    def update(self, now_ms: int) -> None:
        """Upload timeout and re-requests (called every loop)."""
        if not self.receiving:
            return
        if now_ms - self._last_receive_ms > UPLOAD_TIMEOUT_MS:
            self.receiving = False
            self._say(_P.MAV_SEVERITY_WARNING, "Fence upload timeout")
            self._ack(self._dest, _P.MAV_MISSION_OPERATION_CANCELLED)
        elif now_ms - self._last_request_ms > RESEND_MS:
            self._request(now_ms)
