"""Going to a point, the pure parts: how targets are read, where they land in the estimate's frame, the
track fit that ties the frames, and the controller driving a unicycle through the real limiter."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from navsupport import FakeSource, lat_lon

from rover_bridge.command.navigation import (
    FIT_MAX_SIGMA_RAD,
    GotoController,
    NavTarget,
    Unresolved,
    fit_track,
    north_anchor,
    resolve,
)
from rover_bridge.command.targets import (
    ACCELERATION_IGNORED,
    ALTITUDE_IGNORED,
    GlobalTarget,
    LocalTarget,
    Refused,
    SpeedChange,
    changes_mode,
    decode_command,
    decode_mission_item,
    decode_position_target,
    uses_position,
)
from rover_bridge.frames import LocalAnchor
from rover_bridge.kinematics import Twist2D
from rover_bridge.limits import TwistLimiter, TwistLimits
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.odometry import Pose2D, wrap_angle
from rover_bridge.params import LimitsParams, NavigationParams

POS = 0x0DF8  # x, y, z used; velocity, acceleration, yaw ignored (yaw rate ignored too)
POS_YAW = POS & ~1024
POS_VEL = POS & ~(8 | 16)
NAV = NavigationParams()
LIMITS = LimitsParams()


def local(frame: int, x: float, y: float, mask: int = POS, **kw: float) -> mavlink.MAVLink_message:
    values = dict(vx=0.0, vy=0.0, yaw=0.0)
    values.update(kw)
    return mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, frame, mask, x, y, 0.0, values["vx"], values["vy"], 0.0, 0.0, 0.0, 0.0, values["yaw"], 0.0)


def global_target(lat: float, lon: float, frame: int = 6, mask: int = POS) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_set_position_target_global_int_message(
        0, 1, 1, frame, mask, round(lat * 1e7), round(lon * 1e7), 10.0, 0, 0, 0, 0, 0, 0, 0, 0)


def item_int(lat: float, lon: float, command: int = 16, frame: int = 6) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_mission_item_int_message(1, 1, 0, frame, command, 2, 0, 0, 0, 0, 0,
                                                    round(lat * 1e7), round(lon * 1e7), 0.0, 0)


def command(cmd: int, kind: str = "int", p1: float = 0.0, p2: float = 0.0, p4: float = 0.0, x: int = 0,
            y: int = 0, frame: int = 5) -> mavlink.MAVLink_message:
    if kind == "int":
        return mavlink.MAVLink_command_int_message(1, 1, frame, cmd, 0, 0, p1, p2, 0.0, p4, x, y, 0.0)
    return mavlink.MAVLink_command_long_message(1, 1, cmd, 0, p1, p2, 0.0, p4, x * 1e-7, y * 1e-7, 0.0)


# ---------------------------------------------------------------- reading targets

@pytest.mark.parametrize(("frame", "kind"), [(1, "local"), (7, "offset"), (8, "body"), (9, "body")])
def test_each_local_frame_reads_as_arducopter_rover_reads_it(frame: int, kind: str) -> None:
    decoded = decode_position_target(local(frame, 2.0, -1.0))
    assert decoded == LocalTarget(kind, 2.0, -1.0)


@pytest.mark.parametrize("frame", [12, 20, 2, 13])
def test_frames_rover_ignores_for_positions_are_refused(frame: int) -> None:
    # ArduPilot's handle_set_position_target_local_ned takes 1, 7, 8, 9 only (LOCAL_FRD/BODY_FRD: ignored).
    assert decode_position_target(local(frame, 2.0, 0.0)) == Refused("unsupported_frame")


def test_position_is_used_only_with_x_and_y_both_used() -> None:
    assert uses_position(local(1, 1.0, 1.0))
    assert not uses_position(local(1, 1.0, 1.0, mask=POS | 2))  # y ignored: Rover's POS_IGNORE is either bit
    assert not uses_position(local(1, 1.0, 1.0, mask=POS | 1))


def test_yaw_velocity_and_acceleration_of_a_target() -> None:
    decoded = decode_position_target(local(1, 3.0, 4.0, mask=POS_YAW, yaw=1.5))
    assert isinstance(decoded, LocalTarget) and decoded.yaw_cw_rad == pytest.approx(1.5)
    decoded = decode_position_target(local(1, 3.0, 4.0, mask=POS_VEL, vx=0.3, vy=0.4))
    assert isinstance(decoded, LocalTarget) and decoded.speed_m_s == pytest.approx(0.5)
    decoded = decode_position_target(local(1, 3.0, 4.0, mask=POS & ~64))
    assert isinstance(decoded, LocalTarget) and ACCELERATION_IGNORED in decoded.notes


@pytest.mark.parametrize("values", [dict(x=math.nan), dict(x=2e5), dict(yaw=7.0, mask=POS_YAW),
                                    dict(vx=math.inf, mask=POS_VEL), dict(vx=500.0, mask=POS_VEL)])
def test_garbage_values_refuse_the_target(values: dict[str, float]) -> None:
    x = values.pop("x", 1.0)
    mask = int(values.pop("mask", POS))
    assert decode_position_target(local(1, x, 1.0, mask=mask, **values)) == Refused("bad_value")


@pytest.mark.parametrize("frame", [0, 3, 5, 6, 10, 11])
def test_global_frames_ignore_altitude(frame: int) -> None:
    decoded = decode_position_target(global_target(-35.0, 149.0, frame))
    assert isinstance(decoded, GlobalTarget) and ALTITUDE_IGNORED in decoded.notes
    assert (decoded.lat_deg, decoded.lon_deg) == pytest.approx((-35.0, 149.0))


def test_global_target_in_another_frame_or_off_the_earth_is_refused() -> None:
    assert decode_position_target(global_target(-35.0, 149.0, 1)) == Refused("unsupported_frame")
    assert decode_position_target(global_target(95.0, 149.0)) == Refused("bad_value")


def test_guided_mission_item_answers_with_ardupilots_codes() -> None:
    assert isinstance(decode_mission_item(item_int(-35.0, 149.0)), GlobalTarget)
    assert decode_mission_item(item_int(-35.0, 149.0, command=17)).mission_result == \
        mavlink.MAV_MISSION_UNSUPPORTED  # type: ignore[union-attr]
    assert decode_mission_item(item_int(-35.0, 149.0, frame=1)).mission_result == \
        mavlink.MAV_MISSION_UNSUPPORTED_FRAME  # type: ignore[union-attr]
    assert decode_mission_item(item_int(91.0, 149.0)).mission_result == \
        mavlink.MAV_MISSION_INVALID_PARAM5_X  # type: ignore[union-attr]
    assert decode_mission_item(item_int(10.0, 181.0)).mission_result == \
        mavlink.MAV_MISSION_INVALID_PARAM6_Y  # type: ignore[union-attr]
    legacy = mavlink.MAVLink_mission_item_message(1, 1, 0, 3, 16, 2, 0, 0, 0, 0, 0, -35.5, 149.5, 0.0, 0)
    decoded = decode_mission_item(legacy)
    assert isinstance(decoded, GlobalTarget) and (decoded.lat_deg, decoded.lon_deg) == pytest.approx((-35.5, 149.5))


def test_do_reposition_over_command_int_only_with_speed_and_yaw() -> None:
    rep = mavlink.MAV_CMD_DO_REPOSITION
    decoded = decode_command(command(rep, p1=0.7, p4=math.pi / 2, x=-353632610, y=1491652300))
    assert isinstance(decoded, GlobalTarget)
    assert decoded.speed_m_s == pytest.approx(0.7) and decoded.yaw_cw_rad == pytest.approx(math.pi / 2)
    defaults = decode_command(command(rep, p1=-1.0, p4=math.nan, x=-353632610, y=1491652300))
    assert isinstance(defaults, GlobalTarget) and defaults.speed_m_s is None and defaults.yaw_cw_rad is None
    # ArduPilot: float lat/lon in COMMAND_LONG lose a metre, so DO_REPOSITION there is UNSUPPORTED.
    long = decode_command(command(rep, "long", x=-353632610, y=1491652300))
    assert isinstance(long, Refused) and long.command_result == mavlink.MAV_RESULT_UNSUPPORTED
    assert isinstance(decode_command(command(rep)), Refused)  # 0, 0: DENIED, as Rover
    assert changes_mode(command(rep, p2=1.0)) and not changes_mode(command(rep, p2=0.0))
    assert decode_command(command(mavlink.MAV_CMD_DO_SET_MODE)) is None


def test_do_change_speed() -> None:
    speed = mavlink.MAV_CMD_DO_CHANGE_SPEED
    assert decode_command(command(speed, "long", p1=1.0, p2=0.4)) == SpeedChange(0.4)
    assert decode_command(command(speed, p1=0.0, p2=0.4)) == SpeedChange(0.4)  # airspeed: taken as ground speed
    assert decode_command(command(speed, "long", p1=1.0, p2=-2.0)) == SpeedChange(None, reset=True)
    assert decode_command(command(speed, "long", p1=1.0, p2=-1.0)) == SpeedChange(None)
    assert isinstance(decode_command(command(speed, "long", p1=2.0, p2=0.4)), Refused)  # climb speed
    assert isinstance(decode_command(command(speed, "long", p1=1.0, p2=0.01)), Refused)


# ---------------------------------------------------------------- where targets land

def moved_source(rotation_deg: float = 30.0) -> FakeSource:
    """A rover 2 m forward and 1 m left of its start, facing 90 deg left of its start heading."""
    return FakeSource(pose=Pose2D(2.0, 1.0, math.pi / 2), north_rotation_cw_rad=math.radians(rotation_deg),
                      north0_m=10.0, east0_m=-5.0)


def resolved(target: LocalTarget | GlobalTarget, source: FakeSource, **kw: object) -> NavTarget:
    out = resolve(target, source, source.now_s, NAV, LIMITS.max_linear_m_s, **kw)  # type: ignore[arg-type]
    assert isinstance(out, NavTarget), out
    return out


def ned_of(source: FakeSource, t: NavTarget) -> tuple[float, float]:
    ned = source.anchor.to_ned(t.x_m, t.y_m, 0.0)
    return ned.north_m, ned.east_m


def test_body_offset_is_forward_and_right_of_the_rover() -> None:
    source = moved_source()
    t = resolved(LocalTarget("body", 3.0, 1.0), source)
    # Facing +y (left) of the start frame: 3 m forward is +3 y, 1 m right is +1 x.
    assert (t.x_m, t.y_m) == pytest.approx((3.0, 4.0))
    assert (t.start_x_m, t.start_y_m) == (2.0, 1.0)


def test_offset_and_local_targets_land_in_the_autopilots_ned() -> None:
    source = moved_source()
    source.fix(0.0)
    here = source.ned()
    t = resolved(LocalTarget("offset", 3.0, -2.0), source)
    assert ned_of(source, t) == pytest.approx((here[0] + 3.0, here[1] - 2.0))
    t = resolved(LocalTarget("local", 12.0, -1.0), source)
    assert t.frame_note == "autopilot"
    assert ned_of(source, t) == pytest.approx((12.0, -1.0))


def test_local_target_without_the_autopilots_position_is_from_the_start_pose_north_up() -> None:
    source = moved_source()
    source.fixes_on = False
    t = resolved(LocalTarget("local", 4.0, 0.0), source)
    assert t.frame_note == "start"
    # 4 m north of the start pose, which faces 30 deg east of north: forward 4 cos 30, right 4 sin 30 ... turned back.
    assert (t.x_m, t.y_m) == pytest.approx((4.0 * math.cos(math.radians(30)), 4.0 * math.sin(math.radians(30))))


def test_global_target_lands_on_its_point() -> None:
    source = moved_source()
    lat, lon = lat_lon(*(a + b for a, b in zip(source.ned(), (30.0, -40.0), strict=True)))
    t = resolved(GlobalTarget(lat, lon), source)
    north, east = ned_of(source, t)
    assert (north - source.ned()[0], east - source.ned()[1]) == pytest.approx((30.0, -40.0), abs=0.01)
    assert t.global_target is not None


def test_yaw_on_arrival_is_taken_in_the_targets_frame() -> None:
    source = moved_source()
    t = resolved(LocalTarget("offset", 1.0, 0.0, yaw_cw_rad=math.radians(90)), source)  # face east
    assert t.yaw_rad is not None
    assert source.anchor.to_ned(0, 0, t.yaw_rad).yaw_cw_rad == pytest.approx(math.radians(90))
    t = resolved(LocalTarget("body", 1.0, 0.0, yaw_cw_rad=math.radians(90)), source)  # 90 right of now
    assert t.yaw_rad == pytest.approx(0.0)


def test_cruise_speed_target_then_change_speed_then_default_within_limits() -> None:
    source = moved_source()
    assert resolved(LocalTarget("offset", 1, 0, speed_m_s=0.3), source, cruise_m_s=0.6).speed_m_s == 0.3
    assert resolved(LocalTarget("offset", 1, 0), source, cruise_m_s=0.6).speed_m_s == 0.6
    assert resolved(LocalTarget("offset", 1, 0), source).speed_m_s == NAV.speed_m_s
    assert resolved(LocalTarget("offset", 1, 0, speed_m_s=9.0), source).speed_m_s == LIMITS.max_linear_m_s


def test_unresolvable_targets_say_why() -> None:
    source = moved_source()
    far = resolve(LocalTarget("offset", 150.0, 150.0), source, 0.0, NAV, 1.0)
    assert far == Unresolved("212 m away, max 200 m", temporary=False)
    source.gps_on = False
    assert resolve(GlobalTarget(-35.0, 149.0), source, 0.0, NAV, 1.0) == Unresolved("no GPS (GLOBAL_POSITION_INT)")
    source.gps_on, source.gps_age_s = True, NAV.gps_timeout_s + 0.1
    assert resolve(GlobalTarget(-35.0, 149.0), source, 0.0, NAV, 1.0) == Unresolved("no GPS (GLOBAL_POSITION_INT)")
    source.has_heading, source.fixes_on = False, False
    assert resolve(LocalTarget("offset", 1, 0), source, 0.0, NAV, 1.0) == Unresolved("no heading (ATTITUDE)")
    assert isinstance(resolve(LocalTarget("body", 1, 0), source, 0.0, NAV, 1.0), NavTarget)  # needs no north
    source.fresh = False
    assert resolve(LocalTarget("body", 1, 0), source, 0.0, NAV, 1.0) == Unresolved("no position estimate")


# ---------------------------------------------------------------- the track fit

@settings(max_examples=60, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-50, 50), st.floats(-50, 50), st.integers(0, 2**31))
def test_track_fit_recovers_the_frames_rotation(rotation: float, north0: float, east0: float, seed: int) -> None:
    import random

    rng = random.Random(seed)
    source = FakeSource(north_rotation_cw_rad=rotation, north0_m=north0, east0_m=east0)
    for i in range(20):  # a wandering drive of a few metres
        source.move(Twist2D(0.5, rng.uniform(-1.0, 1.0)), 0.5)
        source.fix(float(i))
    fit = fit_track(source.fixes, -1.0)
    assert fit is not None
    assert math.remainder(fit.rotation_cw_rad - rotation, 2 * math.pi) == pytest.approx(0.0, abs=1e-6)
    assert fit.sigma_rad < FIT_MAX_SIGMA_RAD


def test_the_heading_is_used_until_the_track_says_more() -> None:
    source = FakeSource(north_rotation_cw_rad=0.5, heading_error_rad=math.radians(3))
    source.fix(0.0)
    anchor, origin = north_anchor(source, 0.0, 1.0)
    assert origin == "heading" and anchor is not None
    assert anchor.rotation_cw_rad == pytest.approx(0.5 + math.radians(3))  # the heading's error and all
    for i in range(1, 8):
        source.move(Twist2D(0.5, 0.0), 0.5)
        source.fix(float(i))
    anchor, origin = north_anchor(source, 8.0, 1.0)
    assert origin == "track" and anchor is not None and anchor.rotation_cw_rad == pytest.approx(0.5)
    # A noisy GPS over a short track says less than the heading: the heading is used.
    for n, f in enumerate(source.fixes):
        source.fixes[n] = (*f[:4], f[4] + (0.8 if n % 2 else -0.8), f[5])
    assert north_anchor(source, 8.0, 1.0)[1] == "heading"
    assert fit_track(source.fixes[:3], -1.0) is None


# ---------------------------------------------------------------- the controller

def drive(target: NavTarget, start: Pose2D, limits: LimitsParams = LIMITS, params: NavigationParams = NAV,
          seconds: float = 60.0) -> tuple[Pose2D, list[Pose2D], list[Twist2D], bool]:
    """A unicycle following the controller through the real limiter at 20 Hz (no wheel lag)."""
    ctl = GotoController(params, limits)
    limiter = TwistLimiter(TwistLimits.from_params(limits))
    pose, path, twists, done = start, [start], [], False
    for _ in range(round(seconds * 20)):
        want, status = ctl.twist(pose, target)
        if status.phase == "done":
            done = True
            want = Twist2D()
        limiter.step(want, 0.05)
        twists.append(limiter.current)
        pose = Pose2D(*_advance(pose, limiter.current, 0.05))
        path.append(pose)
        if done and limiter.current == Twist2D():
            break
    return pose, path, twists, done


def _advance(pose: Pose2D, t: Twist2D, dt: float) -> tuple[float, float, float]:
    yaw = pose.yaw_rad + 0.5 * t.omega_rad_s * dt
    return (pose.x_m + t.v_m_s * dt * math.cos(yaw), pose.y_m + t.v_m_s * dt * math.sin(yaw),
            wrap_angle(pose.yaw_rad + t.omega_rad_s * dt))


@settings(max_examples=40, deadline=None)
@given(st.floats(-15, 15), st.floats(-15, 15), st.floats(-math.pi, math.pi), st.floats(0.2, 0.8),
       st.one_of(st.none(), st.floats(-math.pi, math.pi)))
def test_controller_reaches_any_target_inside_the_radius_within_the_limits(
        tx: float, ty: float, yaw0: float, speed: float, final_yaw: float | None) -> None:
    start = Pose2D(0.0, 0.0, yaw0)
    target = NavTarget(tx, ty, 0.0, 0.0, final_yaw, speed, LocalAnchor())
    end, path, twists, done = drive(target, start, seconds=1.5 * math.hypot(tx, ty) / speed + 10.0)
    assert done
    assert math.hypot(end.x_m - tx, end.y_m - ty) <= NAV.arrival_radius_m
    if final_yaw is not None:
        assert abs(wrap_angle(end.yaw_rad - final_yaw)) <= math.radians(NAV.yaw_tolerance_deg) + 0.05
    assert all(abs(t.v_m_s) <= speed + 1e-9 and abs(t.omega_rad_s) <= LIMITS.max_angular_rad_s + 1e-9
               for t in twists)
    assert all(t.v_m_s >= 0.0 for t in twists)  # it never reverses toward a target
    # No overshoot past the target along the leg, and never more than the radius beyond it.
    leg = math.hypot(tx, ty)
    if leg > 0.5:
        ux, uy = tx / leg, ty / leg
        assert max(p.x_m * ux + p.y_m * uy for p in path) <= leg + NAV.arrival_radius_m


def test_controller_turns_in_place_when_the_target_is_behind_then_drives_straight() -> None:
    target = NavTarget(-3.0, 0.0, 0.0, 0.0, None, 0.5, LocalAnchor())
    _, path, twists, done = drive(target, Pose2D())
    assert done
    turning = [t for t in twists if t.v_m_s == 0.0 and t.omega_rad_s != 0.0]
    assert len(turning) > 5
    assert max(math.hypot(p.x_m, p.y_m) for p in path[:len(turning)]) < 1e-9  # the turn is on the spot
    assert max(abs(p.y_m) for p in path) < 0.05  # then straight down the leg


def test_controller_comes_back_onto_the_leg() -> None:
    # Started 0.5 m off the leg's line, facing along it: pure pursuit joins the line well before the end.
    target = NavTarget(6.0, 0.0, 0.0, 0.0, None, 0.5, LocalAnchor())
    _, path, _, done = drive(target, Pose2D(0.0, 0.5, 0.0))
    assert done
    assert all(abs(p.y_m) < 0.05 for p in path if 3.0 < p.x_m < 5.5)


def test_controller_status_cross_track_is_right_of_the_leg_positive() -> None:
    ctl = GotoController(NAV, LIMITS)
    target = NavTarget(5.0, 0.0, 0.0, 0.0, None, 0.5, LocalAnchor())
    assert ctl.status(Pose2D(1.0, -0.2, 0.0), target).crosstrack_m == pytest.approx(0.2)  # y left -: right
    assert ctl.status(Pose2D(1.0, 0.3, 0.0), target).crosstrack_m == pytest.approx(-0.3)
