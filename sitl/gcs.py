"""A scripted ground station for an in-process Emulator: missions, modes, commands and overrides.

No sockets: messages go in through ``Emulator.handle_message`` (packed as system 255, component 190,
so sender ids are real) and come back from ``Emulator.sent_log`` (``record_sent=True``). Simulated time
moves only in ``run``/``run_until``; everything is deterministic. Tests and benchmarks use it to drive
the emulator the way QGroundControl or MAVProxy would (the mission protocol as ArduPilot speaks it:
MISSION_COUNT, then one item per MISSION_REQUEST, then MISSION_ACK).
"""

from __future__ import annotations

from collections.abc import Callable

from sitl.emulator import Emulator
from sitl.geo import lat_lon_of
from sitl.mav import MAVLinkMessage, mavlink

_P = mavlink
GCS_SYSID = 255
GCS_COMPID = 190


class InProcessGcs:
    """A ground station wired straight into ``emu`` (which must record what it sends)."""

    def __init__(self, emu: Emulator, sysid: int = GCS_SYSID, compid: int = GCS_COMPID) -> None:
        if emu.sent_log is None:
            raise ValueError("the emulator must be created with record_sent=True")
        self.emu = emu
        self.sysid, self.compid = sysid, compid
        self._seen = len(emu.sent_log)
        self.received: list[tuple[float, MAVLinkMessage]] = []
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)

    # ------------------------------------------------------------------ wire
    def send(self, msg: MAVLinkMessage) -> None:
        self.emu.handle_message(msg, src_system=self.sysid, src_component=self.compid)

    def run(self, seconds: float, dt_s: float = 0.01, each: Callable[[], None] | None = None) -> list[MAVLinkMessage]:
        """Step the emulator; return what it sent meanwhile. ``each`` runs before every step."""
        start = len(self.received)
        for _ in range(max(1, round(seconds / dt_s))):
            if each is not None:
                each()
            self.emu.step(dt_s)
            self._collect()
        return [m for _, m in self.received[start:]]

    def run_until(self, done: Callable[[], bool], timeout_s: float, dt_s: float = 0.01,
                  each: Callable[[], None] | None = None) -> bool:
        end = self.emu.sim_time_s + timeout_s
        while self.emu.sim_time_s < end - 1e-9:
            if done():
                return True
            self.run(dt_s, dt_s, each)
        return done()

    def _collect(self) -> None:
        log = self.emu.sent_log
        assert log is not None
        self.received += log[self._seen:]
        self._seen = len(log)

    def of(self, type_name: str) -> list[MAVLinkMessage]:
        return [m for _, m in self.received if m.get_type() == type_name]

    def texts(self) -> list[str]:
        """STATUSTEXTs, chunks of a long one (same id) joined."""
        out: list[str] = []
        last_id = 0
        for m in self.of("STATUSTEXT"):
            if m.id != 0 and m.id == last_id and m.chunk_seq > 0:
                out[-1] += m.text
            else:
                out.append(m.text)
            last_id = m.id
        return out

    # ------------------------------------------------------------------ conveniences
    def heartbeat(self) -> None:
        self.send(self.mav.heartbeat_encode(_P.MAV_TYPE_GCS, _P.MAV_AUTOPILOT_INVALID, 0, 0, 0))

    def command(self, command: int, *params: float) -> int | None:
        """COMMAND_LONG to 1/1; the COMMAND_ACK's result (None without one)."""
        p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
        self.send(self.mav.command_long_encode(1, 1, command, 0, *p))
        acks = [m for m in self.run(0.02) if m.get_type() == "COMMAND_ACK" and m.command == command]
        return int(acks[-1].result) if acks else None

    def set_mode(self, custom_mode: int) -> int | None:
        return self.command(_P.MAV_CMD_DO_SET_MODE, _P.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom_mode)

    def arm(self, force: bool = False) -> int | None:
        return self.command(_P.MAV_CMD_COMPONENT_ARM_DISARM, 1, 21196 if force else 0)

    def override(self, **channels: int) -> None:
        values = [channels.get(f"ch{i}", 65535 if i <= 8 else 0) for i in range(1, 19)]
        self.send(self.mav.rc_channels_override_encode(1, 1, *values))

    def waypoint(self, seq: int, north_m: float, east_m: float, hold_s: float = 0.0) -> MAVLinkMessage:
        """A MISSION_ITEM_INT NAV_WAYPOINT north/east of the emulator's origin (relative altitude 0)."""
        v = self.emu.vehicle
        lat, lon = lat_lon_of(north_m, east_m, v.origin_lat_deg, v.origin_lon_deg)
        return self.mav.mission_item_int_encode(1, 1, seq, _P.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                _P.MAV_CMD_NAV_WAYPOINT, 0, 1, hold_s, 0.0, 0.0, 0.0,
                                                round(lat * 1e7), round(lon * 1e7), 0.0)

    def fence_item(self, seq: int, command: int, north_m: float, east_m: float, param1: float) -> MAVLinkMessage:
        """A MISSION_ITEM_INT of mission type FENCE north/east of the origin (param1: vertex count or radius)."""
        v = self.emu.vehicle
        lat, lon = lat_lon_of(north_m, east_m, v.origin_lat_deg, v.origin_lon_deg)
        return self.mav.mission_item_int_encode(1, 1, seq, _P.MAV_FRAME_GLOBAL_INT, command, 0, 1, param1, 0.0, 0.0,
                                                0.0, round(lat * 1e7), round(lon * 1e7), 0.0,
                                                _P.MAV_MISSION_TYPE_FENCE)

    def upload(self, items: list[MAVLinkMessage], timeout_s: float = 5.0,
               mission_type: int = _P.MAV_MISSION_TYPE_MISSION) -> int | None:
        """MISSION_COUNT, then each item MISSION_REQUEST(_INT) asks for; the final MISSION_ACK type."""
        start = len(self.received)
        self.send(self.mav.mission_count_encode(1, 1, len(items), mission_type))
        answered: set[int] = set()
        end = self.emu.sim_time_s + timeout_s
        while self.emu.sim_time_s < end:
            for _, m in self.received[start:]:
                if m.get_type() == "MISSION_ACK":
                    return int(m.type)
                if m.get_type() in ("MISSION_REQUEST", "MISSION_REQUEST_INT") and m.seq not in answered:
                    answered.add(m.seq)
                    self.send(items[m.seq])
            start = len(self.received)
            self.run(0.02)
        return None

    def download(self, timeout_s: float = 5.0, mission_type: int = _P.MAV_MISSION_TYPE_MISSION) -> list[MAVLinkMessage]:
        """MISSION_REQUEST_LIST, then MISSION_REQUEST_INT for each item; the MISSION_ITEM_INTs, in order."""
        self.send(self.mav.mission_request_list_encode(1, 1, mission_type))
        counts = [m for m in self.run(0.02) if m.get_type() == "MISSION_COUNT"]
        if not counts:
            return []
        items: list[MAVLinkMessage] = []
        for seq in range(counts[-1].count):
            self.send(self.mav.mission_request_int_encode(1, 1, seq, mission_type))
            got = [m for m in self.run(0.02) if m.get_type() == "MISSION_ITEM_INT" and m.seq == seq]
            if not got:
                break
            items.append(got[-1])
        self.send(self.mav.mission_ack_encode(1, 1, _P.MAV_MISSION_ACCEPTED, mission_type))
        return items
