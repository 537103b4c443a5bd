"""Simple avoidance wired into the command core (rover_bridge.command.proximity): messages and times in, the
limited twist and the exact PWM out.

Profile: the open-loop test profile with fast acceleration (the first output carries the request) but the
default deceleration 2 m/s^2, so the cap uses a = 1 m/s^2 (half, as Rover), delay 0.3 + 0.05 s. Default
geometry: 0.5 m/s on both wheels is PWM 1739 (tests/test_command_core.py).
"""

from __future__ import annotations

import pytest
from test_command_core import Rig, overrides, profile, texts
from test_drivers import AUTO, DriveRig

from rover_bridge.app.composition import BridgeCore
from rover_bridge.command.avoidance import cap_speed_m_s
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.wire import Incoming, Link, Outgoing
from rover_bridge.params import Profile

MANUAL, GUIDED = 0, 15
A_M_S2, DELAY_S = 1.0, 0.35


def prof(decel_m_s2: float = 2.0, **avoidance: object) -> Profile:
    """The cap's tests brake at 2 m/s^2; the others brake at once (the limiter's ramp is not what they test)."""
    return profile(limits={"max_linear_decel_m_s2": decel_m_s2}, avoidance=avoidance)


FAST_BRAKE = 100.0


class AvoidRig(Rig):
    def distance(self, t: float, cm: int, orientation: int = 0, sensor_id: int = 10, src: tuple[int, int] = (1, 1),
                 max_cm: int = 20000) -> None:
        mav = mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
        msg = mavlink.MAVLink_distance_sensor_message(int(t * 1000), 0, max_cm, cm,
                                                      mavlink.MAV_DISTANCE_SENSOR_LASER, sensor_id, orientation, 0)
        self.feed(Link.AUTOPILOT, self.wire(mav, msg), t)

    def param(self, t: float, name: str, value: float) -> None:
        msg = mavlink.MAVLink_param_value_message(name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32, 900, 0)
        self.feed(Link.AUTOPILOT, self.wire(self.ap, msg), t)

    def tick(self, t: float) -> list[Outgoing]:
        out = self.core.tick(t)
        self.sent += [(t, o) for o in out]
        return out


def ready(p: Profile | None = None, mode: int = GUIDED) -> AvoidRig:
    rig = AvoidRig(p or prof())
    rig.heartbeat(0.0, mode=mode)
    return rig


def expected_cap(distance_m: float, margin_m: float = 2.0) -> float:
    return cap_speed_m_s(distance_m - margin_m, A_M_S2, DELAY_S)


def test_a_wall_ahead_caps_the_speed_toward_it_says_so_and_counts_it() -> None:
    rig = ready()
    rig.distance(0.10, 250)
    out = rig.local(0.11, vx=1.0, mask=3527).out
    cap = expected_cap(2.5)
    assert 0.6 < cap < 0.7  # -0.35 + sqrt(0.35^2 + 2 * 0.439)
    assert rig.core.commanded.v_m_s == pytest.approx(cap)
    assert "RB: obstacle ahead: slowing to stop 2 m short" in texts(out)
    assert rig.core.counters["avoid.obstacle_slow"] == 1
    # Closer: the cap falls (the limiter brakes to it at 2 m/s^2); inside the margin: stopped, said no more.
    for k in range(6):
        rig.distance(0.16 + 0.05 * k, 210)
        rig.tick(0.16 + 0.05 * k)
    assert rig.core.commanded.v_m_s == pytest.approx(expected_cap(2.1))
    out = []
    for k in range(6):
        rig.distance(0.46 + 0.05 * k, 195)
        out = rig.tick(0.46 + 0.05 * k)
    assert rig.core.commanded.v_m_s == 0.0
    assert overrides(out) == [(1500, 1500)]
    assert rig.core.counters["avoid.obstacle_stop"] == 1
    assert not any("obstacle" in t for t in texts(out))


def test_motion_away_or_beside_passes_and_backing_away_from_a_wall_inside_the_margin_works() -> None:
    rig = ready(prof(FAST_BRAKE))
    rig.distance(0.10, 150)  # ahead, inside the margin
    rig.distance(0.10, 150, orientation=2, sensor_id=12)  # to the right
    assert overrides(rig.local(0.11, vx=-0.5, mask=3527).out) == [(1261, 1261)]  # back away: untouched
    assert rig.core.commanded.v_m_s == pytest.approx(-0.5)
    assert overrides(rig.local(0.12, vx=0.5, mask=3527).out) == [(1500, 1500)]  # toward it: stopped
    rig2 = ready(prof(FAST_BRAKE))
    rig2.distance(0.10, 150, orientation=4, sensor_id=14)  # behind
    assert overrides(rig2.local(0.11, vx=0.5, mask=3527).out) == [(1739, 1739)]
    assert rig2.core.counters.get("avoid.obstacle_slow", 0) == 0


def test_manual_is_not_avoided_by_default_and_is_with_in_manual() -> None:
    rig = ready(prof(FAST_BRAKE), mode=MANUAL)
    rig.distance(0.10, 150)
    assert overrides(rig.manual(0.11, 1000, 0).out) == [(1739, 1739)]
    rig2 = ready(prof(FAST_BRAKE, in_manual=True), mode=MANUAL)
    rig2.distance(0.10, 150)
    assert overrides(rig2.manual(0.11, 1000, 0).out) == [(1500, 1500)]
    # The same MANUAL_CONTROL in GUIDED (ACRO, STEERING alike) is avoided by default.
    rig3 = ready(prof(FAST_BRAKE))
    rig3.distance(0.10, 150)
    assert overrides(rig3.manual(0.11, 1000, 0).out) == [(1500, 1500)]


def test_the_autopilots_own_navigation_passes_unchanged() -> None:
    def run(with_wall: bool) -> list[tuple[int, int]]:
        rig = DriveRig(prof())
        rig.heartbeat(0.0, mode=AUTO)
        out: list[Outgoing] = []
        for k in range(40):
            t = 0.01 + k * 0.025
            if with_wall:
                msg = mavlink.MAVLink_distance_sensor_message(int(t * 1000), 0, 20000, 100,
                                                              mavlink.MAV_DISTANCE_SENSOR_LASER, 10, 0, 0)
                rig.feed(Link.AUTOPILOT, rig.wire(rig.ap, msg), t)
            out += rig.servo(t, 1750, 1750)
            if rig.core.next_deadline_s(t) <= t:
                out += rig.core.tick(t)
        return overrides(out)

    moving = run(with_wall=True)
    assert moving == run(with_wall=False)
    assert moving[-1][0] > 1600


def test_a_silent_sensor_crawls_in_every_direction_and_says_so_once() -> None:
    rig = ready(prof(FAST_BRAKE))
    rig.distance(0.10, 1500)  # far: no limit
    rig.local(0.11, vx=0.5, mask=3527)
    assert rig.core.commanded.v_m_s == pytest.approx(0.5)
    out = rig.local(0.70, vx=0.5, mask=3527).out  # 0.6 s silent > sensor_timeout_s 0.5
    assert rig.core.commanded.v_m_s == pytest.approx(0.2)
    assert "RB: proximity sensor silent: crawling (0.2 m/s)" in texts(out)
    rig.local(0.75, vx=-0.5, mask=3527)
    assert rig.core.commanded.v_m_s == pytest.approx(-0.2)
    later = [o for t, o in rig.sent if t > 0.70]
    assert not any("silent" in t for t in texts(later))
    assert rig.core.counters["avoid.sensor_silent"] == 1
    rig.distance(0.80, 1500)  # back: full speed again
    rig.local(0.81, vx=0.5, mask=3527)
    assert rig.core.commanded.v_m_s == pytest.approx(0.5)
    assert rig.core.counters["avoid.sensor_back"] == 1


AVOID_AND_FENCE = ["AVOID_ENABLE", "AVOID_MARGIN", "AVOID_BACKUP_SPD", "FENCE_ENABLE", "FENCE_TYPE", "FENCE_RADIUS",
                   "FENCE_MARGIN"]
FENCE_OFF = (("FENCE_ENABLE", 0.0), ("FENCE_TYPE", 6.0), ("FENCE_RADIUS", 300.0), ("FENCE_MARGIN", 2.0))


def avoid_reads(out: list[Outgoing]) -> list[str]:
    return [o.msg.param_id for o in out if o.msg.get_type() == "PARAM_REQUEST_READ" and o.msg.param_id in
            AVOID_AND_FENCE]


def test_avoid_and_fence_params_are_read_at_the_first_heartbeat_and_avoid_enable_0_turns_it_off() -> None:
    rig = ready()
    assert avoid_reads(rig.tick(0.05)) == AVOID_AND_FENCE  # asked once the autopilot is known, as FS_GCS_*
    rig.param(0.13, "AVOID_MARGIN", 1.0)
    rig.param(0.13, "AVOID_BACKUP_SPD", 0.75)
    rig.distance(0.135, 160)
    rig.local(0.14, vx=1.0, mask=3527)
    assert rig.core.commanded.v_m_s == pytest.approx(expected_cap(1.6, margin_m=1.0))  # AVOID_ENABLE: default 3
    rig.param(0.15, "AVOID_ENABLE", 0.0)
    rig.distance(0.16, 160)
    rig.local(0.17, vx=1.0, mask=3527)
    assert rig.core.commanded.v_m_s == pytest.approx(0.8)  # max_linear_m_s: not avoided


def test_an_unasked_avoid_enable_0_is_not_believed_until_the_autopilot_says_it() -> None:
    rig = ready(prof(FAST_BRAKE))
    rig.tick(0.05)
    rig.distance(0.10, 150)
    for name, value in (("AVOID_ENABLE", 3.0), ("AVOID_MARGIN", 2.0), ("AVOID_BACKUP_SPD", 0.75), *FENCE_OFF):
        rig.param(0.13, name, value)
    assert avoid_reads(rig.tick(2.5)) == []  # all answered: the reader stops asking
    rig.param(2.60, "AVOID_ENABLE", 0.0)  # a lone frame (forged, corrupted, or a GCS's PARAM_SET)
    rig.distance(2.605, 150)
    assert overrides(rig.local(2.61, vx=0.5, mask=3527).out) == [(1500, 1500)]
    assert avoid_reads(rig.tick(2.70)) == ["AVOID_ENABLE"]
    rig.param(2.71, "AVOID_ENABLE", 0.0)  # the autopilot confirms
    rig.distance(2.72, 150)
    assert overrides(rig.local(2.73, vx=0.5, mask=3527).out) == [(1739, 1739)]


def test_sensors_of_other_systems_are_ignored_and_a_companion_scan_on_the_gcs_link_counts() -> None:
    rig = ready(prof(FAST_BRAKE))
    rig.distance(0.10, 150, src=(7, 1))
    assert overrides(rig.local(0.11, vx=0.5, mask=3527).out) == [(1739, 1739)]
    assert rig.core.avoid.picture is None
    camera = mavlink.MAVLink(None, srcSystem=1, srcComponent=196)
    scan = [65535] * 72
    scan[0] = scan[71] = scan[1] = 150  # straight ahead, 1.5 m (BODY_FRD)
    msg = mavlink.MAVLink_obstacle_distance_message(0, mavlink.MAV_DISTANCE_SENSOR_LASER, scan, 5, 20, 1000, 0.0,
                                                    -5.0, mavlink.MAV_FRAME_BODY_FRD)
    rig.feed(Link.GCS, rig.wire(camera, msg), 0.12)
    assert overrides(rig.local(0.13, vx=0.5, mask=3527).out) == [(1500, 1500)]


def _script(rig: Rig) -> list[tuple[float, str, tuple[object, ...]]]:
    """Requests, MANUAL_CONTROL, ticks and heartbeats for 3 s; every message sent, as comparable tuples."""
    rig.heartbeat(0.0, mode=GUIDED)
    rig.local(0.01, vx=0.6, yaw_rate=0.2)
    rig.run_until(1.0, 0.01)
    rig.manual(1.02, 800, -300)
    rig.run_until(2.0, 1.02)
    rig.local(2.01, vx=-0.4, mask=3527)
    rig.run_until(3.0, 2.01)
    return [(t, o.msg.get_type(), tuple(o.msg.to_dict().items())) for t, o in rig.sent]


def _drive(sent: list[tuple[float, str, tuple[object, ...]]]) -> list[tuple[float, str, tuple[object, ...]]]:
    """What was sent, but the avoidance's reads of AVOID_* / FENCE_* (a few frames at the first heartbeat)."""
    return [m for m in sent if m[1] != "PARAM_REQUEST_READ" or dict(m[2])["param_id"] not in AVOID_AND_FENCE]


def test_without_any_sensor_the_outputs_are_exactly_todays() -> None:
    on = Rig(profile(fast=False))
    off = Rig(profile(fast=False, avoidance={"enabled": False}))
    sent_on, sent_off = _script(on), _script(off)
    assert _drive(sent_on) == sent_off
    reads = [m for m in sent_on if m not in _drive(sent_on)]
    assert len(reads) == 2 * len(AVOID_AND_FENCE)  # asked and asked again: this autopilot answers nothing
    assert on.core.avoid.picture is None
    assert not any(k.startswith("avoid.") for k in on.core.counters)


HB = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                       mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED, mavlink.MAV_STATE_ACTIVE, 3)


class Autopilot:
    """A BridgeCore fed by a scripted autopilot that accepts every SET_MESSAGE_INTERVAL at once."""

    def __init__(self, p: Profile) -> None:
        self.core = BridgeCore(p)
        self.ap = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)

    def feed(self, msg: MAVLinkMessage, t: float) -> list[Outgoing]:
        return list(self.core.handle(Incoming(Link.AUTOPILOT, self.ap.decode(bytearray(msg.pack(self.ap)))), t).out)

    def run(self, out: list[Outgoing], t0: float, t1: float) -> list[Outgoing]:
        """From t0 to t1 on a 10 ms clock: heartbeats at 1 Hz, ticks, every interval request answered."""
        sent, pending = list(out), list(out)
        k = round(t0 * 100)
        while k < round(t1 * 100):
            t = k / 100.0
            new: list[Outgoing] = []
            for o in pending:
                if o.msg.get_type() == "COMMAND_LONG" and o.msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                    new += self.feed(mavlink.MAVLink_command_ack_message(o.msg.command, mavlink.MAV_RESULT_ACCEPTED,
                                                                         0, 0, o.src_system, o.src_component), t)
            new += (self.feed(HB, t) if k % 100 == 0 else []) + self.core.tick(t)
            sent += new
            pending = new
            k += 1
        return sent


def asked(out: list[Outgoing]) -> list[tuple[float, float]]:
    return [(o.msg.param1, o.msg.param2) for o in out if o.msg.get_type() == "COMMAND_LONG"
            and o.msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
            and o.msg.param1 == mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR]


def test_the_bridge_asks_for_distance_sensor_at_the_sensor_rate_once_the_autopilot_sends_one() -> None:
    rig = Autopilot(prof())
    before = rig.run(rig.feed(HB, 0.0), 0.0, 3.0)
    assert asked(before) == []
    out = rig.feed(mavlink.MAVLink_distance_sensor_message(100, 0, 20000, 500, 0, 10, 0, 0), 3.0)
    assert asked(rig.run(out, 3.0, 5.0)) == [(float(mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR), 100000.0)]


def test_without_any_sensor_the_whole_bridge_sends_exactly_what_it_sends_with_avoidance_off() -> None:
    def script(p: Profile) -> list[tuple[str, tuple[object, ...]]]:
        rig = Autopilot(p)
        return [(o.msg.get_type(), tuple(o.msg.to_dict().items())) for o in rig.run(rig.feed(HB, 0.0), 0.0, 4.0)]

    on = script(prof())
    assert len(on) > 80  # overrides at 20 Hz, heartbeats, stream requests
    drive = [m for m in on if m[0] != "PARAM_REQUEST_READ" or dict(m[1])["param_id"] not in AVOID_AND_FENCE]
    assert drive == script(prof(enabled=False))
    assert len(on) - len(drive) == 2 * len(AVOID_AND_FENCE)  # the reads: 0 s and 2 s (nobody answers them)
