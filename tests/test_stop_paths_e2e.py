"""Every stop path while the autopilot drives (issue 29), end to end: a mission flown in AUTO through the bridge,
then the autopilot disarmed by a ground station, its heartbeat lost, the link to it silent, or its demand stale.

Judged on what the emulator obeys (its motor outputs 1 and 3: the bridge's overrides through passthrough),
what it still asks for (its own demand on outputs 5 and 6), its ground truth, and the STATUSTEXT the ground
station gets; every bound comes from the shipped profile (params/ardupilot-sitl-skid.toml) and .parm, not from
wall time. Lockstep, UDP loopback (tests/navrig.py, tests/lockstep.py). The same paths against ArduPilot's own
SITL: tests/test_ardupilot_sitl_nav.py; in the pure core: tests/test_drivers.py.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import pytest
from navrig import WAYPOINTS, BridgeRig, shipped_parm, shipped_profile

from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.params import Profile
from sitl.modes import MODE_AUTO, MODE_HOLD, MODE_MANUAL
from sitl.scenario import LinkSilence

pytestmark = pytest.mark.e2e

P = mavlink
TRIM = 1500
HEARTBEAT = P.MAVLINK_MSG_ID_HEARTBEAT
DEMAND = P.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW
BRAKING = "RB: no demand from the autopilot, braking"
LOST = "RB: autopilot heartbeat lost, neutral"
DISARMED = "RB: autopilot disarmed, neutral"

EPS_S = 1e-6  # float sums of the 10 ms steps
Sample = tuple[float, int, int, int]  # time, motor outputs 1 and 3 (what the bridge's overrides set), demand 5


class StopRig(BridgeRig):
    """The bridge rig, keeping every step what the emulator's outputs carry and every message it sends."""

    def __init__(self, profile: Profile | None = None) -> None:
        self.profile = profile or shipped_profile()
        self.outputs: list[Sample] = []
        self.still: list[bool] = []  # the rover stood still at the end of each step (truth)
        super().__init__(self.profile)
        self.emu.sent_log = []

    def _record(self) -> None:
        super()._record()
        o = self.emu.servo_outputs
        self.outputs.append((self.ls.t_s, o[1], o[3], o[5]))
        self.still.append(self.stopped())

    def since(self, t_s: float) -> list[Sample]:
        return [s for s in self.outputs if s[0] >= t_s]

    def said(self, text: str, after_s: float) -> list[float]:
        """When the ground station got `text` (the bridge's or the autopilot's STATUSTEXT)."""
        return [t for t, m in self.ls.view.of("STATUSTEXT") if t >= after_s and m.text == text]

    def sent(self, msg_id: int) -> list[float]:
        """When the emulator sent a message of `msg_id` (what it withholds or loses to silence is not sent)."""
        assert self.emu.sent_log is not None
        return [t for t, m in self.emu.sent_log if m.get_msgId() == msg_id]


def on_a_mission(profile: Profile | None = None) -> StopRig:
    """The shipped setup flying the three-waypoint mission in AUTO, on its first leg at over 2 m/s."""
    rig = StopRig(profile)
    assert rig.upload(WAYPOINTS) == P.MAV_MISSION_ACCEPTED
    rig.set_mode(MODE_AUTO)
    assert rig.run_until(lambda: rig.emu.truth.v_m_s > 2.0, 20.0)
    rig.run(0.5)
    assert rig.outputs[-1][1] > 1700 and "RB: AUTO: the autopilot drives" in rig.texts()
    return rig


# -- bounds from the profile ----------------------------------------------------------------------------------

def period_s(p: Profile) -> float:
    return 1.0 / p.command.rate_hz


def speed_m_s(p: Profile, pwm_us: int) -> float:
    """A wheel's ground speed at this PWM by the profile's map (the rover-skid model's is the same line)."""
    o = p.output
    return (pwm_us - o.pwm_trim) / (o.pwm_max - o.pwm_trim) * p.robot.max_wheel_rad_s * p.robot.wheel_radius_m


def step_bound_us(p: Profile) -> float:
    """The most one wheel's PWM may change from one output to the next: one period of the limiter's limits."""
    lim, robot = p.limits, p.robot
    dv = max(lim.max_linear_accel_m_s2, lim.max_linear_decel_m_s2) * period_s(p)
    dw = lim.max_angular_accel_rad_s2 * period_s(p)
    wheel_rad_s = (dv + dw * robot.track_width_m / 2.0) / robot.wheel_radius_m
    return (p.output.pwm_max - p.output.pwm_trim) * wheel_rad_s / robot.max_wheel_rad_s + 1.0  # +1: whole us


def largest_step_us(samples: list[Sample]) -> int:
    return max((max(abs(a[1] - b[1]), abs(a[2] - b[2])) for a, b in itertools.pairwise(samples)), default=0)


def check_braked(rig: StopRig, from_s: float) -> tuple[float, float]:
    """From `from_s` the outputs ramp to trim at the limiter's deceleration, never up, never a step, then stay at
    trim. Returns (the speed the ramp began from, how long it took)."""
    p = rig.profile
    before = [s for s in rig.outputs if s[0] < from_s][-1]
    ramp = [before, *rig.since(from_s)]
    at_trim = next(i for i, s in enumerate(ramp) if s[1] == s[2] == TRIM)
    down = ramp[:at_trim + 1]
    assert all(b[1] <= a[1] and b[2] <= a[2] for a, b in itertools.pairwise(down))  # never back up
    assert largest_step_us(down) <= step_bound_us(p)  # the limiter's rate, not a step
    assert all(s[1] == s[2] == TRIM for s in ramp[at_trim:])  # and stays at trim
    v0 = speed_m_s(p, max(before[1], before[2]))
    took = down[-1][0] - from_s
    # A straight leg: the limiter's linear deceleration sets the time, to within one output period either way.
    assert took == pytest.approx(v0 / p.limits.max_linear_decel_m_s2, abs=period_s(p) + rig.ls.dt_s)
    return v0, took


def stops_within(rig: StopRig, from_s: float, bound_s: float) -> tuple[float, float]:
    """The rover truly stops within `bound_s` of `from_s`: (seconds it took, metres it went meanwhile)."""
    assert rig.run_until(rig.stopped, from_s + bound_s - rig.ls.t_s)
    assert len(rig.track) == len(rig.outputs) == len(rig.still)  # all kept every step
    i0 = next(i for i, s in enumerate(rig.outputs) if s[0] >= from_s)
    i1 = next(i for i in range(i0, len(rig.still)) if rig.still[i])
    return rig.outputs[i1][0] - from_s, sum(math.dist(a, b) for a, b in itertools.pairwise(rig.track[i0:i1 + 1]))


# -- the tests ------------------------------------------------------------------------------------------------


def test_a_stale_demand_in_auto_brakes_through_the_limiter_then_idles_and_the_mission_drives_on() -> None:
    """A ground station turns SERVO_OUTPUT_RAW off (SET_MESSAGE_INTERVAL -1) while HEARTBEAT goes on: no demand for
    [demand] timeout_s brakes at the limiter's deceleration, as a request timeout does; the bridge finds the
    stream slow and asks for it again, and the mission drives on from a standstill, never a step."""
    rig = on_a_mission()
    p = rig.profile
    try:
        t_cmd = rig.ls.t_s
        rig.ls.gcs.mav.command_long_send(1, 1, P.MAV_CMD_SET_MESSAGE_INTERVAL, 0, DEMAND, -1, 0, 0, 0, 0, 0)
        top_m_s = p.robot.max_wheel_rad_s * p.robot.wheel_radius_m
        rig.run(p.demand.timeout_s + top_m_s / p.limits.max_linear_decel_m_s2 + 0.5)  # time to brake from any speed
        demand = rig.sent(DEMAND)
        last = max(t for t in demand if t <= rig.ls.t_s)
        assert t_cmd - EPS_S <= last <= t_cmd + 0.1 and not [t for t in demand if last < t]  # the stream stopped
        braking = rig.said(BRAKING, t_cmd)
        due = last + p.demand.timeout_s
        assert braking and due - EPS_S <= braking[0] <= due + rig.ls.dt_s + EPS_S
        held = [s for s in rig.outputs if last < s[0] < braking[0]]
        assert held and all(s[1] > 1700 and s[2] > 1700 for s in held)  # until then, still the last demand
        v0, took = check_braked(rig, braking[0])
        assert all(s[3] > 1700 for s in rig.since(braking[0])[:20])  # the autopilot still asked to drive
        stop_s, stop_m = stops_within(rig, braking[0], v0 / p.limits.max_linear_decel_m_s2 + 2.0)
        # The bridge asks again (the stream slow for its rate window): the demand is back, taken from rest.
        resumed_from = rig.ls.t_s
        assert rig.run_until(lambda: rig.outputs[-1][1] > 1600, 15.0)
        assert any(t > last for t in rig.sent(DEMAND))
        assert largest_step_us(rig.since(resumed_from)) <= step_bound_us(p)
    finally:
        rig.close()
    print(f"\nstale demand in AUTO: braking {1000 * (braking[0] - last):.0f} ms after the last SERVO_OUTPUT_RAW, "
          f"{v0:.2f} m/s to trim in {1000 * took:.0f} ms; rover stopped {stop_s:.2f} s / {stop_m:.2f} m after; "
          f"driving again {rig.ls.t_s - t_cmd:.1f} s after the stream stopped")


def test_the_autopilots_heartbeat_lost_in_auto_is_neutral_at_once_and_held() -> None:
    """The autopilot's HEARTBEAT stops while the rest streams on (its demand too): at safety.heartbeat_timeout_s
    after the last one, neutral at once, held by overrides refreshed every period (not released: the passthrough
    outputs would follow the radio), whatever the demand says; the heartbeat back, the demand drives again from
    rest."""
    rig = on_a_mission()
    p = rig.profile
    try:
        t_cmd = rig.ls.t_s
        rig.emu.withheld.add(HEARTBEAT)
        last_hb = max(rig.sent(HEARTBEAT))
        rig.run(last_hb + p.safety.heartbeat_timeout_s + 2.0 - rig.ls.t_s)
        lost = rig.said(LOST, t_cmd)
        deadline = last_hb + p.safety.heartbeat_timeout_s
        assert lost and deadline - EPS_S <= lost[0] <= deadline + rig.ls.dt_s + EPS_S
        driving = [s for s in rig.outputs if t_cmd <= s[0] < lost[0]]
        assert driving and all(s[1] > 1600 and s[2] > 1600 for s in driving)  # silence alone is not yet a loss
        after = rig.since(lost[0] + rig.ls.dt_s)  # what the bridge sends lands in the emulator's next step
        assert all(s[1] == s[2] == TRIM for s in after)  # neutral at once: the first output after is trim
        assert all(s[3] > 1600 for s in after)  # while the autopilot's demand still says drive
        now_us = rig.emu.sim_time_us
        assert rig.emu.autopilot.has_override(1, now_us) and rig.emu.autopilot.has_override(3, now_us)
        assert rig.emu.rc_inputs[1] == rig.emu.rc_inputs[3] == TRIM  # held by fresh neutral overrides
        stop_s, stop_m = stops_within(rig, lost[0], 3.0)
        # The heartbeat back: the demand is taken again, from rest, at the limiter's pace.
        rig.emu.withheld.clear()
        back = rig.ls.t_s
        assert rig.run_until(lambda: rig.outputs[-1][1] > 1600, 5.0)
        assert largest_step_us(rig.since(back)) <= step_bound_us(p)
    finally:
        rig.close()
    print(f"\nheartbeat lost in AUTO: neutral {1000 * (lost[0] - last_hb):.0f} ms after the last HEARTBEAT; "
          f"rover stopped {stop_s:.2f} s / {stop_m:.2f} m after")


def test_the_link_to_the_autopilot_silent_in_auto_stops_and_the_stop_cannot_be_confirmed() -> None:
    """Nothing gets through either way (a cable pulled). The bridge brakes for the stale demand, then says the
    heartbeat lost, but none of it reaches the autopilot: its overrides lapse RC_OVERRIDE_TIME after the last
    one and the motors go to the radio's trim (ArduPilot's own stop, the shipped .parm's 1 s). A shutdown
    meanwhile cannot be confirmed, and the bridge says so."""
    rig = on_a_mission()
    p = rig.profile
    override_time_s = shipped_parm()["RC_OVERRIDE_TIME"]
    try:
        t_cmd = rig.ls.t_s
        last_demand, last_hb = max(rig.sent(DEMAND)), max(rig.sent(HEARTBEAT))
        rig.emu.scenario = dataclasses.replace(rig.emu.scenario, silences=(LinkSilence(t_cmd, math.inf),))
        held_pwm = rig.outputs[-1][1:3]
        rig.run(last_hb + p.safety.heartbeat_timeout_s + 1.0 - rig.ls.t_s)
        braking, lost = rig.said(BRAKING, t_cmd), rig.said(LOST, t_cmd)
        assert braking and braking[0] <= last_demand + p.demand.timeout_s + rig.ls.dt_s + EPS_S
        assert lost and lost[0] <= last_hb + p.safety.heartbeat_timeout_s + rig.ls.dt_s + EPS_S
        # The autopilot heard nothing: the last override holds for RC_OVERRIDE_TIME, then the radio's trim.
        held = [s for s in rig.outputs if t_cmd <= s[0] < t_cmd + override_time_s - 2 * period_s(p)]
        assert held and all(s[1:3] == held_pwm for s in held)
        assert all(s[1] == s[2] == TRIM for s in rig.since(t_cmd + override_time_s + rig.ls.dt_s))
        stop_s, stop_m = stops_within(rig, t_cmd, override_time_s + 3.0)
        rig.ls.stop(max_s=p.safety.stop_confirm_timeout_s + 0.5)
        assert rig.ls.core.stop_confirmed is False
        assert rig.said("RB: stop NOT confirmed by the autopilot", t_cmd)
    finally:
        rig.close()
    print(f"\nlink silent in AUTO: the bridge braking at +{1000 * (braking[0] - t_cmd):.0f} ms, heartbeat lost at "
          f"+{lost[0] - t_cmd:.2f} s (unheard); ArduPilot's overrides lapsed at RC_OVERRIDE_TIME "
          f"{override_time_s:.0f} s; "
          f"rover stopped {stop_s:.2f} s / {stop_m:.2f} m after the silence began; stop at exit not confirmed")


@pytest.mark.parametrize("require_armed", [True, False], ids=["shipped", "require_armed_off"])
def test_a_disarm_in_auto_stops_the_wheels(require_armed: bool) -> None:
    """A ground station disarms the rover mid-mission (MAV_CMD_COMPONENT_ARM_DISARM 0, forced with 21196):
    ArduPilot's demand goes to trim at once (disarmed, AP_MotorsUGV outputs trim) and the bridge, following it,
    brakes at the limiter's deceleration to neutral; ArduPilot's "Throttle disarmed" reaches the ground station
    through the bridge. With safety.require_armed (shipped) the bridge also goes DISARMED at the heartbeat that
    says so: neutral from then on, and says it; without it the trim demand alone stops the rover."""
    base = shipped_profile()
    profile = dataclasses.replace(base, safety=dataclasses.replace(base.safety, require_armed=require_armed))
    rig = on_a_mission(profile)
    p = rig.profile
    try:
        t_cmd = rig.ls.t_s
        rig.ls.gcs.mav.command_long_send(1, 1, P.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0)
        rig.run(3.0)
        disarmed = rig.said("Throttle disarmed", t_cmd)
        assert disarmed and disarmed[0] <= t_cmd + 2 * rig.ls.dt_s + EPS_S and not rig.emu.armed
        assert all(s[3] == TRIM for s in rig.since(disarmed[0] + 2 * rig.ls.dt_s))  # the demand: trim
        # The first trim demand is answered at once: the ramp starts within a demand period.
        first_down = next(s[0] for a, s in itertools.pairwise(rig.since(disarmed[0])) if s[1] < a[1])
        assert first_down <= disarmed[0] + 1.0 / p.demand.rate_hz + rig.ls.dt_s + EPS_S
        ours = rig.said(DISARMED, t_cmd)
        if require_armed:
            # Braking on the trim demand until the heartbeat says disarmed; from then on neutral at once.
            beat = min(t for t in rig.sent(HEARTBEAT) if t >= disarmed[0])
            assert ours == [pytest.approx(beat)]
            ramp = [s for s in rig.outputs if first_down - rig.ls.dt_s <= s[0] <= ours[0]]
            assert all(b[1] <= a[1] and b[2] <= a[2] for a, b in itertools.pairwise(ramp))
            assert largest_step_us(ramp) <= step_bound_us(p)
            assert all(s[1] == s[2] == TRIM for s in rig.since(ours[0] + rig.ls.dt_s))
            assert rig.ls.core.command.counters.get("state.disarmed") == 1
            v0, took = speed_m_s(p, ramp[0][1]), ours[0] + rig.ls.dt_s - ramp[0][0]
        else:
            v0, took = check_braked(rig, first_down - rig.ls.dt_s)
            assert ours == []  # require_armed off: the trim demand alone stops it, the bridge says nothing more
        stop_s, stop_m = stops_within(rig, disarmed[0], v0 / p.limits.max_linear_decel_m_s2 + 2.0)
    finally:
        rig.close()
    print(f"\ndisarm in AUTO (require_armed {'on, shipped' if require_armed else 'off'}): outputs ramping "
          f"{1000 * (first_down - disarmed[0]):.0f} ms after 'Throttle disarmed', {v0:.2f} m/s to trim in "
          f"{1000 * took:.0f} ms; rover stopped {stop_s:.2f} s / {stop_m:.2f} m after")


# -- handing the wheels over mid-mission ----------------------------------------------------------------------

HOLDING = "RB: autopilot in HOLD, braking, then neutral"


def switch_mode(rig: StopRig, mode: int) -> float:
    """A ground station's DO_SET_MODE through the bridge; when it was sent."""
    rig.ls.gcs.mav.command_long_send(1, 1, P.MAV_CMD_DO_SET_MODE, 0, P.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode,
                                     0, 0, 0, 0, 0)
    return rig.ls.t_s


def test_auto_to_manual_mid_mission_hands_the_wheels_to_the_gcs_without_a_jump() -> None:
    """Mid-mission at over 2 m/s a ground station switches to MANUAL while it streams a velocity request (0.5 m/s
    ahead, refused in AUTO): the motor outputs go from the autopilot's demand to the request at the limiter's
    pace, never a step, and the rover then drives at the request, straight."""
    rig = on_a_mission()
    p = rig.profile
    try:
        forward = rig.drive(0.5)
        rig.run(1.0, forward)
        assert rig.ls.core.command.counters.get("dropped.mode", 0) > 0  # in AUTO the request does not drive
        t_cmd = switch_mode(rig, MODE_MANUAL)
        rig.run(4.0, forward)
        assert rig.emu.mode == MODE_MANUAL and rig.said("RB: MANUAL: GCS requests drive", t_cmd)
        handover = rig.since(t_cmd - 1.0)
        assert largest_step_us(handover) <= step_bound_us(p)
        # Slowed to the request, never stopped on the way: the wheels' speed is measured late, so the loop holds
        # them at zero a little past the request (the integrator must not wind up backwards meanwhile).
        i0 = next(i for i, s in enumerate(rig.outputs) if s[0] >= t_cmd)
        slowest_m_s = min(math.dist(a, b) / rig.ls.dt_s for a, b in itertools.pairwise(rig.track[i0:]))
        assert slowest_m_s >= 0.5 * 0.5
        assert rig.emu.truth.v_m_s == pytest.approx(0.5, abs=0.05)
        assert abs(rig.emu.truth.yaw_rate_rad_s) < 0.05
    finally:
        rig.close()
    print(f"\nAUTO -> MANUAL mid-mission at {speed_m_s(p, handover[0][1]):.2f} m/s: largest output step "
          f"{largest_step_us(handover)} us (limiter bound {step_bound_us(p):.0f} us), slowest {slowest_m_s:.2f} m/s "
          f"on the way to the request's 0.5 m/s")


def test_auto_to_hold_mid_mission_brakes_to_a_stop_and_holds() -> None:
    """Mid-mission a ground station switches to HOLD (the autopilot's own demand then says stop too): the bridge
    says so, brakes at the limiter's deceleration to trim and holds it; the rover stops."""
    rig = on_a_mission()
    p = rig.profile
    try:
        t_cmd = switch_mode(rig, MODE_HOLD)
        rig.run(3.0)
        holding = rig.said(HOLDING, t_cmd)
        assert rig.emu.mode == MODE_HOLD and holding and holding[0] <= t_cmd + 0.1
        before = [s for s in rig.outputs if s[0] < holding[0]][-1]
        ramp = [before, *rig.since(holding[0])]
        at_trim = next(i for i, s in enumerate(ramp) if s[1] == s[2] == TRIM)
        v0, took = speed_m_s(p, max(before[1:3])), ramp[at_trim][0] - holding[0]
        # Braked by the wheel-speed loop along the limiter's ramp: no step beyond it, no push beyond where the
        # wheels were (the loop's map may differ from the demand's by a few microseconds), at the limiter's
        # deceleration or firmer where the motors lag it, then trim and held.
        assert largest_step_us(ramp[:at_trim + 1]) <= step_bound_us(p)
        assert all(max(s[1:3]) <= max(before[1:3]) + 5 for s in ramp)
        # (from where the loop's map put the wheels: up to those few microseconds above the demand's speed)
        assert took <= speed_m_s(p, max(before[1:3]) + 5) / p.limits.max_linear_decel_m_s2 + period_s(p) + rig.ls.dt_s
        stop_s, stop_m = stops_within(rig, t_cmd, v0 / p.limits.max_linear_decel_m_s2 + 2.0)
        rig.run(2.0)
        assert rig.stopped() and all(s[1] == s[2] == TRIM for s in ramp[at_trim:] + rig.since(ramp[-1][0]))
    finally:
        rig.close()
    print(f"\nAUTO -> HOLD mid-mission: braking {1000 * (holding[0] - t_cmd):.0f} ms after the command, "
          f"{v0:.2f} m/s to trim in {1000 * took:.0f} ms; rover stopped {stop_s:.2f} s / {stop_m:.2f} m after")
