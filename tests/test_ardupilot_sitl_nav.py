"""Against a real ArduPilot Rover SITL (optional): the autopilot drives through the bridge (issue 29).

Runs only when ROVER_BRIDGE_ARDUROVER names an `ardurover` binary (see tests/test_ardupilot_sitl.py); about 8
minutes of wall time: `python -m pytest -m ardupilot_sitl -s tests/test_ardupilot_sitl_nav.py` (-s prints the
figures). Two SITLs run side by side, both rover-skid with rover.parm + rover-skid.parm:

- the anchor: ArduPilot alone, SERVO1/3 = 73/74, a ground station (pymavlink, 255/190) on its SERIAL0;
- the bridge setup: deploy/ardupilot-rover.parm loaded as shipped, `rover-bridge run` with
  params/ardupilot-sitl-skid.toml on its SERIAL0 (TCP), the ground station on the bridge's UDP port.

Each keeps a monitor (250/191) on SERIAL1 that reads the simulator's truth (SIMSTATE, 20 Hz), the outputs
(SERVO_OUTPUT_RAW, 40 Hz), the mode and the texts. Scenarios run in file order on the same two SITLs; each
starts by arming (ArduPilot sets home and clears SmartRTL's path there) and ends disarmed.
The SITLs, their links and the bridge process come from tests/ardupilot_rig.py (shared with
benchmarks/bench_sitl_control.py).
"""

from __future__ import annotations

import itertools
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from ardupilot_rig import BINARY, EARTH_RADIUS_M, PARM, PROFILE, REAL_SITL, Bridge, Link, Sitl
from navmetrics import Point, distance_to_path_m, route_figures

from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.params import load_profile

pytestmark = REAL_SITL

ANCHOR_INSTANCE, BRIDGE_INSTANCE = 5, 6  # ports 5760 + 10 * I (SERIAL0), + 2 (SERIAL1)
MANUAL, HOLD, AUTO, RTL, SMART_RTL = 0, 4, 10, 11, 12
WAYPOINTS: list[Point] = [(10.0, 0.0), (10.0, 10.0), (0.0, 10.0)]
TRIM = 1500
BODY_VELOCITY_MASK = 0b0000_0101_1100_0111
COMMON = "ARMING_CHECK 0\nSERIAL1_PROTOCOL 2\n"
ANCHOR_PARAMS = COMMON  # rover-skid.parm's SERVO1/3 = 73/74
# The bridge profile's wheel encoders (SITL's, with the profile's effective track): see test_ardupilot_sitl.py.
BRIDGE_PARAMS = COMMON + "WENC_TYPE 10\nWENC2_TYPE 10\nWENC_POS_Y 0.8185\nWENC2_POS_Y -0.8185\n"
FIGURES: list[str] = []  # printed at the end of the module (pytest -s)


class Side:
    """One SITL and how its ground station reaches it (directly: the anchor; through the bridge)."""

    def __init__(self, name: str, sitl: Sitl, gcs: Link, bridge: Bridge | None) -> None:
        self.name, self.sitl, self.gcs, self.bridge = name, sitl, gcs, bridge

    def set_mode(self, mode: int) -> None:
        for _ in range(30):
            self.gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, mode)
            if self.sitl.monitor.wait(lambda: self.sitl.mode() == mode, 1.0):
                return
        raise AssertionError(f"{self.name}: mode {mode} refused ({self.sitl.monitor.texts()[-5:]})")

    def arm(self) -> None:
        self.set_mode(MANUAL)
        time.sleep(2.5)  # disarmed, ArduPilot moves home to here once a second (Rover::update_home)
        assert self.gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, 21196) == mavlink.MAV_RESULT_ACCEPTED
        time.sleep(0.5)
        self.sitl.home_here()

    def disarm(self) -> None:
        self.set_mode(MANUAL)
        self.drive(0.0, 0.0)
        self.gcs.wait(self.sitl.stopped, 10.0)
        self.gcs.each = None
        self.release()
        assert self.gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196) == mavlink.MAV_RESULT_ACCEPTED

    def drive(self, v_m_s: float, yaw_rate_cw_rad_s: float) -> None:
        """In MANUAL: the anchor by its sticks (RC1 steering, RC3 throttle overrides), the bridge by velocity
        requests (SET_POSITION_TARGET_LOCAL_NED, body frame), 10 Hz either way."""
        mav = self.gcs.conn.mav
        if self.bridge is None:
            thr, steer = round(TRIM + 500 * v_m_s / 4.0), round(TRIM + 500 * yaw_rate_cw_rad_s / 2.44)
            self.gcs.each = lambda: mav.rc_channels_override_send(1, 1, steer, 65535, thr, 65535, 65535, 65535,
                                                                  65535, 65535)
        else:
            self.gcs.each = lambda: mav.set_position_target_local_ned_send(
                0, 1, 1, mavlink.MAV_FRAME_BODY_NED, BODY_VELOCITY_MASK, 0, 0, 0, v_m_s, 0, 0, 0, 0, 0, 0,
                yaw_rate_cw_rad_s)

    def release(self) -> None:
        self.gcs.each = None
        if self.bridge is None:
            with self.gcs.lock:
                self.gcs.conn.mav.rc_channels_override_send(1, 1, 0, 0, 0, 0, 0, 0, 0, 0)

    def drive_until(self, until: Callable[[], bool], v_m_s: float, yaw_rate_cw_rad_s: float = 0.0) -> None:
        self.drive(v_m_s, yaw_rate_cw_rad_s)
        assert self.gcs.wait(until, 30.0), f"{self.name}: never got there"
        self.drive(0.0, 0.0)
        assert self.gcs.wait(self.sitl.stopped, 10.0)

    def from_home_m(self) -> float:
        return math.hypot(*self.sitl.truth())

    def upload(self, points: list[Point]) -> None:
        items = [(0.0, 0.0), *points]
        since = time.monotonic()
        with self.gcs.lock:
            self.gcs.conn.mav.mission_count_send(1, 1, len(items), mavlink.MAV_MISSION_TYPE_MISSION)
        answered: set[int] = set()
        end = time.monotonic() + 20.0
        while time.monotonic() < end:
            if self.gcs.of("MISSION_ACK", since):
                assert self.gcs.of("MISSION_ACK", since)[-1].type == mavlink.MAV_MISSION_ACCEPTED
                return
            for m in self.gcs.of("MISSION_REQUEST", since) + self.gcs.of("MISSION_REQUEST_INT", since):
                if m.seq not in answered:
                    answered.add(m.seq)
                    lat, lon = self.sitl.lat_lon_e7(*items[m.seq])
                    with self.gcs.lock:
                        self.gcs.conn.mav.mission_item_int_send(1, 1, m.seq, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                                mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0, lat,
                                                                lon, 0, mavlink.MAV_MISSION_TYPE_MISSION)
            time.sleep(0.02)
        raise AssertionError(f"{self.name}: no MISSION_ACK")

    def settle_home(self, since: float) -> float:
        """Distance from home once "Reached destination" is said and the rover has stopped."""
        assert self.sitl.monitor.wait(lambda: "Reached destination" in self.sitl.monitor.texts(since), 60.0), \
            f"{self.name}: {self.sitl.monitor.texts(since)}"
        assert self.sitl.monitor.wait(self.sitl.stopped, 15.0)
        time.sleep(1.0)
        assert self.sitl.stopped()
        return self.from_home_m()


@pytest.fixture(scope="module")
def sides(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Side, Side]]:
    work = tmp_path_factory.mktemp("sitl_nav")
    anchor_sitl = Sitl(BINARY, ANCHOR_INSTANCE, ANCHOR_PARAMS, work / "anchor")
    bridge_sitl = Sitl(BINARY, BRIDGE_INSTANCE, BRIDGE_PARAMS, work / "bridge", (PARM,))
    anchor_gcs = anchor_sitl.gcs_on_serial0()
    bridge = Bridge(bridge_sitl, work)
    anchor, through = Side("anchor", anchor_sitl, anchor_gcs, None), Side("bridge", bridge_sitl, bridge.gcs, bridge)
    try:
        # The shipped file was loaded as it is (comments and all).
        assert bridge_sitl.monitor.get_param("SERVO5_FUNCTION") == 73
        assert bridge_sitl.monitor.get_param("SERVO6_MAX") == 2000
        assert bridge_sitl.monitor.get_param("RC_OVERRIDE_TIME") == 1
        for side in (anchor, through):  # GPS and EKF: AUTO, RTL need a position (about 25-45 s after boot)
            assert side.sitl.monitor.wait(lambda s=side: any("is using GPS" in t for t in s.sitl.monitor.texts()),
                                          120.0), side.sitl.monitor.texts()
        time.sleep(5.0)
        yield anchor, through
    finally:
        print("\n" + "\n".join(FIGURES))
        bridge.close()
        anchor_gcs.close()
        bridge_sitl.close()
        anchor_sitl.close()


def fly_mission(side: Side) -> tuple[Any, list[int]]:
    side.arm()
    side.upload(WAYPOINTS)
    since = time.monotonic()
    side.set_mode(AUTO)
    start = time.monotonic()
    at = side.sitl.truth()
    reached = lambda: [m.seq for m in side.gcs.of("MISSION_ITEM_REACHED", since)]  # noqa: E731
    assert side.gcs.wait(lambda: len(reached()) >= len(WAYPOINTS), 120.0), f"{side.name}: {reached()}"
    done = time.monotonic()
    figures = route_figures(side.sitl.track(start, done), at, WAYPOINTS, done - start)
    side.disarm()
    return figures, reached()


def test_a_mission_through_the_bridge_against_ardupilot_alone(sides: tuple[Side, Side]) -> None:
    anchor, through = sides
    alone, alone_reached = fly_mission(anchor)
    bridged, bridged_reached = fly_mission(through)
    FIGURES.append(f"mission (time | closest WP1/2/3 | xtrack max / rms): alone {alone.row()} ; bridge {bridged.row()}")
    assert alone_reached == [1, 2, 3] and bridged_reached == [1, 2, 3]
    assert max(bridged.closest_m) <= 0.5
    assert bridged.time_s <= 1.1 * alone.time_s
    assert bridged.xtrack_max_m <= alone.xtrack_max_m + 0.3


GUIDED = 15
POSITION_ONLY = 0x0DF8  # SET_POSITION_TARGET: x, y (z) used; velocity, acceleration, yaw ignored


def go_to_8_m(side: Side) -> tuple[float, float, float]:
    """In GUIDED, a target 8 m ahead (BODY_NED) sent once: the time from it to rest (the simulator's position,
    to 1e-7 deg at 20 Hz, unchanged from then on), the distance from the target at rest and the most the rover
    went past it along the way, by the simulator's truth."""
    side.arm()
    side.set_mode(GUIDED)
    time.sleep(1.0)
    sitl = side.sitl
    yaw = float(sitl.monitor.of("SIMSTATE")[-1].yaw)  # radians clockwise from north
    start = sitl.truth()
    un, ue = math.cos(yaw), math.sin(yaw)
    since = time.monotonic()
    with side.gcs.lock:
        side.gcs.conn.mav.set_position_target_local_ned_send(0, 1, 1, mavlink.MAV_FRAME_BODY_NED, POSITION_ONLY,
                                                             8.0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    assert side.gcs.wait(lambda: math.dist(sitl.truth(), start) > 1.0, 10.0), f"{side.name}: it did not go"
    assert side.gcs.wait(sitl.stopped, 30.0), f"{side.name}: it did not stop"
    time.sleep(1.5)
    samples = [(t, m.lat, m.lng) for t, m in list(sitl.monitor.messages) if t >= since and m.get_type() == "SIMSTATE"]
    rest_s = max(t for (t, lat, lng), (_, lat0, lng0) in itertools.pairwise(samples[::-1])
                 if (lat, lng) != (lat0, lng0)) - since
    along = [(n - start[0]) * un + (e - start[1]) * ue for n, e in sitl.track(since)]
    end = sitl.truth()
    error_m = math.dist(end, (start[0] + 8.0 * un, start[1] + 8.0 * ue))
    side.disarm()
    return rest_s, error_m, max(along) - 8.0


def test_a_brisk_go_to_against_ardupilot_alone(sides: tuple[Side, Side]) -> None:
    """Issue 42: within 1.2 x ArduPilot alone's time to rest, <= 0.15 m from the target, <= 0.1 m past it."""
    anchor, through = sides
    alone, bridged = go_to_8_m(anchor), go_to_8_m(through)
    FIGURES.append(f"go-to 8 m (at rest s | error m | past m): alone {alone[0]:.2f} | {alone[1]:.3f} | "
                   f"{alone[2]:+.3f} ; bridge {bridged[0]:.2f} | {bridged[1]:.3f} | {bridged[2]:+.3f}")
    assert bridged[0] <= 1.2 * alone[0]
    assert bridged[1] <= 0.15 and bridged[2] <= 0.1


def rtl(side: Side) -> float:
    side.arm()
    side.drive_until(lambda: side.from_home_m() >= 11.0, 1.5)
    side.release()
    since = time.monotonic()
    side.set_mode(RTL)
    final = side.settle_home(since)
    side.disarm()
    return final


def test_rtl_from_eleven_metres(sides: tuple[Side, Side]) -> None:
    anchor, through = sides
    alone, bridged = rtl(anchor), rtl(through)
    FIGURES.append(f"RTL from 11 m, final distance from home: alone {alone:.2f} m ; bridge {bridged:.2f} m")
    assert bridged <= 1.0


def smart_rtl(side: Side) -> tuple[float, float]:
    side.arm()
    side.drive_until(lambda: side.from_home_m() >= 6.0, 1.5)
    corner = side.sitl.truth()
    t_turn = time.monotonic()
    side.drive_until(lambda: _turned_deg(side, t_turn) >= 85.0, 0.0, 0.8)
    side.drive_until(lambda: math.dist(side.sitl.truth(), corner) >= 6.0, 1.5)
    out = side.sitl.track(0.0)
    side.release()
    since = time.monotonic()
    side.set_mode(SMART_RTL)
    final = side.settle_home(since)
    off_path = max(distance_to_path_m(p, out) for p in side.sitl.track(since))
    side.disarm()
    return final, off_path


def _turned_deg(side: Side, since: float) -> float:
    att = side.sitl.monitor.of("ATTITUDE", since)
    if len(att) < 2:
        return 0.0
    return abs(math.degrees((att[-1].yaw - att[0].yaw + math.pi) % (2 * math.pi) - math.pi))


def test_smart_rtl_along_the_way_it_came(sides: tuple[Side, Side]) -> None:
    anchor, through = sides
    alone, bridged = smart_rtl(anchor), smart_rtl(through)
    FIGURES.append(f"SMART_RTL final / largest distance from the way out: alone {alone[0]:.2f} / {alone[1]:.2f} m ;"
                   f" bridge {bridged[0]:.2f} / {bridged[1]:.2f} m")
    assert bridged[0] <= 1.0 and bridged[1] <= 1.5


@pytest.mark.parametrize(("action", "mode"), [(1, RTL), (2, HOLD)])
def test_a_fence_breach_in_manual_through_the_bridge(sides: tuple[Side, Side], action: int, mode: int) -> None:
    _anchor, side = sides
    # AVOID_ENABLE 0: with its default (3: stop at the fence) ArduPilot's RTL after a circle-fence breach stops
    # about FENCE_MARGIN inside the fence and never gets home, ArduPilot alone as well (measured: 6.6 m from home
    # for 30 s; with AVOID_ENABLE 0 home at 0.37 m).
    for name, value in (("AVOID_ENABLE", 0), ("FENCE_TYPE", 2), ("FENCE_RADIUS", 8), ("FENCE_ACTION", action),
                        ("FENCE_ENABLE", 1)):
        side.sitl.monitor.set_param(name, value)
    try:
        side.arm()
        since = time.monotonic()
        side.drive(1.5, 0.0)  # and keeps asking to drive on
        assert side.sitl.monitor.wait(lambda: side.sitl.mode() == mode, 30.0)
        at_m = side.from_home_m()
        if mode == HOLD:
            time.sleep(3.0)
            assert side.sitl.stopped()
            final = side.from_home_m()
            assert final <= 8.0 + 1.5
        else:
            final = side.settle_home(since)
            assert final <= 1.0
        FIGURES.append(f"fence 8 m, FENCE_ACTION {action}: mode changed at {at_m:.2f} m, ended {final:.2f} m "
                       "from home (bridge, the GCS still asking to drive on)")
    finally:
        side.gcs.each = None
        side.sitl.monitor.set_param("FENCE_ENABLE", 0)
        side.disarm()


def failsafe_said(texts: list[str]) -> bool:
    """ArduPilot's GCS failsafe says "GCS Failsafe" or, acted on in the radio check, "Radio Failsafe"."""
    return any(t in ("GCS Failsafe", "Radio Failsafe") for t in texts)


def test_ardupilots_gcs_failsafe_counts_overrides_as_the_gcs(sides: tuple[Side, Side]) -> None:
    """The hole, on ArduPilot alone: the GCS's heartbeats stop, its overrides (MAV_GCS_SYSID) go on: no failsafe;
    the overrides stop too: the failsafe fires FS_GCS_TIMEOUT + FS_TIMEOUT later."""
    anchor, _through = sides
    mon = anchor.sitl.monitor
    for name, value in (("FS_GCS_ENABLE", 1), ("FS_ACTION", 2)):
        mon.set_param(name, value)
    try:
        anchor.arm()
        anchor.drive(0.0, 0.0)  # neutral sticks, as the bridge's idle overrides
        anchor.gcs.beating = False
        since = time.monotonic()
        time.sleep(15.0)
        masked = not failsafe_said(mon.texts(since))
        anchor.release()
        stopped_at = time.monotonic()
        assert mon.wait(lambda: failsafe_said(mon.texts(since)), 15.0)
        fired_s = next(t for t, m in list(mon.messages) if t > since and m.get_type() == "STATUSTEXT"
                   and failsafe_said([m.text])) - stopped_at
        FIGURES.append(f"ArduPilot alone, heartbeats stopped, overrides from 255 on for 15 s: failsafe "
                       f"{'never fired' if masked else 'FIRED'}; overrides stopped: it fired {fired_s:.1f} s later")
        assert masked and fired_s <= 5.0 + 1.5 + 0.5
    finally:
        anchor.gcs.beating = True
        mon.set_param("FS_GCS_ENABLE", 0)
        time.sleep(1.0)
        anchor.disarm()


@pytest.mark.parametrize(("start", "fs_action", "expect"), [(MANUAL, 2, HOLD), (AUTO, 1, RTL)])
def test_a_silent_gcs_lets_ardupilots_failsafe_act_through_the_bridge(sides: tuple[Side, Side], start: int,
                                                                      fs_action: int, expect: int) -> None:
    _anchor, side = sides
    mon = side.sitl.monitor
    for name, value in (("FS_GCS_ENABLE", 1), ("FS_ACTION", fs_action)):
        mon.set_param(name, value)
    try:
        side.arm()
        if start == AUTO:
            side.upload(WAYPOINTS)
        side.set_mode(start)
        time.sleep(2.0)
        side.gcs.beating = False
        quiet = time.monotonic()
        last_beat = quiet - 1.0  # its last heartbeat went out within the second before
        assert mon.wait(lambda: side.sitl.mode() == expect, 30.0), mon.texts(quiet)
        # ArduPilot queues the text and changes the mode at once: a HEARTBEAT may show the mode first.
        assert mon.wait(lambda: failsafe_said(mon.texts(quiet)), 5.0), mon.texts(quiet)
        fired = [t for t, m in list(mon.messages) if t > quiet and m.get_type() == "STATUSTEXT"
                 and failsafe_said([m.text])]
        final = side.settle_home(quiet) if expect == RTL else math.nan
        FIGURES.append(f"bridge, GCS silent in mode {start} (FS_GCS_ENABLE 1, FS_ACTION {fs_action}): 'GCS Failsafe' "
                       f"{fired[0] - quiet:.1f} s after the GCS went quiet (last heartbeat <= 1 s before), mode "
                       f"{side.sitl.mode()}" + (f", home at {final:.2f} m" if expect == RTL else ""))
        assert fired[0] - last_beat <= 2 * 5.0 + 1.5 + 1.5
        if expect == RTL:
            assert final <= 1.0
    finally:
        side.gcs.beating = True
        mon.set_param("FS_GCS_ENABLE", 0)
        time.sleep(1.5)
        side.disarm()


# -- every stop path in AUTO (the SIGTERM one just below; heartbeat lost and a stale demand at the end of the file,
#    through a proxy, once the shared bridge is gone) -------------------------------------------------------------


def in_auto_at_speed(side: Side) -> None:
    side.arm()
    side.upload(WAYPOINTS)
    side.set_mode(AUTO)
    assert side.sitl.monitor.wait(lambda: side.sitl._speed_from_track() > 1.5, 20.0)


def outputs_at_trim(mon: Link, since: float) -> float | None:
    """When the monitor first saw outputs 1 and 3 (the motors) both at trim after `since`."""
    return next((t for t, m in list(mon.messages) if t > since and m.get_type() == "SERVO_OUTPUT_RAW"
                 and m.servo1_raw == TRIM and m.servo3_raw == TRIM), None)


def stopping(side: Side, since: float) -> tuple[float, float]:
    """(seconds from `since` until the rover stood still, metres it went meanwhile), from the simulator's truth."""
    assert side.sitl.monitor.wait(side.sitl.stopped, 10.0)
    time.sleep(0.5)
    assert side.sitl.origin_deg is not None
    lat0, lon0 = side.sitl.origin_deg
    track = [(t, (math.radians(m.lat * 1e-7 - lat0) * EARTH_RADIUS_M,
                  math.radians(m.lng * 1e-7 - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))))
             for t, m in list(side.sitl.monitor.messages) if t >= since and m.get_type() == "SIMSTATE"]
    final = track[-1][1]
    still = next(t for t, p in track if math.dist(p, final) < 0.02)
    return still - since, sum(math.dist(a[1], b[1]) for a, b in itertools.pairwise(track))


def test_a_disarm_in_auto_stops_the_wheels_through_the_bridge(sides: tuple[Side, Side]) -> None:
    """A GCS disarms mid-mission (forced: 21196): ArduPilot's demand (SERVO5/6) goes to trim at once, the bridge
    follows it through its limiter to trim on the motor outputs 1/3, the rover stops; ArduPilot's words reach the
    GCS through the bridge, and the bridge's own (the shipped require_armed: neutral at the heartbeat saying so)."""
    _anchor, side = sides
    p = load_profile(PROFILE)
    mon = side.sitl.monitor
    in_auto_at_speed(side)
    t0 = time.monotonic()
    assert side.gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196) == mavlink.MAV_RESULT_ACCEPTED
    assert mon.wait(lambda: outputs_at_trim(mon, t0) is not None, 5.0)
    at_trim = outputs_at_trim(mon, t0)
    assert at_trim is not None
    stop_s, stop_m = stopping(side, t0)
    ramp = [m.servo1_raw for m in mon.of("SERVO_OUTPUT_RAW", t0)]
    ramp = ramp[:ramp.index(TRIM) + 1]
    ramp = ramp[ramp.index(max(ramp)):]  # from where the disarm met it (AUTO may still have been speeding up)
    demand = [(m.servo5_raw, m.servo6_raw) for m in mon.of("SERVO_OUTPUT_RAW", at_trim)]
    said = [t for t in side.gcs.texts(t0) if "isarm" in t]
    # On the monitor's clock: ArduPilot said it disarmed, then the motor outputs began to fall.
    t_dis = next(t for t, m in list(mon.messages) if t > t0 and m.get_type() == "STATUSTEXT" and "isarm" in m.text)
    outs = [(t, m.servo1_raw) for t, m in list(mon.messages) if t >= t_dis and m.get_type() == "SERVO_OUTPUT_RAW"]
    first_down = next(b[0] for a, b in itertools.pairwise(outs) if b[1] < a[1])
    # require_armed: neutral at once from the first heartbeat that says disarmed (the braking may end earlier)
    t_beat = next(t for t, m in list(mon.messages) if t > t_dis and m.get_type() == "HEARTBEAT"
                  and m.get_srcSystem() == 1 and not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
    v0 = (ramp[0] - TRIM) / 500.0 * p.robot.max_wheel_rad_s * p.robot.wheel_radius_m
    trim_s = at_trim - t0
    FIGURES.append(f"disarm in AUTO at {v0:.2f} m/s (bridge): outputs 1/3 at trim {1000 * trim_s:.0f} ms after the "
                   f"command, falling {1000 * (first_down - t_dis):.0f} ms after ArduPilot said it disarmed; rover "
                   f"still {stop_s:.2f} s / {stop_m:.2f} m after; GCS got {said}")
    side.set_mode(MANUAL)
    period_s = 1.0 / p.command.rate_hz
    # Braked at the limiter's deceleration, not stepped: no faster than that, and not much slower (the demand
    # arrives every 1/[demand] rate_hz; the links and a loaded machine add a little).
    assert all(b <= a for a, b in itertools.pairwise(ramp))
    assert first_down - t_dis <= 1.0 / p.demand.rate_hz + period_s + 0.1  # the trim demand followed at once
    assert min(v0 / p.limits.max_linear_decel_m_s2 - 2 * period_s, t_beat - t0 - 0.1) <= trim_s
    assert trim_s <= 1.0 / p.demand.rate_hz + v0 / p.limits.max_linear_decel_m_s2 + 2 * period_s + 0.25
    assert demand and all(d == (TRIM, TRIM) for d in demand)  # ArduPilot's own demand: trim, disarmed
    assert any(t.startswith("RB: autopilot disarmed") for t in said) and stop_m <= 3.0


def test_sigterm_in_auto_trims_the_outputs(sides: tuple[Side, Side]) -> None:
    _anchor, side = sides
    assert side.bridge is not None
    side.arm()
    side.upload(WAYPOINTS)
    side.set_mode(AUTO)
    mon = side.sitl.monitor
    assert mon.wait(lambda: side.sitl._speed_from_track() > 1.0, 20.0)
    t0 = side.bridge.stop()
    at_trim = lambda: [t for t, m in list(mon.messages) if t > t0 and m.get_type() == "SERVO_OUTPUT_RAW"  # noqa: E731
                       and m.servo1_raw == TRIM and m.servo3_raw == TRIM]
    assert mon.wait(lambda: bool(at_trim()), 5.0)
    trim_s = at_trim()[0] - t0
    log = side.bridge.log_path.read_text()
    FIGURES.append(f"SIGTERM in AUTO at speed: outputs 1/3 at trim {1000 * trim_s:.0f} ms later; "
                   f"{'stop confirmed' if 'stop confirmed' in log else 'NOT confirmed'}")
    assert trim_s < 0.25 and "stop confirmed" in log
    # The bridge is gone: AUTO's demand reaches nothing, the rover stops and stays (passthrough at the RC input).
    time.sleep(2.0)
    assert side.sitl.stopped()
    mon.command(mavlink.MAV_CMD_DO_SET_MODE, 1, MANUAL)  # the bridge is gone: the monitor tidies up
    mon.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)


class Proxy:
    """A TCP proxy between the bridge and the SITL's SERIAL0: whole MAVLink frames forwarded both ways, except
    those from the autopilot whose id is in `drop` (None: every frame). Keeps when it last forwarded each message
    id to the bridge, and every RC_CHANNELS_OVERRIDE the bridge sent (time, channel 1, channel 3)."""

    def __init__(self, serial0: int) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.serial0 = serial0
        self.drop: frozenset[int] | None = frozenset()
        self.forwarded: dict[int, float] = {}
        self.overrides: list[tuple[float, int, int]] = []
        self.alive = True
        self.socks: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        bridge, _ = self.server.accept()
        autopilot = socket.create_connection(("127.0.0.1", self.serial0))
        self.socks = [bridge, autopilot]
        threading.Thread(target=self._pump, args=(autopilot, bridge, True), daemon=True).start()
        threading.Thread(target=self._pump, args=(bridge, autopilot, False), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket, to_bridge: bool) -> None:
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        while self.alive:
            try:
                data = src.recv(65536)
            except OSError:
                return
            if not data:
                return
            out = bytearray()
            now = time.monotonic()
            for m in parser.parse_buffer(data) or []:
                if m.get_type() == "BAD_DATA":
                    continue
                mid = m.get_msgId()
                if to_bridge:
                    drop = self.drop
                    if drop is None or mid in drop:
                        continue
                    self.forwarded[mid] = now
                elif m.get_type() == "RC_CHANNELS_OVERRIDE":
                    self.overrides.append((now, m.chan1_raw, m.chan3_raw))
                out += m.get_msgbuf()
            try:
                dst.sendall(out)
            except OSError:
                return

    def close(self) -> None:
        self.alive = False
        for sock in (*self.socks, self.server):
            sock.close()


def proxied(side: Side, workdir: Path) -> tuple[Proxy, Side]:
    """The bridge again, now through a Proxy (the shared bridge, if still running, stopped first: SERIAL0 serves
    one client)."""
    if side.bridge is not None and side.bridge.proc.poll() is None:
        side.bridge.stop()
    proxy = Proxy(side.sitl.serial0)
    bridge = Bridge(side.sitl, workdir, autopilot=f"tcp:127.0.0.1:{proxy.port}")
    return proxy, Side("bridge via proxy", side.sitl, bridge.gcs, bridge)


def text_at(side: Side, text: str, since: float) -> float | None:
    return next((t for t, m in list(side.gcs.messages) if t >= since and m.get_type() == "STATUSTEXT"
                 and m.text == text), None)


def tidy_up(side: Side, proxy: Proxy) -> None:
    """Back to MANUAL, disarmed, the bridge and the proxy gone (the monitor does it: the bridge may be neutral)."""
    mon = side.sitl.monitor
    mon.command(mavlink.MAV_CMD_DO_SET_MODE, 1, MANUAL)
    mon.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)
    assert side.bridge is not None
    if side.bridge.proc.poll() is None:
        side.bridge.stop()
    side.bridge.close()
    proxy.close()
    time.sleep(1.0)


@pytest.mark.parametrize("dropped", ["heartbeat", "everything"])
def test_the_autopilots_heartbeat_lost_in_auto_through_a_proxy(sides: tuple[Side, Side], dropped: str,
                                                               tmp_path: Path) -> None:
    """From the bridge's view the autopilot's HEARTBEAT stops (alone, or with everything else: a link that fails
    one way). The bridge says the heartbeat lost within safety.heartbeat_timeout_s of the last one it got, and from
    then on sends neutral overrides every period (it does not release them: ArduPilot's passthrough outputs would
    follow the radio), so ArduPilot's motor outputs sit at trim because of the bridge, not RC_OVERRIDE_TIME."""
    _anchor, shared = sides
    p = load_profile(PROFILE)
    proxy, side = proxied(shared, tmp_path)
    mon = side.sitl.monitor
    try:
        in_auto_at_speed(side)
        t0 = time.monotonic()
        proxy.drop = frozenset({mavlink.MAVLINK_MSG_ID_HEARTBEAT}) if dropped == "heartbeat" else None
        last_hb = proxy.forwarded[mavlink.MAVLINK_MSG_ID_HEARTBEAT]
        lost_text = "RB: autopilot heartbeat lost, neutral"
        assert side.gcs.wait(lambda: text_at(side, lost_text, t0) is not None, p.safety.heartbeat_timeout_s + 3.0)
        lost = text_at(side, lost_text, t0)
        assert lost is not None
        braking = text_at(side, "RB: no demand from the autopilot, braking", t0)
        time.sleep(2.0)
        end = time.monotonic()
        after = [o for o in proxy.overrides if lost + 0.1 <= o[0] <= end]
        at_trim = outputs_at_trim(mon, t0)
        assert at_trim is not None
        stop_s, stop_m = stopping(side, t0)
        demand = [m.servo5_raw for m in mon.of("SERVO_OUTPUT_RAW", lost + 0.1)]
        FIGURES.append(f"heartbeat lost in AUTO (proxy drops {dropped} to the bridge): said "
                       f"{1000 * (lost - last_hb):.0f} ms after the last HEARTBEAT forwarded"
                       + (f", braking for the stale demand {1000 * (braking - t0):.0f} ms after the drop" if braking
                          else "")
                       + f"; outputs 1/3 at trim {1000 * (at_trim - t0):.0f} ms after the drop; "
                       f"{len(after) / (end - lost - 0.1):.1f} neutral overrides/s kept coming; "
                       f"rover still {stop_s:.2f} s / {stop_m:.2f} m after the drop")
        timeout = p.safety.heartbeat_timeout_s
        assert timeout - 0.1 <= lost - last_hb <= timeout + 0.5
        assert after and all(o[1:] == (TRIM, TRIM) for o in after)  # neutral, refreshed: not released
        assert len(after) >= 0.8 * p.command.rate_hz * (end - lost - 0.1)
        if dropped == "heartbeat":
            assert braking is None and any(abs(d - TRIM) > 100 for d in demand)  # the demand came, saying drive
            assert at_trim - lost <= 0.25  # neutral at once: no ramp
        else:
            assert braking is not None and braking - t0 <= p.demand.timeout_s + 0.25  # the stale demand first
    finally:
        tidy_up(side, proxy)


def test_a_stale_demand_in_auto_brakes_through_a_proxy(sides: tuple[Side, Side], tmp_path: Path) -> None:
    """SERVO_OUTPUT_RAW stops reaching the bridge while HEARTBEAT goes on (the proxy drops id 36): [demand]
    timeout_s after the last one the bridge brakes, its overrides ramping to trim at the limiter's deceleration;
    ArduPilot still asks to drive. (A GCS's SET_MESSAGE_INTERVAL -1 through the bridge does the same until the
    bridge asks for the stream again: tests/test_stop_paths_e2e.py; the monitor's own -1 would change only its
    own link's rate, SERIAL1.)"""
    _anchor, shared = sides
    p = load_profile(PROFILE)
    proxy, side = proxied(shared, tmp_path)
    mon = side.sitl.monitor
    period_s = 1.0 / p.command.rate_hz
    try:
        in_auto_at_speed(side)
        t0 = time.monotonic()
        proxy.drop = frozenset({mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW})
        last = proxy.forwarded[mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW]
        braking_text = "RB: no demand from the autopilot, braking"
        assert side.gcs.wait(lambda: text_at(side, braking_text, t0) is not None, 3.0)
        braking = text_at(side, braking_text, t0)
        assert braking is not None
        assert side.gcs.wait(lambda: any(o[0] > braking and o[1:] == (TRIM, TRIM) for o in proxy.overrides), 3.0)
        held = [o for o in proxy.overrides if o[0] < braking - 0.01][-1]
        ramp = [o for o in proxy.overrides if o[0] >= braking - 0.01]
        ramp = [held, *ramp[:next(i for i, o in enumerate(ramp) if o[1:] == (TRIM, TRIM)) + 1]]
        took = ramp[-1][0] - ramp[0][0]
        v0 = (max(held[1], held[2]) - TRIM) / 500.0 * p.robot.max_wheel_rad_s * p.robot.wheel_radius_m
        largest = max(max(abs(a[1] - b[1]), abs(a[2] - b[2])) for a, b in itertools.pairwise(ramp))
        stop_s, stop_m = stopping(side, t0)
        FIGURES.append(f"stale demand in AUTO (proxy drops SERVO_OUTPUT_RAW): braking {1000 * (braking - last):.0f} ms "
                       f"after the last one forwarded; {v0:.2f} m/s to trim in {1000 * took:.0f} ms over "
                       f"{len(ramp) - 1} overrides (largest step {largest} us); rover still {stop_s:.2f} s / "
                       f"{stop_m:.2f} m after the drop")
        assert p.demand.timeout_s - 0.05 <= braking - last <= p.demand.timeout_s + 0.25
        assert all(b[1] <= a[1] and b[2] <= a[2] for a, b in itertools.pairwise(ramp))  # never back up
        # One period of the limits per override (linear and angular deceleration, as tests/test_drivers.py).
        lim, robot = p.limits, p.robot
        wheel = (lim.max_linear_decel_m_s2 + lim.max_angular_accel_rad_s2 * robot.track_width_m / 2.0) * period_s
        assert largest <= 500.0 * wheel / robot.wheel_radius_m / robot.max_wheel_rad_s + 1.0
        assert took >= v0 / lim.max_linear_decel_m_s2 - 2 * period_s  # a ramp, not a step
        assert any(abs(m.servo5_raw - TRIM) > 100 for m in mon.of("SERVO_OUTPUT_RAW", braking))  # it still drives
    finally:
        tidy_up(side, proxy)


def test_auto_to_manual_then_hold_mid_mission_through_a_proxy(sides: tuple[Side, Side], tmp_path: Path) -> None:
    """Mid-mission the GCS switches to MANUAL while it streams a request (0.5 m/s ahead, refused in AUTO): the
    bridge's overrides (every one, seen by the proxy) go from ArduPilot's demand to the request without a step
    beyond one period of the limiter's limits, and the rover drives at the request; then HOLD brakes it to a
    stop and the overrides stay at trim."""
    _anchor, shared = sides
    p = load_profile(PROFILE)
    proxy, side = proxied(shared, tmp_path)
    period_s = 1.0 / p.command.rate_hz
    lim, robot = p.limits, p.robot
    dv = max(lim.max_linear_accel_m_s2, lim.max_linear_decel_m_s2) * period_s
    dw = lim.max_angular_accel_rad_s2 * period_s
    step_us = 500.0 * (dv + dw * robot.track_width_m / 2.0) / robot.wheel_radius_m / robot.max_wheel_rad_s + 1.0
    try:
        in_auto_at_speed(side)
        side.drive(0.5, 0.0)
        time.sleep(1.0)
        t0 = time.monotonic()
        v_auto = side.sitl._speed_from_track()
        side.set_mode(MANUAL)
        assert side.sitl.monitor.wait(lambda: abs(side.sitl._speed_from_track() - 0.5) < 0.1, 10.0)
        time.sleep(1.0)
        v_manual = side.sitl._speed_from_track()
        handover = [o for o in proxy.overrides if o[0] >= t0 - 0.5]
        worst = max(max(abs(b[1] - a[1]), abs(b[2] - a[2])) for a, b in itertools.pairwise(handover))
        t1 = time.monotonic()
        side.set_mode(HOLD)
        stop_s, stop_m = stopping(side, t1)
        said = side.gcs.texts(t0)
        held = [o[1:] for o in proxy.overrides if o[0] >= t1 + stop_s]
        FIGURES.append(f"AUTO -> MANUAL at {v_auto:.2f} m/s, the GCS asking 0.5 m/s: largest step between two of the "
                       f"bridge's overrides {worst} us (limiter bound {step_us:.0f} us), then {v_manual:.2f} m/s; "
                       f"-> HOLD: still {stop_s:.2f} s / {stop_m:.2f} m after")
    finally:
        tidy_up(side, proxy)
    assert "RB: MANUAL: GCS requests drive" in said and "RB: autopilot in HOLD, braking, then neutral" in said
    assert worst <= step_us and abs(v_manual - 0.5) < 0.1
    assert held and all(h == (TRIM, TRIM) for h in held) and stop_m <= 3.0
