"""Which message goes out when: stream groups (SRn_*), SET_MESSAGE_INTERVAL and one-off requests.

Read in ArduPilot (4.7): libraries/GCS_MAVLink/GCS_MAVLink_Parameters.cpp (the groups),
GCS_Common.cpp (set_message_interval, cap_message_interval, handle_command_request_message). What is kept:

- Groups: RAW_SENSORS (RAW_IMU, SCALED_IMU), EXTENDED_STATUS (SYS_STATUS, MISSION_CURRENT,
  NAV_CONTROLLER_OUTPUT), RC_CHANNELS (SERVO_OUTPUT_RAW, RC_CHANNELS), POSITION (GLOBAL_POSITION_INT,
  LOCAL_POSITION_NED), EXTRA1 (ATTITUDE, SIMSTATE, PID_TUNING, WHEEL_DISTANCE), EXTRA2 (VFR_HUD),
  EXTRA3 (SYSTEM_TIME, DISTANCE_SENSOR: one slot sends every range sensor's). HEARTBEAT at 1 Hz.
  HOME_POSITION only on request or when home is set.
- SET_MESSAGE_INTERVAL: param3 != 0 is DENIED; -1 stops the message, 0 goes back to the group's rate,
  other negatives are DENIED; the interval is taken in whole milliseconds (1 ms at least, 60 s at most);
  one shorter than 1.25 loop periods (interval_ms * 800 < loop period in us: 25 ms at
  SCHED_LOOP_RATE 50) is DENIED with "Requested rate for message ID N too fast. Increase
  SCHED_LOOP_RATE". A message with no internal mapping: DENIED, "No ap_message for mavlink id (N)".
- A group's rate (REQUEST_DATA_STREAM, SRn_) is capped instead (cap_message_interval): at most 0.8 x
  SCHED_LOOP_RATE, 40 Hz at SCHED_LOOP_RATE 50.
- Intervals live in RAM: a reboot forgets them (SRn_ parameters persist). Sending keeps the average
  rate (the next time is the last due time plus the interval) and skips, rather than bursts, when late.
"""

from __future__ import annotations

from sitl.mav import mavlink

_P = mavlink
ACCEPTED: int = _P.MAV_RESULT_ACCEPTED
DENIED: int = _P.MAV_RESULT_DENIED
HOME_POSITION: int = _P.MAVLINK_MSG_ID_HOME_POSITION

# Stream group id -> (SRn parameter, MAVLink message ids in the group).
STREAM_GROUPS: dict[int, tuple[str, tuple[int, ...]]] = {
    _P.MAV_DATA_STREAM_RAW_SENSORS: ("SR0_RAW_SENS", (_P.MAVLINK_MSG_ID_RAW_IMU, _P.MAVLINK_MSG_ID_SCALED_IMU)),
    _P.MAV_DATA_STREAM_EXTENDED_STATUS: (
        "SR0_EXT_STAT",
        (_P.MAVLINK_MSG_ID_SYS_STATUS, _P.MAVLINK_MSG_ID_MISSION_CURRENT, _P.MAVLINK_MSG_ID_NAV_CONTROLLER_OUTPUT),
    ),
    _P.MAV_DATA_STREAM_RC_CHANNELS: (
        "SR0_RC_CHAN",
        (_P.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, _P.MAVLINK_MSG_ID_RC_CHANNELS),
    ),
    _P.MAV_DATA_STREAM_POSITION: (
        "SR0_POSITION",
        (_P.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, _P.MAVLINK_MSG_ID_LOCAL_POSITION_NED),
    ),
    _P.MAV_DATA_STREAM_EXTRA1: (
        "SR0_EXTRA1",
        (_P.MAVLINK_MSG_ID_ATTITUDE, _P.MAVLINK_MSG_ID_SIMSTATE, _P.MAVLINK_MSG_ID_PID_TUNING,
         _P.MAVLINK_MSG_ID_WHEEL_DISTANCE),
    ),
    _P.MAV_DATA_STREAM_EXTRA2: ("SR0_EXTRA2", (_P.MAVLINK_MSG_ID_VFR_HUD,)),
    _P.MAV_DATA_STREAM_EXTRA3: ("SR0_EXTRA3", (_P.MAVLINK_MSG_ID_SYSTEM_TIME, _P.MAVLINK_MSG_ID_DISTANCE_SENSOR)),
}
GROUP_OF_MESSAGE = {m: g for g, (_, ids) in STREAM_GROUPS.items() for m in ids}
STREAMABLE = (_P.MAVLINK_MSG_ID_HEARTBEAT, *GROUP_OF_MESSAGE)
MAPPED = frozenset((*STREAMABLE, HOME_POSITION))


class Streams:
    """Per-message intervals and due times (pure: the caller passes times and parameters)."""

    def __init__(self) -> None:
        self.intervals_us: dict[int, int] = {}  # SET_MESSAGE_INTERVAL overrides (-1 = off)
        self.next_due_us: dict[int, int] = {}
        self.pending: list[int] = []  # sent with the next emit (REQUEST_MESSAGE, heartbeat on a mode change)

    def clear(self) -> None:
        """A reboot: intervals and pending requests are gone."""
        self.intervals_us.clear()
        self.next_due_us.clear()
        self.pending.clear()

    def interval_us(self, msg_id: int, group_hz: float | None, loop_period_us: int = 0) -> int | None:
        """Current interval of a message (None = off); ``group_hz`` is its group's SRn_ rate, capped, as every
        interval is, at 0.8 x SCHED_LOOP_RATE (40 Hz at 50: a 50 Hz REQUEST_DATA_STREAM streams at 40 Hz)."""
        override = self.intervals_us.get(msg_id)
        if override is not None:
            return None if override < 0 else override
        if msg_id == _P.MAVLINK_MSG_ID_HEARTBEAT:
            return 1_000_000
        if group_hz is None or group_hz <= 0:
            return None
        interval = round(1e6 / group_hz)
        if interval * 0.8 < loop_period_us:
            return int(loop_period_us / 800) * 1000  # whole milliseconds, as ArduPilot keeps intervals
        return interval

    def reset_group(self, group: int, now_us: int) -> None:
        """REQUEST_DATA_STREAM / an SRn_ change: the group's own intervals go, the new rate starts at once."""
        for mid in STREAM_GROUPS[group][1]:
            self.intervals_us.pop(mid, None)
            self.next_due_us[mid] = now_us

    def set_interval(self, msg_id: int, interval_us: float, param3: float, loop_period_us: int,
                     now_us: int) -> tuple[int, str | None]:
        """(MAV_RESULT, STATUSTEXT or None) for SET_MESSAGE_INTERVAL."""
        if param3 != 0:
            return DENIED, None
        interval = int(interval_us)
        if interval == -1:
            interval_ms = -1
        elif interval == 0:
            interval_ms = 0
        elif interval < 0:
            return DENIED, None
        else:
            interval_ms = max(1, min(60_000, interval // 1000))
            if interval_ms * 800 < loop_period_us:
                return DENIED, f"Requested rate for message ID {msg_id} too fast. Increase SCHED_LOOP_RATE"
        if interval_ms == 0:
            self.intervals_us.pop(msg_id, None)  # back to the default (group) rate
        else:
            self.intervals_us[msg_id] = -1 if interval_ms < 0 else interval_ms * 1000
        self.next_due_us[msg_id] = now_us
        return ACCEPTED, None

    def take_due(self, msg_id: int, interval_us: int, now_us: int, boot_us: int) -> bool:
        """True when ``msg_id`` is due now; its next due time is then advanced."""
        due = self.next_due_us.get(msg_id, boot_us)
        if now_us < due:
            return False
        due += interval_us
        if due <= now_us:  # fell behind (a big step): skip, do not burst
            due = now_us + interval_us
        self.next_due_us[msg_id] = due
        return True
