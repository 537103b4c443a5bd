"""Going to a point, the pure parts: how targets are read, where they land in the estimate's frame, the
track fit that ties the frames, and the controller driving a unicycle through the real limiter."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from navsupport import FakeSource, lat_lon

from rover_bridge.command.approach import StopProfile, approach_lag_s
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
from rover_bridge.params import LimitsParams, NavigationParams, profile_from_dict

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

OUTPUT_S = 0.05  # the simulations' output period (20 Hz)


def stop_profile(limits: LimitsParams, wheel_s: float = 0.0) -> StopProfile:
    """The curve the bridge derives for the simulation: its output period, the wheels' lag."""
    return StopProfile(limits.max_linear_decel_m_s2, OUTPUT_S + wheel_s, wheel_s,
                       limits.max_linear_decel_m_s2 * OUTPUT_S)


def drive(target: NavTarget, start: Pose2D, limits: LimitsParams = LIMITS, params: NavigationParams = NAV,
          seconds: float = 60.0, wheel_lag_s: float = 0.0,
          ) -> tuple[Pose2D, list[Pose2D], list[Twist2D], bool]:
    """A unicycle following the controller through the real limiter at 20 Hz. Each output holds for one
    period; with `wheel_lag_s` the unicycle's speeds follow the outputs through a first-order lag of that
    time constant (a wheel), and the controller is told the lag the bridge derives (output + wheel)."""
    ctl = GotoController(params, limits, stop_profile(limits, wheel_lag_s))
    limiter = TwistLimiter(TwistLimits.from_params(limits))
    pose, path, twists, done = start, [start], [], False
    moving = Twist2D()
    steps = 10  # the plant's sub-steps per output
    for _ in range(round(seconds / OUTPUT_S)):
        want, status = ctl.twist(pose, target)
        if status.phase == "done":
            done = True
            want = Twist2D()
        limiter.step(want, OUTPUT_S)
        twists.append(limiter.current)
        for _ in range(steps):
            if wheel_lag_s > 0.0:
                k = 1.0 - math.exp(-OUTPUT_S / steps / wheel_lag_s)
                moving = Twist2D(moving.v_m_s + k * (limiter.current.v_m_s - moving.v_m_s),
                                 moving.omega_rad_s + k * (limiter.current.omega_rad_s - moving.omega_rad_s))
            else:
                moving = limiter.current
            pose = Pose2D(*_advance(pose, moving, OUTPUT_S / steps))
        path.append(pose)
        if done and limiter.current == Twist2D() and abs(moving.v_m_s) < 1e-3:
            break
    return pose, path, twists, done


def _advance(pose: Pose2D, t: Twist2D, dt: float) -> tuple[float, float, float]:
    yaw = pose.yaw_rad + 0.5 * t.omega_rad_s * dt
    return (pose.x_m + t.v_m_s * dt * math.cos(yaw), pose.y_m + t.v_m_s * dt * math.sin(yaw),
            wrap_angle(pose.yaw_rad + t.omega_rad_s * dt))


@settings(max_examples=40, deadline=None)
@given(st.floats(-15, 15), st.floats(-15, 15), st.floats(-math.pi, math.pi), st.floats(0.2, 0.8),
       st.one_of(st.none(), st.floats(-math.pi, math.pi)), st.sampled_from([0.0, 0.15]))
def test_controller_reaches_any_target_inside_the_radius_within_the_limits(
        tx: float, ty: float, yaw0: float, speed: float, final_yaw: float | None, wheel_lag_s: float) -> None:
    start = Pose2D(0.0, 0.0, yaw0)
    target = NavTarget(tx, ty, 0.0, 0.0, final_yaw, speed, LocalAnchor())
    end, path, twists, done = drive(target, start, seconds=1.5 * math.hypot(tx, ty) / speed + 10.0,
                                    wheel_lag_s=wheel_lag_s)
    assert done
    assert math.hypot(end.x_m - tx, end.y_m - ty) <= NAV.arrival_radius_m
    if final_yaw is not None:
        assert abs(wrap_angle(end.yaw_rad - final_yaw)) <= math.radians(NAV.yaw_tolerance_deg) + 0.05
    assert all(abs(t.v_m_s) <= speed + 1e-9 and abs(t.omega_rad_s) <= LIMITS.max_angular_rad_s + 1e-9
               for t in twists)
    assert all(t.v_m_s >= 0.0 for t in twists)  # it never reverses toward a target
    # Never more than 0.1 m past the target along the leg (issue 42's bound).
    leg = math.hypot(tx, ty)
    if leg > 0.5:
        ux, uy = tx / leg, ty / leg
        assert max(p.x_m * ux + p.y_m * uy for p in path) <= leg + 0.1


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
    ctl = GotoController(NAV, LIMITS, stop_profile(LIMITS))
    target = NavTarget(5.0, 0.0, 0.0, 0.0, None, 0.5, LocalAnchor())
    assert ctl.status(Pose2D(1.0, -0.2, 0.0), target).crosstrack_m == pytest.approx(0.2)  # y left -: right
    assert ctl.status(Pose2D(1.0, 0.3, 0.0), target).crosstrack_m == pytest.approx(-0.3)


# ---------------------------------------------------------------- the braking curve

SKID = LimitsParams(max_linear_m_s=3.0, max_angular_rad_s=2.0, max_linear_accel_m_s2=3.0,
                    max_linear_decel_m_s2=5.0, max_angular_accel_rad_s2=6.0)  # params/ardupilot-sitl-skid.toml


def trapezoid_s(distance_m: float, cruise_m_s: float, accel: float, decel: float) -> float:
    """The least time over `distance_m` from rest to rest within a speed, an acceleration and a deceleration."""
    ramps_m = cruise_m_s ** 2 / (2.0 * accel) + cruise_m_s ** 2 / (2.0 * decel)
    if ramps_m <= distance_m:
        return cruise_m_s / accel + cruise_m_s / decel + (distance_m - ramps_m) / cruise_m_s
    peak = math.sqrt(2.0 * distance_m * accel * decel / (accel + decel))
    return peak / accel + peak / decel


@pytest.mark.parametrize(("lag_s", "wheel_s"), [(0.0, 0.0), (0.05, 0.0), (0.2, 0.15)])
def test_the_braking_curve_is_the_stopping_distance_after_a_lag(lag_s: float, wheel_s: float) -> None:
    curve = StopProfile(5.0, lag_s, wheel_s, 0.25)
    for v in (0.01, 0.3, 1.0, 3.0):
        assert curve.speed_m_s(curve.stop_distance_m(v)) == pytest.approx(v)
    # The ramp, the lag's distance and, braking at nearly the full rate, the wheels' lead of wheel_s x decel.
    assert curve.stop_distance_m(3.0) == pytest.approx(0.9 + 3.0 * lag_s + lag_s * wheel_s * 5.0, rel=0.3)
    assert curve.stop_distance_m(3.0) <= 0.9 + 3.0 * lag_s + lag_s * wheel_s * 5.0
    assert curve.speed_m_s(0.0) == curve.speed_m_s(-0.5) == 0.0
    if lag_s == 0.0:
        assert curve.speed_m_s(0.9) == pytest.approx(3.0)  # sqrt(2 a d)
    else:  # the last millimetres: still a speed (a rover that stopped short creeps in), d over a time
        assert curve.speed_m_s(0.001) == pytest.approx(0.001 / (lag_s + lag_s * wheel_s * 5.0 / 0.25), rel=0.1)


def test_the_lag_is_the_output_period_the_wheels_response_and_the_jerk_ramp() -> None:
    p = profile_from_dict({"command": {"rate_hz": 20.0}, "control": {"reference_s": 0.15},
                           "limits": {"max_linear_decel_m_s2": 5.0}})
    assert approach_lag_s(p) == pytest.approx(0.05 + 0.15)
    jerky = profile_from_dict({"command": {"rate_hz": 20.0}, "control": {"reference_s": 0.15},
                               "limits": {"max_linear_decel_m_s2": 5.0, "max_linear_jerk_m_s3": 20.0}})
    assert approach_lag_s(jerky) == pytest.approx(0.05 + 0.15 + 0.125)
    curve = StopProfile.of(jerky)
    assert (curve.decel_m_s2, curve.wheel_s) == (5.0, pytest.approx(0.275))
    assert curve.settle_m_s == pytest.approx(5.0 / 20.0)


@pytest.mark.parametrize("wheel_lag_s", [0.0, 0.15, 0.3])
def test_an_8_m_go_to_runs_the_trapezoid_and_stops_on_the_point(wheel_lag_s: float) -> None:
    # The shipped skid profile's limits, cruise 3 m/s: up at the acceleration limit, along at the cruise
    # speed, down the braking curve at the deceleration limit, at rest on the point; not a slow approach.
    target = NavTarget(8.0, 0.0, 0.0, 0.0, None, 3.0, LocalAnchor())
    end, path, twists, done = drive(target, Pose2D(), limits=SKID, seconds=20.0, wheel_lag_s=wheel_lag_s)
    assert done
    ideal_s = trapezoid_s(8.0, 3.0, 3.0, 5.0)  # 3.47 s
    lag_s = OUTPUT_S + wheel_lag_s
    at_rest_s = len(twists) * OUTPUT_S
    # The ramps and the cruise, the lag once over, and the wheel's own decay from the last command.
    assert at_rest_s <= ideal_s + lag_s + 6.0 * wheel_lag_s + 0.2
    assert max(t.v_m_s for t in twists) == pytest.approx(3.0)
    assert abs(end.x_m - 8.0) <= 0.03 and abs(end.y_m) < 1e-6  # the bound: 0.15 m
    assert max(p.x_m for p in path) - 8.0 <= 0.03  # the bound: 0.1 m past
    # Braking starts no earlier than the curve asks: the speed holds at the cruise until 8 m less the
    # stopping distance (0.9 m at 5 m/s^2, the lag's 3 m/s x lag, the wheels' lead), one output's travel.
    cruising = next(i for i, t in enumerate(twists) if t.v_m_s >= 3.0 - 1e-9)
    braking_at_m = next(path[i].x_m for i in range(cruising, len(twists)) if twists[i].v_m_s < 3.0 - 1e-9)
    assert braking_at_m >= 8.0 - stop_profile(SKID, wheel_lag_s).stop_distance_m(3.0) - 3.0 * OUTPUT_S
    assert stop_profile(SKID, wheel_lag_s).stop_distance_m(3.0) <= 0.9 + 3.0 * lag_s + lag_s * wheel_lag_s * 5.0


def test_the_target_is_reached_once_the_rover_is_nearly_stopped_not_on_entering_the_radius() -> None:
    ctl = GotoController(NAV, SKID, stop_profile(SKID, 0.15))
    target = NavTarget(8.0, 0.0, 0.0, 0.0, None, 3.0, LocalAnchor())
    # Inside the radius at 0.14 m: the curve still asks for speed, straight on (no steering at what is aside).
    twist, status = ctl.twist(Pose2D(7.86, 0.02, 0.0), target)
    assert status.phase == "drive" and twist.v_m_s > ctl.stop.settle_m_s and twist.omega_rad_s == 0.0
    # Still inside, further on: no longer worth a command; reached.
    twist, status = ctl.twist(Pose2D(7.97, 0.02, 0.0), target)
    assert status.phase == "done" and twist == Twist2D()
    # Just past the point: done stays done, nothing turns back to it.
    twist, status = ctl.twist(Pose2D(8.05, 0.0, 0.0), target)
    assert status.phase == "done" and twist == Twist2D()
