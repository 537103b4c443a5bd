"""The MAVLink mission protocol of ArduPilot (upload, download, clear, set current), as behaviour.

Read in ArduPilot (4.7): libraries/GCS_MAVLink/MissionItemProtocol.cpp, MissionItemProtocol_Waypoints.cpp,
GCS_Common.cpp (handle_mission_item, handle_mission_set_current) and AP_Mission.cpp
(mavlink_int_to_mission_cmd, mission_cmd_to_mavlink_int). What is kept:

- Upload: MISSION_COUNT (count > 700: MAV_MISSION_NO_SPACE) truncates the stored mission at once, then
  each item is asked for with MISSION_REQUEST (ArduPilot asks with MISSION_REQUEST, not _INT, and takes
  MISSION_ITEM_INT or MISSION_ITEM in answer), again after 1 s without an answer; 8 s without an item
  cancels ("Mission upload timeout", MAV_MISSION_OPERATION_CANCELLED). An item out of sequence:
  MAV_MISSION_INVALID_SEQUENCE (the upload goes on); from another system or component: DENIED; a bad
  frame or position ends the upload with that error. After the last: "Flight plan received" and
  MAV_MISSION_ACCEPTED. MISSION_COUNT 0 is a clear. A second uploader while one is running: DENIED.
- An item outside an upload: MAV_MISSION_ERROR. "got MISSION_ITEM; GCS should send MISSION_ITEM_INT"
  and "got MISSION_REQUEST; use MISSION_REQUEST_INT!" are said once per upload / download.
- Download: MISSION_REQUEST_LIST -> MISSION_COUNT (items with home), MISSION_REQUEST_INT n ->
  MISSION_ITEM_INT n (item 0 = home, frame GLOBAL; items with a relative altitude come back with frame
  GLOBAL_RELATIVE_ALT (3), absolute GLOBAL (0), terrain (10): the non-INT frame numbers, as ArduPilot
  returns them); past the end: MISSION_COUNT then MAV_MISSION_INVALID_SEQUENCE; during an upload: DENIED.
  NAV_WAYPOINT keeps only param1 (whole seconds of hold time), as Rover stores it.
- MISSION_CLEAR_ALL: ACCEPTED, or ERROR while armed with the mission running. MISSION_SET_CURRENT n:
  answered by MISSION_CURRENT n when taken.
- MISSION_ITEM(_INT) with current = 2 or 3 (a guided "go here" or an altitude change) is not a mission
  item; the emulator does not navigate GUIDED and ignores it (counted), as it always has.
- Fence transfers (mission_type 1) are sitl/fence_protocol.py's. Rally transfers (2) are not emulated:
  MAV_MISSION_UNSUPPORTED, and an empty list on download.
"""

from __future__ import annotations

from collections.abc import Callable

from sitl.fence_protocol import TYPE_FENCE, FenceProtocol
from sitl.mav import MAVLinkMessage, mavlink
from sitl.mission import CMD_NAV_LAST, CMD_NAV_WAYPOINT, Mission, MissionItem, MissionRunner

_P = mavlink
MAX_ITEMS = 700
UPLOAD_TIMEOUT_MS = 8000
RESEND_MS = 1000
FRAME_ABSOLUTE = (0, 2, 5)  # MAV_FRAME_GLOBAL, MISSION, GLOBAL_INT
FRAME_RELATIVE = (3, 6)  # GLOBAL_RELATIVE_ALT(_INT)
FRAME_TERRAIN = (10, 11)
TYPE_MISSION: int = _P.MAV_MISSION_TYPE_MISSION
WARNING = _P.MAV_SEVERITY_WARNING
MISSION_IDS = frozenset({
    _P.MAVLINK_MSG_ID_MISSION_COUNT, _P.MAVLINK_MSG_ID_MISSION_ITEM, _P.MAVLINK_MSG_ID_MISSION_ITEM_INT,
    _P.MAVLINK_MSG_ID_MISSION_REQUEST, _P.MAVLINK_MSG_ID_MISSION_REQUEST_INT, _P.MAVLINK_MSG_ID_MISSION_REQUEST_LIST,
    _P.MAVLINK_MSG_ID_MISSION_CLEAR_ALL, _P.MAVLINK_MSG_ID_MISSION_SET_CURRENT, _P.MAVLINK_MSG_ID_MISSION_ACK,
})


def _sender(msg: MAVLinkMessage) -> tuple[int, int]:
    return msg.get_srcSystem(), msg.get_srcComponent()


def item_from_message(msg: MAVLinkMessage) -> tuple[MissionItem, int] | int:
    """(stored item, seq) from MISSION_ITEM(_INT), or the MAV_MISSION_RESULT refusing it."""
    legacy = msg.get_msgId() == _P.MAVLINK_MSG_ID_MISSION_ITEM
    command, frame = int(msg.command), int(msg.frame)
    x, y = (int(msg.x * 1e7), int(msg.y * 1e7)) if legacy and command <= CMD_NAV_LAST else (int(msg.x), int(msg.y))
    params = [float(msg.param1), float(msg.param2), float(msg.param3), float(msg.param4)]
    if command <= CMD_NAV_LAST:
        if frame not in FRAME_ABSOLUTE + FRAME_RELATIVE + FRAME_TERRAIN:
            return int(_P.MAV_MISSION_UNSUPPORTED_FRAME)
        if abs(x) > 900_000_000:
            return int(_P.MAV_MISSION_INVALID_PARAM5_X)
        if abs(y) > 1_800_000_000:
            return int(_P.MAV_MISSION_INVALID_PARAM6_Y)
        frame = 3 if frame in FRAME_RELATIVE else 10 if frame in FRAME_TERRAIN else 0
    if command == CMD_NAV_WAYPOINT:
        params = [float(max(0, min(65535, int(params[0])))), 0.0, 0.0, 0.0]
    p1, p2, p3, p4 = params
    return MissionItem(command, frame, p1, p2, p3, p4, x=x, y=y, z=float(msg.z)), int(msg.seq)


class MissionProtocol:
    """One autopilot's mission transfers (see the module docstring)."""

    def __init__(self, mission: Mission, mav: mavlink.MAVLink, send: Callable[[MAVLinkMessage], None],
                 say: Callable[[int, str], None], home_item: Callable[[], MissionItem],
                 count: Callable[[str], None], fence: FenceProtocol | None = None) -> None:
        self.mission = mission
        self.fence = fence
        self.mav = mav
        self._send = send
        self._say = say
        self._home_item = home_item
        self._count_event = count
        self.receiving = False
        self._request_i = self._request_last = 0
        self._dest = (0, 0)
        self._last_receive_ms = self._last_request_ms = 0
        self._item_warned = self._request_warned = False

    def _ack(self, to: tuple[int, int], result: int, mission_type: int = TYPE_MISSION) -> None:
        self._send(self.mav.mission_ack_encode(to[0], to[1], result, mission_type))

    def _request(self, now_ms: int) -> None:
        self._send(self.mav.mission_request_encode(self._dest[0], self._dest[1], self._request_i, TYPE_MISSION))
        self._last_request_ms = now_ms

    def _cancel_upload(self, sender: tuple[int, int]) -> bool:
        if self.receiving and sender != self._dest:
            self._ack(sender, _P.MAV_MISSION_DENIED)
            return False
        self.receiving = False
        return True

    def _complete(self, to: tuple[int, int]) -> None:
        self.receiving = False
        self._say(_P.MAV_SEVERITY_INFO, "Flight plan received")
        self._ack(to, _P.MAV_MISSION_ACCEPTED)

    def handle(self, msg: MAVLinkMessage, now_ms: int, armed: bool, runner: MissionRunner,
               current_msg: Callable[[int], MAVLinkMessage]) -> None:
        """One mission message addressed to us."""
        mid, sender = msg.get_msgId(), _sender(msg)
        mission_type = int(getattr(msg, "mission_type", TYPE_MISSION))
        if mid == _P.MAVLINK_MSG_ID_MISSION_SET_CURRENT:
            if self.mission.set_current(int(msg.seq), runner):
                self._send(current_msg(int(msg.seq)))
            return
        if mid == _P.MAVLINK_MSG_ID_MISSION_ACK:
            return
        if mid in (_P.MAVLINK_MSG_ID_MISSION_ITEM, _P.MAVLINK_MSG_ID_MISSION_ITEM_INT) and int(msg.current) in (2, 3):
            self._count_event("mission_guided_ignored")  # guided "go here" / altitude change: not navigated
            return
        if mission_type == TYPE_FENCE and self.fence is not None:
            self.fence.handle(msg, now_ms)
            return
        if mission_type != TYPE_MISSION:
            if mid == _P.MAVLINK_MSG_ID_MISSION_REQUEST_LIST:
                self._send(self.mav.mission_count_encode(sender[0], sender[1], 0, mission_type))
            else:
                self._ack(sender, _P.MAV_MISSION_UNSUPPORTED, mission_type)
            return
        if mid == _P.MAVLINK_MSG_ID_MISSION_COUNT:
            self._count(msg, sender, now_ms)
        elif mid in (_P.MAVLINK_MSG_ID_MISSION_ITEM, _P.MAVLINK_MSG_ID_MISSION_ITEM_INT):
            self._item(msg, sender, now_ms)
        elif mid == _P.MAVLINK_MSG_ID_MISSION_REQUEST_LIST:
            if self.receiving:
                self._ack(sender, _P.MAV_MISSION_DENIED)
            else:
                self._send(self.mav.mission_count_encode(sender[0], sender[1], self.mission.count(), TYPE_MISSION))
        elif mid in (_P.MAVLINK_MSG_ID_MISSION_REQUEST_INT, _P.MAVLINK_MSG_ID_MISSION_REQUEST):
            self._download(msg, sender, legacy=mid == _P.MAVLINK_MSG_ID_MISSION_REQUEST)
        elif mid == _P.MAVLINK_MSG_ID_MISSION_CLEAR_ALL and self._cancel_upload(sender):
            ok = self.mission.clear(armed)
            self._ack(sender, _P.MAV_MISSION_ACCEPTED if ok else _P.MAV_MISSION_ERROR)

    def _count(self, msg: MAVLinkMessage, sender: tuple[int, int], now_ms: int) -> None:
        if not self._cancel_upload(sender):
            return
        count = int(msg.count)
        if count > MAX_ITEMS:
            self._ack(sender, _P.MAV_MISSION_NO_SPACE)
            self._say(WARNING, f"Only {MAX_ITEMS} items are supported")
            return
        self.mission.truncate(count)
        if count == 0:
            self._complete(sender)
            return
        self.receiving, self._dest = True, sender
        self._request_i, self._request_last = 0, count - 1
        self._last_receive_ms = now_ms
        self._item_warned = self._request_warned = False
        self._request(now_ms)

    def _item(self, msg: MAVLinkMessage, sender: tuple[int, int], now_ms: int) -> None:
        if msg.get_msgId() == _P.MAVLINK_MSG_ID_MISSION_ITEM and not self._item_warned:
            self._item_warned = True
            self._say(WARNING, "got MISSION_ITEM; GCS should send MISSION_ITEM_INT")
        if not self.receiving:
            self._ack(sender, _P.MAV_MISSION_ERROR)
            return
        if int(msg.seq) != self._request_i:
            self._ack(sender, _P.MAV_MISSION_INVALID_SEQUENCE)
            return
        if sender != self._dest:
            self._ack(sender, _P.MAV_MISSION_DENIED)
            return
        parsed = item_from_message(msg)
        if isinstance(parsed, int) or not self.mission.write(parsed[1], parsed[0]):
            self._ack(sender, parsed if isinstance(parsed, int) else _P.MAV_MISSION_ERROR)
            self.receiving = False
            return
        self._last_receive_ms = now_ms
        self._request_i += 1
        if self._request_i > self._request_last:
            self._complete(sender)
        else:
            self._request(now_ms)

    def _download(self, msg: MAVLinkMessage, sender: tuple[int, int], legacy: bool) -> None:
        if self.receiving and not legacy:
            self._ack(sender, _P.MAV_MISSION_DENIED)
            return
        seq = int(msg.seq)
        item = self._home_item() if seq == 0 else self.mission.item(seq)
        if item is None or (seq != 0 and seq >= self.mission.count()):
            if not legacy:
                self._send(self.mav.mission_count_encode(sender[0], sender[1], self.mission.count(), TYPE_MISSION))
            self._ack(sender, _P.MAV_MISSION_INVALID_SEQUENCE)
            return
        current = 1 if seq != 0 and seq == self.mission.current_nav_index() else 0
        args = (sender[0], sender[1], seq, item.frame, item.command, current, item.autocontinue,
                item.param1, item.param2, item.param3, item.param4)
        if not legacy:
            self._send(self.mav.mission_item_int_encode(*args, item.x, item.y, item.z, TYPE_MISSION))
            return
        if not self._request_warned:
            self._request_warned = True
            self._say(WARNING, "got MISSION_REQUEST; use MISSION_REQUEST_INT!")
        x, y = (item.x * 1e-7, item.y * 1e-7) if item.command <= CMD_NAV_LAST else (float(item.x), float(item.y))
        self._send(self.mav.mission_item_encode(*args, x, y, item.z, TYPE_MISSION))

    def update(self, now_ms: int) -> None:
        """Upload timeout and re-requests (called every loop)."""
        if self.fence is not None:
            self.fence.update(now_ms)
        if not self.receiving:
            return
        if now_ms - self._last_receive_ms > UPLOAD_TIMEOUT_MS:
            self.receiving = False
            self._say(WARNING, "Mission upload timeout")
            self._ack(self._dest, _P.MAV_MISSION_OPERATION_CANCELLED)
        elif now_ms - self._last_request_ms > RESEND_MS:
            self._request(now_ms)
