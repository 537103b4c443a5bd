"""The command flow's drivers and the mode table, in the pure core: messages and times in, exact messages out.

Who holds the wheels in which autopilot mode ([modes]); the autopilot's own navigation as a driver (its
per-wheel demand in SERVO_OUTPUT_RAW through the whole pipeline); the handovers between drivers when the mode
changes (a GCS, a fence or a failsafe switching it); every stop path while the autopilot drives.

Geometry of the default profile (tests/test_command_core.py): wheel radius 0.05 m, track 0.30 m, full PWM =
20.944 rad/s, PWM 1000/1500/2000. A demand output at 1750 is half throttle forward: 10.472 rad/s, and with
both wheels there 0.5236 m/s.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_command_core import Rig, overrides, profile, texts

from rover_bridge.app.composition import BridgeCore
from rover_bridge.command.core import CommandState
from rover_bridge.errors import ConfigError
from rover_bridge.kinematics import MeasuredWheels, WheelSpeeds
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.wire import Incoming, Link, Outgoing
from rover_bridge.params import Profile, load_profile, profile_from_dict

MANUAL, HOLD, SIMPLE, AUTO, RTL, GUIDED = 0, 4, 7, 10, 11, 15
PERIOD_S = 0.05
DEMAND_PERIOD_S = 0.025  # 40 Hz
TOP_RAD_S = 200.0 * 2.0 * math.pi / 60.0
REPO = Path(__file__).resolve().parent.parent


class DriveRig(Rig):
    """A Rig with the autopilot's SERVO_OUTPUT_RAW and NAV_CONTROLLER_OUTPUT, and a scripted run."""

    def servo(self, t: float, left_us: int, right_us: int, port: int = 0) -> list[Outgoing]:
        outs = [1500] * 16
        outs[4], outs[5] = left_us, right_us  # servo5, servo6: the default [demand] outputs
        msg = mavlink.MAVLink_servo_output_raw_message(int(t * 1e6), port, *outs)
        return list(self.feed(Link.AUTOPILOT, self.wire(self.ap, msg), t).out)

    def nav(self, t: float, wp_dist: int) -> None:
        msg = mavlink.MAVLink_nav_controller_output_message(0.0, 0.0, 90, 90, wp_dist, 0.0, 0.0, 0.0)
        self.feed(Link.AUTOPILOT, self.wire(self.ap, msg), t)

    def run(self, t0: float, t1: float, mode: Callable[[float], int], demand: Callable[[float], tuple[int, int] | None],
            manual: Callable[[float], tuple[int, int] | None] = lambda t: None,
            beating: Callable[[float], bool] = lambda t: True) -> list[tuple[float, Outgoing]]:
        """From t0 to t1 on a 1 ms clock: the autopilot's heartbeat at 1 Hz and whenever the mode changes (as
        ArduPilot sends one at once), its demand at 40 Hz, a GCS's MANUAL_CONTROL at 10 Hz, ticks at the deadlines."""
        out: list[tuple[float, Outgoing]] = []
        last_mode = None
        for k in range(round(t0 * 1000), round(t1 * 1000)):
            t = k / 1000.0
            m = mode(t)
            if beating(t) and (k % 1000 == 0 or m != last_mode):
                out += [(t, o) for o in self.heartbeat(t, mode=m).out]
                last_mode = m
            if k % round(DEMAND_PERIOD_S * 1000) == 0:
                pwm = demand(t)
                if pwm is not None:
                    out += [(t, o) for o in self.servo(t, *pwm)]
            if k % 100 == 50:
                stick = manual(t)
                if stick is not None:
                    out += [(t, o) for o in self.manual(t, *stick).out]
            if self.core.next_deadline_s(t) <= t:
                ticked = self.core.tick(t)
                self.sent += [(t, o) for o in ticked]
                out += [(t, o) for o in ticked]
        return out


def fast() -> Profile:
    return profile()


def slow() -> Profile:
    return profile(fast=False)


def pwm_step_bound_us(p: Profile) -> float:
    """The largest change of one wheel's PWM between two outputs the limiter allows (one period of its limits)."""
    lim, robot = p.limits, p.robot
    dv = max(lim.max_linear_accel_m_s2, lim.max_linear_decel_m_s2) * PERIOD_S
    dw = lim.max_angular_accel_rad_s2 * PERIOD_S
    wheel = (dv + dw * robot.track_width_m / 2.0) / robot.wheel_radius_m
    return 500.0 * wheel / robot.max_wheel_rad_s + 1.0  # +1: whole microseconds


def largest_step(out: list[tuple[float, Outgoing]]) -> int:
    pwm = overrides(out)
    return max((max(abs(a[0] - b[0]), abs(a[1] - b[1])) for a, b in itertools.pairwise(pwm)), default=0)


def expected_pwm(left_rad_s: float) -> int:
    return round(1500 + 500 * left_rad_s / TOP_RAD_S)


# ------------------------------------------------------------------ the table


def test_the_default_table_follows_ardupilot_rovers_modes() -> None:
    m = Profile().modes
    assert set(m.gcs) == {0, 1, 3, 15} and set(m.targets) == {15} and set(m.stop) == {4}
    assert set(m.autopilot) == {5, 6, 8, 9, 10, 11, 12}  # LOITER FOLLOW DOCK CIRCLE AUTO RTL SMART_RTL
    listed = set(m.gcs) | set(m.targets) | set(m.autopilot) | set(m.stop)
    assert {7, 16} - listed == {7, 16}  # SIMPLE and INITIALISING stop: no driver


@pytest.mark.parametrize(("section", "key", "moved"), [("safety", "stop_modes", "stop"),
                                                         ("navigation", "guided_modes", "targets")])
def test_an_old_mode_key_says_where_it_moved(section: str, key: str, moved: str) -> None:
    with pytest.raises(ConfigError) as err:
        profile_from_dict({section: {key: [4]}})
    assert any(f"{section}.{key}: moved to the mode table: write `{moved} = [4]` under [modes]" in p
               for p in err.value.problems)


def test_a_mode_has_one_owner_and_the_demand_is_checked() -> None:
    with pytest.raises(ConfigError) as err:
        profile_from_dict({"modes": {"stop": [4, 10], "gcs": [0, 11]},
                           "demand": {"pwm_min": 1600, "left_output": 6, "timeout_s": 0.05, "rate_hz": 10.0}})
    problems = "\n".join(err.value.problems)
    assert "mode 10 is in stop and in another list" in problems
    assert "mode 11 is in autopilot and in gcs/targets" in problems
    assert "demand: expected pwm_min < pwm_trim < pwm_max" in problems
    assert "demand: left_output and right_output are both 6" in problems
    assert "demand.timeout_s: 0.05 s is shorter than two SERVO_OUTPUT_RAW periods" in problems
    servo = {"output": {"mode": "servo", "left_channel": 5, "right_channel": 3}}
    with pytest.raises(ConfigError, match="wheel outputs must not be the demand outputs"):
        profile_from_dict(servo)


def test_a_mode_in_no_list_stops_and_says_which() -> None:
    rig = DriveRig(slow())
    rig.heartbeat(0.0, mode=MANUAL)
    rig.manual(0.1, 800, 0)
    rig.run_until(0.5, 0.1, heartbeat_every_s=None)
    assert rig.core.commanded.v_m_s > 0.0
    reaction = rig.heartbeat(0.5, mode=SIMPLE)
    assert state(rig) is CommandState.HOLD and texts(reaction.out) == ["RB: SIMPLE: no driver, braking, then neutral"]
    out = rig.run_until(1.5, 0.5, heartbeat_every_s=None)
    assert overrides(out)[-1] == (1500, 1500) and rig.core.request is None
    assert texts(rig.manual(1.5, 800, 0).out) == ["RB: in SIMPLE, request from 255:190 ignored"]


def state(rig: Rig) -> CommandState:
    return rig.core.state


# ------------------------------------------------------------------ the demand -> the wheels


@pytest.mark.parametrize(("demand", "expected"), [
    ((1750, 1750), (1750, 1750)),  # half throttle both: 0.52 m/s, within every limit: what ArduPilot asked
    ((1600, 1400), (1600, 1400)),  # a pivot to the right (left forward): -1.40 rad/s
    ((1500, 1500), (1500, 1500)),
    ((1000, 1250), (1000, 1250)),  # reverse, turning
])
def test_a_demand_within_the_limits_reaches_the_wheels_as_the_autopilot_meant_it(
        demand: tuple[int, int], expected: tuple[int, int]) -> None:
    rig = DriveRig(fast())
    rig.heartbeat(0.0, mode=AUTO)
    out = rig.servo(0.01, *demand)
    assert overrides(out) == [expected]  # answered at once, as a request is
    assert state(rig) is CommandState.ACTIVE and rig.core.counters["demand.taken"] == 1


def test_a_demand_beyond_the_limits_is_limited_and_keeps_its_curvature() -> None:
    rig = DriveRig(fast())
    rig.heartbeat(0.0, mode=AUTO)
    out = rig.servo(0.01, 2000, 2000)  # full throttle: 1.047 m/s, over max_linear_m_s 0.8
    assert overrides(out) == [(expected_pwm(0.8 / 0.05),) * 2]
    assert rig.core.commanded.v_m_s == pytest.approx(0.8)


def test_the_demand_range_is_the_profiles() -> None:
    rig = DriveRig(profile(demand={"pwm_min": 1100, "pwm_max": 1900}))
    rig.heartbeat(0.0, mode=AUTO)
    assert overrides(rig.servo(0.01, 1700, 1700)) == [(1750, 1750)]  # half of 1500..1900


def test_reports_from_another_port_or_component_or_outside_autopilot_modes_are_not_a_demand() -> None:
    rig = DriveRig(fast())
    rig.heartbeat(0.0, mode=AUTO)
    assert rig.servo(0.01, 1750, 1750, port=1) == []
    other = mavlink.MAVLink(None, srcSystem=1, srcComponent=2)
    msg = mavlink.MAVLink_servo_output_raw_message(0, 0, *([1750] * 16))
    assert rig.feed(Link.AUTOPILOT, Rig.wire(other, msg), 0.02).out == ()
    rig.heartbeat(0.03, mode=MANUAL)
    assert rig.servo(0.04, 1750, 1750) == [] and state(rig) is CommandState.IDLE
    assert "demand.taken" not in rig.core.counters


def weak_motor_in_auto(speed_loop: bool) -> tuple[DriveRig, float]:
    """A weak motor: each wheel turns at 60 % of what the open-loop map says; the demand is 1750 (half) for 5 s.
    Returns the rig and the wheels' final measured speed."""
    p = profile(demand={"speed_loop": speed_loop})
    rig = DriveRig(dataclasses.replace(p, control=Profile().control))  # closed_loop, the shipped gains
    rig.heartbeat(0.0, mode=AUTO)
    measured = 0.0
    for k in range(1, 200):
        t = k * DEMAND_PERIOD_S
        rig.servo(t, 1750, 1750)
        pwm = rig.core.last_wheel_pwm
        assert pwm is not None
        target = 0.6 * (pwm.left_us - 1500) / 500 * TOP_RAD_S
        measured += (target - measured) * 0.3
        rig.core.on_wheels(MeasuredWheels(t, WheelSpeeds(measured, measured)), t)
        if k % 40 == 0:
            rig.heartbeat(t, mode=AUTO)
    return rig, measured


def test_with_demand_speed_loop_the_loop_holds_each_wheel_at_its_share_of_the_demand() -> None:
    # The loop raises the PWM until the measured speed is the demand's share (10.47 rad/s at 1750), which
    # copying the PWM would not.
    rig, measured = weak_motor_in_auto(speed_loop=True)
    assert measured == pytest.approx(0.5 * TOP_RAD_S, rel=0.03)
    assert rig.core.last_wheel_pwm is not None and rig.core.last_wheel_pwm.left_us > 1800


def test_by_default_the_demand_is_not_closed_a_second_time() -> None:
    # The autopilot's own speed and turn-rate loops close around its demand: the bridge maps it (limits, PWM
    # map) and leaves the correcting to them, so the weak wheel stays at 60 % of the demand's share here.
    rig, measured = weak_motor_in_auto(speed_loop=False)
    assert rig.core.last_wheel_pwm is not None and rig.core.last_wheel_pwm.left_us == 1750
    assert measured == pytest.approx(0.6 * 0.5 * TOP_RAD_S, rel=0.03)


_RIGS: dict[tuple[int, int, int], DriveRig] = {}


@settings(derandomize=True, database=None, deadline=None, max_examples=300)
@given(st.integers(800, 2200), st.integers(800, 2200), st.sampled_from([(1000, 1500, 2000), (1100, 1500, 1900),
                                                                        (1000, 1450, 2000)]))
def test_each_wheel_gets_its_fraction_of_its_top_speed(left_us: int, right_us: int,
                                                       pwm: tuple[int, int, int]) -> None:
    lo, trim, hi = pwm
    rig = _RIGS.get(pwm) or _RIGS.setdefault(pwm, DriveRig(profile(demand={"pwm_min": lo, "pwm_trim": trim,
                                                                            "pwm_max": hi})))
    driver = rig.core.autopilot
    demand = driver.to_demand(left_us, right_us)
    for us, got in ((left_us, demand.left), (right_us, demand.right)):
        assert -1.0 <= got <= 1.0 and (got > 0) == (us > trim) and (got < 0) == (us < trim)
        assert driver.fraction(us + 1) >= got  # monotonic
    wheels = rig.core.stage.drive.to_wheel_speeds(demand.twist)  # IK undoes the FK: each wheel its share
    assert wheels.left_rad_s == pytest.approx(demand.left * TOP_RAD_S, abs=1e-9)
    assert wheels.right_rad_s == pytest.approx(demand.right * TOP_RAD_S, abs=1e-9)


# ------------------------------------------------------------------ handovers (fence, failsafe actions: mode changes)


def test_auto_to_manual_mid_mission_hands_the_wheels_to_the_gcs_without_a_jump() -> None:
    p = slow()
    rig = DriveRig(p)
    out = rig.run(0.0, 6.0, mode=lambda t: AUTO if t < 3.0 else MANUAL,
                  demand=lambda t: (1700, 1650) if t < 3.0 else (1500, 1500),  # MANUAL: the sticks' (trim)
                  manual=lambda t: (400, -300))  # a joystick streaming all along (QGC does)
    before = [o for t, o in out if t < 3.0]
    assert rig.core.counters["dropped.mode"] >= 25  # in AUTO its requests do not take the wheels
    assert "RB: in AUTO, request from 255:190 ignored" in texts(before)
    said = [t for t in texts(out) if "drive" in t and "RB: active" not in t]
    assert said == ["RB: AUTO: the autopilot drives", "RB: MANUAL: GCS requests drive"]
    assert largest_step(out) <= pwm_step_bound_us(p)
    # The joystick's twist at the end: 0.2 m/s, turning left at 0.45 rad/s.
    assert rig.core.commanded.v_m_s == pytest.approx(0.2) and rig.core.commanded.omega_rad_s == pytest.approx(0.45)


def test_auto_to_hold_stops_and_the_demand_no_longer_drives() -> None:
    p = slow()
    rig = DriveRig(p)
    out = rig.run(0.0, 5.0, mode=lambda t: AUTO if t < 3.0 else HOLD, demand=lambda t: (1750, 1750))
    after = [(t, o) for t, o in out if t >= 3.0]
    assert "RB: autopilot in HOLD, braking, then neutral" in texts(after)
    left = [pwm[0] for pwm in overrides(after)]
    assert all(a >= b for a, b in itertools.pairwise(left)) and left[-1] == 1500  # braked, never back up
    taken = rig.core.counters["demand.taken"]
    rig.run(5.0, 6.0, mode=lambda t: HOLD, demand=lambda t: (1750, 1750))
    assert state(rig) is CommandState.HOLD and rig.core.counters["demand.taken"] == taken  # not ours in HOLD
    assert largest_step(out) <= pwm_step_bound_us(p)


def test_manual_to_rtl_on_a_fence_breach_hands_the_wheels_to_the_autopilot_without_a_jump() -> None:
    p = slow()
    rig = DriveRig(p)
    out = rig.run(0.0, 6.0, mode=lambda t: MANUAL if t < 3.0 else RTL,
                  demand=lambda t: (1500, 1500) if t < 3.0 else (1400, 1650),  # RTL turns back home
                  manual=lambda t: (800, 0))  # the operator drives on, out through the fence
    expected = rig.core.autopilot.to_demand(1400, 1650).twist
    assert rig.core.commanded.v_m_s == pytest.approx(expected.v_m_s)
    assert rig.core.commanded.omega_rad_s == pytest.approx(expected.omega_rad_s)
    assert "RB: RTL: the autopilot drives" in texts(out)
    assert largest_step(out) <= pwm_step_bound_us(p)
    assert rig.core.counters["dropped.mode"] >= 25


def test_a_wound_up_demand_at_takeover_does_not_step_the_wheels() -> None:
    # Nobody forwarded the demand while the bridge idled in MANUAL: AUTO's speed controller wound up to full.
    p = slow()
    rig = DriveRig(p)
    out = rig.run(0.0, 3.0, mode=lambda t: MANUAL if t < 1.0 else AUTO, demand=lambda t: (2000, 2000))
    assert largest_step(out) <= pwm_step_bound_us(p)
    taken = min(t for t, o in out if o.msg.get_type() == "RC_CHANNELS_OVERRIDE" and o.msg.chan1_raw > 1500)
    first = next(o for t, o in out if t == taken and o.msg.get_type() == "RC_CHANNELS_OVERRIDE")
    assert first.msg.chan1_raw <= 1500 + pwm_step_bound_us(p)  # one period of acceleration, not the demand
    assert rig.core.commanded.v_m_s == pytest.approx(0.8)  # then up to the limit, at the limiter's pace


# ------------------------------------------------------------------ every stop path while the autopilot drives


def driving_in_auto(p: Profile | None = None) -> DriveRig:
    rig = DriveRig(p or slow())
    rig.run(0.0, 2.0, mode=lambda t: AUTO, demand=lambda t: (1750, 1750))
    assert state(rig) is CommandState.ACTIVE and rig.core.commanded.v_m_s == pytest.approx(0.5236, abs=1e-3)
    return rig


def test_shutdown_in_auto_sends_neutral_release_and_waits_for_the_proof() -> None:
    rig = driving_in_auto()
    out = rig.core.shutdown(2.0)
    probe = [o.msg for o in out if o.msg.get_type() == "TIMESYNC"]
    assert overrides(out) == [(1500, 1500), (0, 0)] and len(probe) == 1
    assert rig.servo(2.01, 1750, 1750) == []  # the demand no longer drives anything
    answer = Rig.wire(rig.ap, mavlink.MAVLink_timesync_message(tc1=1, ts1=probe[0].ts1))
    assert rig.feed(Link.AUTOPILOT, answer, 2.02).consumed and rig.core.stop_confirmed is True


def test_a_disarm_in_auto_is_neutral_at_once() -> None:
    rig = driving_in_auto()
    reaction = rig.heartbeat(2.0, armed=False, mode=AUTO)
    assert overrides(reaction.out) == [(1500, 1500)] and state(rig) is CommandState.DISARMED
    assert rig.servo(2.01, 1750, 1750) == [] and rig.core.counters["demand.dropped"] == 1


def test_the_autopilots_heartbeat_lost_in_auto_is_neutral_at_once() -> None:
    rig = driving_in_auto()
    out = rig.run(2.0, 6.0, mode=lambda t: AUTO, demand=lambda t: (1750, 1750), beating=lambda t: False)
    lost = [t for t, o in out if o.msg.get_type() == "STATUSTEXT" and "heartbeat lost" in o.msg.text]
    assert lost == [pytest.approx(4.0)]  # the last heartbeat at 1.0 s + 3 s
    assert all(pwm == (1500, 1500) for pwm in overrides([(t, o) for t, o in out if t >= lost[0]]))


def test_a_stale_demand_brakes_through_the_limiter_then_idles() -> None:
    p = slow()
    rig = driving_in_auto(p)
    out = rig.run(2.0, 4.0, mode=lambda t: AUTO, demand=lambda t: None)
    said = [(t, o.msg.text) for t, o in out if o.msg.get_type() == "STATUSTEXT"]
    assert said[0] == (pytest.approx(2.0 - DEMAND_PERIOD_S + 0.3, abs=0.002),
                       "RB: no demand from the autopilot, braking")
    assert said[1][1] == "RB: idle, wheels neutral"
    # 0.52 m/s at 2 m/s^2: 0.26 s of braking, never backwards, then neutral.
    assert said[1][0] - said[0][0] == pytest.approx(0.5236 / 2.0, abs=PERIOD_S + 1e-6)
    left = [pwm[0] for pwm in overrides(out)]
    assert all(a >= b for a, b in itertools.pairwise(left)) and left[-1] == 1500
    assert largest_step(out) <= pwm_step_bound_us(p)
    assert overrides(rig.servo(4.0, 1750, 1750))[0][0] > 1500  # it comes back: drives again


# ------------------------------------------------------------------ a demand that cannot be one


def test_an_unconfigured_demand_output_is_said_not_driven_through() -> None:
    rig = DriveRig(fast())
    rig.heartbeat(0.0, mode=AUTO)
    out = rig.servo(0.01, 0, 1500)  # no pulses on SERVO5: its FUNCTION is not 73
    assert texts(out) == ["RB: SERVO5 reads 0: set SERVO5_FUNCTION 73"] and overrides(out) == []
    assert rig.core.counters["demand.no_pulses"] == 1 and state(rig) is CommandState.IDLE
    rig.heartbeat(0.02, armed=False, mode=AUTO)
    assert texts(rig.servo(0.03, 0, 0)) == []  # disarmed with MOT_SAFE_DISARM: no pulses is right


def test_no_pulses_while_disarmed_is_no_demand_not_full_reverse() -> None:
    rig = DriveRig(profile(safety={"require_armed": False}))  # as the SITL profile: passthrough drives disarmed
    rig.heartbeat(0.0, armed=False, mode=AUTO)
    assert overrides(rig.servo(0.01, 0, 0)) == [(1500, 1500)] and rig.core.commanded.v_m_s == 0.0
    assert overrides(rig.servo(0.02, 1750, 1750)) == [(1750, 1750)]  # require_armed off: a demand is followed


def test_a_demand_stuck_at_trim_while_the_autopilot_has_far_to_go_is_said() -> None:
    rig = DriveRig(fast())
    out: list[Outgoing] = []
    for k in range(200):  # 5 s
        t = k * DEMAND_PERIOD_S
        if k % 40 == 0:
            rig.heartbeat(t, mode=AUTO)
            rig.nav(t, wp_dist=12)
        out += rig.servo(t, 1500, 1500)
    said = texts(out)
    assert said.count("RB: AUTO: SERVO5/6 at trim: FUNCTION 73/74?") == 1
    assert rig.core.counters["demand.stuck"] >= 1


def test_a_demand_at_trim_near_the_waypoint_is_not_a_fault() -> None:
    rig = DriveRig(fast())
    out: list[Outgoing] = []
    for k in range(200):
        t = k * DEMAND_PERIOD_S
        if k % 40 == 0:
            rig.heartbeat(t, mode=AUTO)
            rig.nav(t, wp_dist=0)  # arrived: the mission ended, the demand is trim
        out += rig.servo(t, 1500, 1500)
    assert "demand.stuck" not in rig.core.counters and not any("trim" in t for t in texts(out))


# ------------------------------------------------------------------ the stream the driver needs


def _interval_requests(out: list[Outgoing]) -> list[MAVLinkMessage]:
    return [o.msg for o in out if o.msg.get_type() == "COMMAND_LONG"
            and o.msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL]


def _bridge_until_requests_settle(core: BridgeCore, ap: mavlink.MAVLink, t: float, result: int,
                                  mode: int) -> tuple[float, list[Outgoing]]:
    """Heartbeats in `mode` and ACKs (`result` for SERVO_OUTPUT_RAW, accepted for the rest) for 3 s."""
    out: list[Outgoing] = []
    end = t + 3.0
    while t < end:
        sent: list[Outgoing] = []
        if round(t * 100) % 100 == 0:
            hb = mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, mavlink.MAV_MODE_FLAG_SAFETY_ARMED,
                mode, mavlink.MAV_STATE_ACTIVE, 3)
            sent += core.handle(Incoming(Link.AUTOPILOT, Rig.wire(ap, hb)), t).out
        sent += core.tick(t) if core.next_deadline_s(t) <= t else []
        while sent:  # the autopilot answers each request at once; the answer may bring the next request
            out += sent
            acks = []
            for req in _interval_requests(sent):
                answer = result if int(req.param1) == mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW else 0
                acks.append(mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, answer, 0, 0,
                                                                1, 191))
            sent = [o for ack in acks for o in core.handle(Incoming(Link.AUTOPILOT, Rig.wire(ap, ack)), t).out]
        t = round(t + 0.01, 6)
    return t, out


def test_the_demand_is_asked_for_at_40_hz_once_the_autopilot_drives_and_again_after_a_reboot() -> None:
    core = BridgeCore(fast())
    ap = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    t, out = _bridge_until_requests_settle(core, ap, 0.0, mavlink.MAV_RESULT_ACCEPTED, MANUAL)
    asked = [int(m.param1) for m in _interval_requests(out)]
    assert mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW not in asked and asked  # MANUAL: nobody needs it
    t, out = _bridge_until_requests_settle(core, ap, t, mavlink.MAV_RESULT_ACCEPTED, AUTO)
    demand = [m for m in _interval_requests(out) if int(m.param1) == mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW]
    assert [m.param2 for m in demand] == [25_000.0]  # 40 Hz
    # The autopilot reboots (its heartbeat gone for 4 s): every interval reset, the demand asked for again.
    t, out = _bridge_until_requests_settle(core, ap, t + 4.0, mavlink.MAV_RESULT_ACCEPTED, MANUAL)
    assert [int(m.param1) for m in _interval_requests(out)].count(mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW) == 1


def test_a_denied_demand_interval_falls_back_to_the_rc_channels_stream() -> None:
    core = BridgeCore(fast())
    ap = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    _, out = _bridge_until_requests_settle(core, ap, 0.0, mavlink.MAV_RESULT_DENIED, AUTO)
    streams = [o.msg for o in out if o.msg.get_type() == "REQUEST_DATA_STREAM"]
    assert [(m.req_stream_id, m.req_message_rate) for m in streams] == [(mavlink.MAV_DATA_STREAM_RC_CHANNELS, 40)]


# ------------------------------------------------------------------ deploy/ardupilot-rover.parm


@pytest.mark.parametrize("name", ["default.toml", "ardupilot-sitl-skid.toml"])
def test_the_shipped_ardupilot_parameters_agree_with_the_shipped_profiles(
        name: str, capsys: pytest.CaptureFixture[str]) -> None:
    from pymavlink.mavparm import MAVParmDict

    parm = MAVParmDict()
    assert parm.load(str(REPO / "deploy" / "ardupilot-rover.parm"))
    assert "Invalid line" not in capsys.readouterr().out  # MAVProxy's and pymavlink's reader take every line
    p = load_profile(REPO / "params" / name)
    o, d = p.output, p.demand
    assert parm[f"SERVO{o.left_channel}_FUNCTION"] == 50 + o.left_channel  # RCINn passthrough (51 = RCIN1)
    assert parm[f"SERVO{o.right_channel}_FUNCTION"] == 50 + o.right_channel
    assert (parm[f"SERVO{d.left_output}_FUNCTION"], parm[f"SERVO{d.right_output}_FUNCTION"]) == (73, 74)
    for output in (d.left_output, d.right_output):
        assert (parm[f"SERVO{output}_MIN"], parm[f"SERVO{output}_TRIM"], parm[f"SERVO{output}_MAX"]) == (
            d.pwm_min, d.pwm_trim, d.pwm_max)
    assert parm["MAV_GCS_SYSID"] == o.override_source_system
    assert 0.8 * parm["SCHED_LOOP_RATE"] >= d.rate_hz  # Rover's shortest interval: 1.25 loop periods
    assert parm["RC_OVERRIDE_TIME"] > 2.0 / p.command.rate_hz


# ------------------------------------------------------------------ through the shell, against the emulator


def test_through_the_shell_rtl_asks_the_emulator_for_the_demand_and_says_an_unconfigured_output() -> None:
    # The emulator's outputs 5/6 have no function (0): it reports them as 0, as ArduPilot reports an output
    # nothing drives. In RTL (AUTO needs a mission) the bridge asks for SERVO_OUTPUT_RAW at 40 Hz and says
    # what to set.
    from lockstep import Lockstep

    lock = Lockstep(Profile())
    try:
        lock.run_for(2.0)
        assert len([m for t, m in lock.view.of("SERVO_OUTPUT_RAW") if t > 1.0]) <= 5  # MANUAL: its own rate
        lock.gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0,
                                       mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, RTL, 0, 0, 0, 0, 0)
        lock.run_for(3.0)
        late = [t for t, m in lock.view.of("SERVO_OUTPUT_RAW") if t > 4.0]
        assert len(late) == pytest.approx(40, abs=2)  # forwarded to the GCS, at the rate the bridge asked for
        said = [m.text for t, m in lock.view.of("STATUSTEXT")]
        assert "RB: RTL: the autopilot drives" in said
        assert "RB: SERVO5 reads 0: set SERVO5_FUNCTION 73" in said
        assert lock.core.command.counters["demand.no_pulses"] >= 80 and "demand.taken" not in lock.core.command.counters
        # WHEEL_DISTANCE's (no interval for it in Rover) and ATTITUDE's (50 Hz is refused at SCHED_LOOP_RATE 50);
        # none for the demand's 40 Hz SERVO_OUTPUT_RAW.
        assert lock.core.estimate.streams.counters["stream_fallbacks"] == 2
    finally:
        lock.close()
