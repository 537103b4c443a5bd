"""Protocol tests of the command core: messages and times in, exact messages out.

Geometry of the default profile: wheel radius 0.05 m, track 0.30 m, max_wheel_rpm 200
(= 20.944 rad/s at full PWM), PWM 1000/1500/2000, left on RC channel 1, right on channel 3.
PWM values below are computed by hand from those numbers:
    left = (v - omega * 0.15) / 0.05, right = (v + omega * 0.15) / 0.05   (omega counter-clockwise)
    pwm = 1500 + 500 * wheel / 20.944, rounded
Most tests use a profile with very high acceleration limits so that the first output already
carries the requested twist; the ramp tests use the default limits.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Sequence

import pytest

from rover_bridge.app.composition import BridgeCore
from rover_bridge.command.core import CommandCore, CommandState
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Incoming, Link, Outgoing, Reaction
from rover_bridge.params import LimitsParams, Profile

VEL_YAW_RATE = 1479  # use vx, vy, vz, yaw_rate
VEL_ONLY = 3527  # use vx, vy, vz
VEL_YAW = 2503  # use vx, vy, vz, yaw
ACCEL_ONLY = 3135
IGNORE = 65535  # ch1-8 "leave alone"
PERIOD_S = 0.05  # default rate_hz = 20

FAST = LimitsParams(max_linear_accel_m_s2=100.0, max_linear_decel_m_s2=100.0, max_angular_accel_rad_s2=500.0)


def profile(fast: bool = True, **sections: object) -> Profile:
    # Open loop unless a test says otherwise: these tests feed no wheel encoders, and the closed loop would
    # add its "no wheel encoders" report (its own tests are in test_wheel_control.py).
    p = dataclasses.replace(Profile(), control=dataclasses.replace(Profile().control, mode="open_loop"))
    if fast:
        p = dataclasses.replace(p, limits=FAST)
    for name, changes in sections.items():
        p = dataclasses.replace(p, **{name: dataclasses.replace(getattr(p, name), **changes)})  # type: ignore[arg-type]
    return p


class Rig:
    """A CommandCore with an autopilot (1/1) and a ground station (255/190), on a simulated clock."""

    def __init__(self, prof: Profile | None = None) -> None:
        self.profile = prof or profile()
        self.identity = Identity.from_profile(self.profile)
        self.reporter = Reporter(self.identity)
        self.core = CommandCore(self.profile, self.identity, self.reporter)
        self.ap = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self.sent: list[tuple[float, Outgoing]] = []

    @staticmethod
    def wire(mav: mavlink.MAVLink, msg: MAVLinkMessage) -> MAVLinkMessage:
        """Pack and decode, as the shell would hand it over (source ids set, floats rounded to float32)."""
        return mav.decode(bytearray(msg.pack(mav)))

    def feed(self, link: Link, msg: MAVLinkMessage, t: float) -> Reaction:
        reaction = self.core.handle(Incoming(link, msg), t)
        self.sent += [(t, o) for o in reaction.out]
        return reaction

    def heartbeat(self, t: float, armed: bool = True, mode: int = 15) -> Reaction:
        base_mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if armed:
            base_mode |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        msg = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER,
                                                mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode, mode,
                                                mavlink.MAV_STATE_ACTIVE, 3)
        return self.feed(Link.AUTOPILOT, self.wire(self.ap, msg), t)

    def attitude(self, t: float, yaw_cw_rad: float) -> Reaction:
        msg = mavlink.MAVLink_attitude_message(int(t * 1000), 0.0, 0.0, yaw_cw_rad, 0.0, 0.0, 0.0)
        return self.feed(Link.AUTOPILOT, self.wire(self.ap, msg), t)

    def local(self, t: float, frame: int = 8, mask: int = VEL_YAW_RATE, vx: float = 0.0, vy: float = 0.0,
              yaw: float = 0.0, yaw_rate: float = 0.0, target: tuple[int, int] = (1, 1),
              src: mavlink.MAVLink | None = None) -> Reaction:
        msg = mavlink.MAVLink_set_position_target_local_ned_message(
            0, target[0], target[1], frame, mask, 0.0, 0.0, 0.0, vx, vy, 0.0, 0.0, 0.0, 0.0, yaw, yaw_rate)
        return self.feed(Link.GCS, self.wire(src or self.gcs, msg), t)

    def global_int(self, t: float, frame: int, vx: float, vy: float) -> Reaction:
        msg = mavlink.MAVLink_set_position_target_global_int_message(
            0, 1, 1, frame, VEL_ONLY, 0, 0, 0.0, vx, vy, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        return self.feed(Link.GCS, self.wire(self.gcs, msg), t)

    def manual(self, t: float, x: int, r: int, target: int = 1) -> Reaction:
        msg = mavlink.MAVLink_manual_control_message(target, x, 0, 500, r, 0)
        return self.feed(Link.GCS, self.wire(self.gcs, msg), t)

    def ack(self, t: float, result: int, target: tuple[int, int] = (255, 191)) -> Reaction:
        msg = mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_DO_SET_SERVO, result, 0, 0, *target)
        return self.feed(Link.AUTOPILOT, self.wire(self.ap, msg), t)

    def run_until(self, t_end: float, t: float,
                  heartbeat_every_s: float | None = 1.0) -> list[tuple[float, Outgoing]]:
        """Tick at the core's deadlines from `t` to `t_end`; autopilot heartbeats on a 1 s grid if asked."""
        out: list[tuple[float, Outgoing]] = []
        every = heartbeat_every_s
        next_hb = None if every is None else (math.floor(t / every) + 1) * every
        while True:
            deadline = self.core.next_deadline_s(t)
            if next_hb is not None and next_hb <= min(deadline, t_end):
                t = next_hb
                reaction = self.heartbeat(t)
                out += [(t, o) for o in reaction.out]
                next_hb += heartbeat_every_s  # type: ignore[operator]
                continue
            if deadline > t_end:
                return out
            t = max(t, deadline)
            ticked = self.core.tick(t)
            self.sent += [(t, o) for o in ticked]
            out += [(t, o) for o in ticked]


Sent = Sequence[tuple[float, Outgoing]] | Sequence[Outgoing]


def state(rig: Rig) -> CommandState:
    return rig.core.state


def overrides(out: Sent) -> list[tuple[int, int]]:
    """(ch1, ch3) of every RC_CHANNELS_OVERRIDE, checking the rest of the message on the way."""
    msgs = [o[1] if isinstance(o, tuple) else o for o in out]
    result = []
    for o in msgs:
        if o.msg.get_type() != "RC_CHANNELS_OVERRIDE":
            continue
        assert (o.dest, o.src_system, o.src_component) == (Link.AUTOPILOT, 255, 191)
        assert (o.msg.target_system, o.msg.target_component) == (1, 1)
        chans = [int(getattr(o.msg, f"chan{i}_raw")) for i in range(1, 19)]
        assert chans[1] == IGNORE and chans[3:8] == [IGNORE] * 5 and chans[8:] == [0] * 10
        result.append((chans[0], chans[2]))
    return result


def texts(out: Sent) -> list[str]:
    msgs = [o[1] if isinstance(o, tuple) else o for o in out]
    return [o.msg.text for o in msgs if o.msg.get_type() == "STATUSTEXT"]


def ready(prof: Profile | None = None, armed: bool = True) -> Rig:
    rig = Rig(prof)
    rig.heartbeat(0.0, armed=armed)
    return rig


# ------------------------------------------------------------------ before any request


def test_nothing_is_sent_before_the_vehicle_is_known_and_requests_are_forwarded() -> None:
    rig = Rig()
    assert rig.run_until(2.0, 0.0, heartbeat_every_s=None) == []
    reaction = rig.local(2.0, vx=0.5)
    assert reaction == Reaction(consumed=False, out=())
    assert rig.core.counters["forwarded.vehicle_unknown"] == 1
    assert state(rig) is CommandState.WAITING


def test_only_neutral_at_the_refresh_rate_before_the_first_request() -> None:
    rig = Rig()
    first = rig.heartbeat(0.0)
    assert overrides(first.out) == [(1500, 1500)]
    assert texts(first.out) == ["RB: idle, wheels neutral"]
    out = rig.run_until(2.001, 0.0)  # a hair past 2.0: the grid is a float sum of 0.05 steps
    ticks = [t for t, o in out if o.msg.get_type() == "RC_CHANNELS_OVERRIDE"]
    assert set(overrides(out)) == {(1500, 1500)}
    assert len(ticks) == 40  # 0.05, 0.10, ... 2.00
    assert all(b - a == pytest.approx(PERIOD_S) for a, b in itertools.pairwise(ticks))
    assert state(rig) is CommandState.IDLE


def test_late_ticks_do_not_slow_the_refresh_rate() -> None:
    # A real loop wakes a little after each deadline; the refresh must stay on its grid, not drift
    # by the lateness every period (3 ms late at 20 Hz would otherwise give 18.9 Hz).
    rig = Rig()
    rig.heartbeat(0.0)
    t, next_heartbeat = 0.0, 1.0
    ticks: list[float] = []
    while t < 10.0:
        t = rig.core.next_deadline_s(t) + 0.003
        if t >= next_heartbeat:  # keep the autopilot link alive
            rig.heartbeat(t)
            next_heartbeat += 1.0
        ticks += [t for o in rig.core.tick(t) if o.msg.get_type() == "RC_CHANNELS_OVERRIDE"]
    assert len(ticks) == pytest.approx(10.0 / PERIOD_S, abs=1)
    assert all(b - a == pytest.approx(PERIOD_S, abs=1e-9) for a, b in itertools.pairwise(ticks))


# ------------------------------------------------------------------ immediate reaction, frames, signs


@pytest.mark.parametrize("frame", [8, 9, 12])
def test_body_request_acted_on_at_once_with_exact_pwm(frame: int) -> None:
    rig = ready()
    reaction = rig.local(0.01, frame=frame, vx=0.5, yaw_rate=0.3)
    # omega = -0.3: left = (0.5 + 0.045) / 0.05 = 10.9 -> 1760.2; right = 9.1 -> 1717.2
    assert reaction.consumed
    assert overrides(reaction.out) == [(1760, 1717)]
    assert texts(reaction.out) == ["RB: active, driving"]
    assert state(rig) is CommandState.ACTIVE
    assert rig.core.last_wheel_pwm is not None
    assert (rig.core.last_wheel_pwm.left_us, rig.core.last_wheel_pwm.right_us) == (1760, 1717)
    assert rig.core.commanded.v_m_s == pytest.approx(0.5)
    assert rig.core.commanded.omega_rad_s == pytest.approx(-0.3)


def test_positive_yaw_rate_makes_the_right_wheel_slower() -> None:
    rig = ready()
    (left, right), = overrides(rig.local(0.01, vx=0.3, yaw_rate=0.5).out)
    assert left > right > 1500


def test_spin_in_place_drives_the_wheels_in_opposite_directions() -> None:
    rig = ready()
    # yaw_rate +1 (clockwise): left = 0.15 / 0.05 = 3 rad/s -> 1571.6; right -3 -> 1428.4
    assert overrides(rig.local(0.01, vx=0.0, yaw_rate=1.0).out) == [(1572, 1428)]
    rig2 = ready()
    assert overrides(rig2.local(0.01, vx=0.0, yaw_rate=-1.0).out) == [(1428, 1572)]


def test_negative_body_vx_drives_backwards() -> None:
    rig = ready()
    # -0.5 m/s: both wheels -10 rad/s -> 1500 - 238.7 = 1261.3
    assert overrides(rig.local(0.01, vx=-0.5, mask=VEL_ONLY).out) == [(1261, 1261)]


def test_mavproxy_velocity_command_drives_straight() -> None:
    rig = ready()
    # 0.5 m/s: both wheels 10 rad/s -> 1500 + 238.7 = 1738.7
    assert overrides(rig.local(0.01, frame=8, mask=4039, vx=0.5).out) == [(1739, 1739)]


@pytest.mark.parametrize("frame", [1, 7])
def test_local_ned_velocity_east_with_yaw_north_turns_right(frame: int) -> None:
    rig = ready()
    rig.attitude(0.0, 0.0)  # facing north
    # heading error +pi/2, kp 2 -> yaw rate cw pi, limited to 3 -> omega -3; speed * cos(pi/2) = 0.
    # left = 0.45 / 0.05 = 9 rad/s -> 1714.9; right -9 -> 1285.1
    assert overrides(rig.local(0.01, frame=frame, mask=VEL_ONLY, vx=0.0, vy=0.5).out) == [(1715, 1285)]


@pytest.mark.parametrize("frame", [5, 6, 11])
def test_global_int_velocity_is_an_earth_frame(frame: int) -> None:
    rig = ready()
    rig.attitude(0.0, math.pi / 2)  # already facing east: straight on at 0.5 m/s
    assert overrides(rig.global_int(0.01, frame, 0.0, 0.5).out) == [(1739, 1739)]


def test_earth_velocity_behind_turns_the_rover_instead_of_reversing() -> None:
    rig = ready()
    rig.attitude(0.0, 0.1)  # facing just right of north; request due south: turn right, no speed yet
    assert overrides(rig.local(0.01, frame=1, mask=VEL_ONLY, vx=-0.5).out) == [(1715, 1285)]


def test_heading_controller_follows_the_reported_yaw() -> None:
    rig = ready()
    rig.attitude(0.0, 0.0)
    rig.local(0.01, frame=1, mask=VEL_ONLY, vy=0.5)
    rig.attitude(0.02, math.pi / 2)  # now facing east
    rig.local(0.03, frame=1, mask=VEL_ONLY, vy=0.5)
    out = rig.run_until(0.08, 0.03)
    assert overrides(out) == [(1739, 1739)]


def test_heading_request_without_attitude_is_rejected() -> None:
    rig = ready()
    reaction = rig.local(0.01, frame=1, mask=VEL_ONLY, vy=0.5)
    assert reaction.consumed and overrides(reaction.out) == []
    assert texts(reaction.out) == ["RB: rejected no_attitude from 255:190"]
    assert rig.core.counters["rejected.no_attitude"] == 1


def test_stale_attitude_during_motion_brakes() -> None:
    rig = ready(profile(fast=False))
    rig.attitude(0.0, math.pi / 2)
    rig.local(0.01, frame=1, mask=VEL_ONLY, vy=0.5)
    t = 0.01
    while t < 0.9:  # keep the request fresh, let the yaw go stale (attitude_timeout_s = 1.0)
        t += 0.1
        rig.local(t, frame=1, mask=VEL_ONLY, vy=0.5)
    assert state(rig) is CommandState.ACTIVE
    rig.local(1.01, frame=1, mask=VEL_ONLY, vy=0.5)
    assert state(rig) is CommandState.BRAKING


def test_manual_control_scaling_and_sign() -> None:
    rig = ready()
    # x = 1000 -> 0.5 m/s -> 1739 both
    assert overrides(rig.manual(0.01, 1000, 0).out) == [(1739, 1739)]
    # r = +1000 -> 1.5 rad/s clockwise -> omega -1.5: left 4.5 rad/s -> 1607.4, right 1392.6
    assert overrides(rig.manual(0.02, 0, 1000).out) == [(1607, 1393)]


def test_manual_control_for_another_vehicle_is_forwarded() -> None:
    rig = ready()
    assert rig.manual(0.01, 1000, 0, target=2) == Reaction(consumed=False, out=())
    assert rig.core.counters["forwarded.not_for_vehicle"] == 1


def test_lateral_velocity_noted_once_per_source() -> None:
    rig = ready()
    first = rig.local(0.01, mask=VEL_ONLY, vx=0.5, vy=0.2)
    assert overrides(first.out) == [(1739, 1739)]
    assert "RB: lateral_ignored (255:190)" in texts(first.out)
    assert texts(rig.local(0.02, mask=VEL_ONLY, vx=0.5, vy=0.2).out) == []
    assert rig.core.counters["note.lateral_ignored"] == 2


# ------------------------------------------------------------------ invalid requests


def test_non_finite_requests_are_rejected_counted_and_only_neutral_reaches_the_wheels() -> None:
    rig = ready()
    r1 = rig.local(0.01, vx=math.nan, yaw_rate=0.1)
    r2 = rig.local(0.02, vx=0.5, yaw_rate=math.inf)
    r3 = rig.local(0.03, vx=-math.inf, mask=VEL_ONLY)
    assert r1.consumed and r2.consumed and r3.consumed
    assert texts(r1.out) == ["RB: rejected non_finite from 255:190"]
    assert texts(r2.out) == [] and texts(r3.out) == []  # reported once per source
    assert overrides(r1.out + r2.out + r3.out) == []
    out = rig.run_until(1.0, 0.03)
    assert set(overrides(rig.sent)) == {(1500, 1500)}
    assert overrides(out)
    assert rig.core.counters["rejected.non_finite"] == 3
    assert state(rig) is CommandState.IDLE


# Position-only requests are targets now ("go there"): tests/test_goto.py.
@pytest.mark.parametrize(("mask", "reason"), [(ACCEL_ONLY, "acceleration_only")])
def test_unsupported_requests_reported_once_per_source(mask: int, reason: str) -> None:
    rig = ready()
    other = mavlink.MAVLink(None, srcSystem=254, srcComponent=1)
    assert texts(rig.local(0.01, mask=mask).out) == [f"RB: rejected {reason} from 255:190"]
    assert texts(rig.local(0.02, mask=mask).out) == []
    assert texts(rig.local(0.03, mask=mask, src=other).out) == [f"RB: rejected {reason} from 254:1"]
    assert rig.core.counters[f"rejected.{reason}"] == 3
    assert set(overrides(rig.sent)) == {(1500, 1500)}


def test_malformed_request_never_raises() -> None:
    rig = ready()
    msg = Rig.wire(rig.gcs, mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, 8, VEL_ONLY, 0, 0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0))
    msg.vx = "fast"
    reaction = rig.feed(Link.GCS, msg, 0.01)
    assert reaction.consumed and overrides(reaction.out) == []
    assert rig.core.counters["rejected.malformed"] == 1


def test_manual_control_out_of_range_rejected() -> None:
    rig = ready()
    assert rig.manual(0.01, 1001, 0).consumed
    assert rig.core.counters["rejected.manual_out_of_range"] == 1
    assert state(rig) is CommandState.IDLE


# ------------------------------------------------------------------ target filtering


@pytest.mark.parametrize(("target", "consumed"), [
    ((1, 0), True), ((1, 1), True), ((1, 191), True), ((1, 50), False), ((2, 1), False), ((0, 0), False),
])
def test_requests_consumed_only_when_addressed(target: tuple[int, int], consumed: bool) -> None:
    rig = ready()
    reaction = rig.local(0.01, vx=0.5, target=target)
    assert reaction.consumed is consumed
    assert (overrides(reaction.out) == [(1739, 1739)]) is consumed


def test_configured_vehicle_id_filters_before_any_heartbeat() -> None:
    rig = Rig(profile(mavlink={"vehicle_system_id": 7}))
    assert rig.local(0.0, vx=0.5, target=(1, 1)).consumed is False
    reaction = rig.local(0.0, vx=0.5, target=(7, 1))
    assert reaction.consumed and overrides(reaction.out) == []  # no autopilot heartbeat yet: dropped
    assert rig.core.counters["dropped.link_lost"] == 1


def test_requests_from_the_autopilot_side_are_not_ours() -> None:
    rig = ready()
    msg = Rig.wire(rig.gcs, mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, 8, VEL_ONLY, 0, 0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0))
    assert rig.feed(Link.AUTOPILOT, msg, 0.01) == Reaction(consumed=False, out=())


def test_override_source_system_is_the_profile_setting() -> None:
    rig = ready(profile(output={"override_source_system": 200}))
    (o,) = [o for o in rig.local(0.01, vx=0.5).out if o.msg.get_type() == "RC_CHANNELS_OVERRIDE"]
    assert (o.src_system, o.src_component) == (200, 191)


# ------------------------------------------------------------------ refresh, timeout ramp


def test_outputs_refreshed_at_rate_while_streaming() -> None:
    rig = ready(profile(fast=False))
    t = 0.0
    stamps = []
    while t < 2.0:  # requests at 7 Hz, off the output grid
        rig.local(t + 0.013, vx=0.4)
        stamps += [s for s, o in rig.sent[-1:] if o.msg.get_type() == "RC_CHANNELS_OVERRIDE"]
        rig.run_until(t + 1 / 7, t + 0.013)
        t += 1 / 7
    stamps = [s for s, o in rig.sent if o.msg.get_type() == "RC_CHANNELS_OVERRIDE"]
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    assert max(gaps) <= PERIOD_S + 1e-9
    assert state(rig) is CommandState.ACTIVE


def test_timeout_ramps_down_monotonically_to_exactly_neutral() -> None:
    rig = ready(profile(fast=False))
    t = 0.01
    while t < 1.0:  # stream 0.5 m/s for ~1 s (0.5 s to accelerate at 1 m/s^2)
        rig.local(t, vx=0.5, mask=VEL_ONLY)
        rig.run_until(t + 0.1, t)
        t += 0.1
    last_request_s = t - 0.1
    assert overrides(rig.sent)[-1] == (1739, 1739)
    out = rig.run_until(last_request_s + 2.0, t)
    stamped = [(s, pwm) for (s, o), pwm in zip(
        [(s, o) for s, o in out if o.msg.get_type() == "RC_CHANNELS_OVERRIDE"], overrides(out), strict=True)]
    lefts = [pwm[0] for _, pwm in stamped]
    assert all(b <= a for a, b in itertools.pairwise(lefts)), lefts
    assert all(left == right for _, (left, right) in stamped)
    deadline = last_request_s + 0.5 + 0.5 / 2.0 + PERIOD_S
    assert all(pwm == (1500, 1500) for s, pwm in stamped if s >= deadline)
    assert any(pwm[0] > 1500 for s, pwm in stamped if s > last_request_s + 0.5)  # it did ramp, not jump
    assert texts(out) == ["RB: no request, braking to a stop", "RB: idle, wheels neutral"]
    assert state(rig) is CommandState.IDLE
    assert rig.core.counters["state.braking"] == 1


def test_a_stalled_loop_does_not_allow_a_jump() -> None:
    rig = ready(profile(fast=False))
    rig.run_until(0.5, 0.0)
    reaction = rig.local(0.9, vx=0.5, mask=VEL_ONLY)  # 0.35 s since the last output
    # dt capped at one period: v = 1 m/s^2 * 0.05 s = 0.05 m/s -> 1 rad/s -> 1523.9
    assert overrides(reaction.out) == [(1524, 1524)]


# ------------------------------------------------------------------ link loss, armed gating


def test_link_loss_goes_neutral_and_only_a_fresh_request_resumes() -> None:
    rig = ready()
    for t in [k / 10 for k in range(1, 30)] + [2.95]:  # the autopilot's heartbeat at 0.0 is its last one
        rig.local(t, vx=0.5, mask=VEL_ONLY)
        rig.core.tick(t)
    assert state(rig) is CommandState.ACTIVE
    lost = rig.core.tick(3.0)
    assert overrides(lost) == [(1500, 1500)]
    assert texts(lost) == ["RB: autopilot heartbeat lost, neutral"]
    assert state(rig) is CommandState.LINK_LOST
    during = rig.local(3.05, vx=0.5, mask=VEL_ONLY)
    assert during.consumed and overrides(during.out) == []
    assert rig.core.counters["dropped.link_lost"] == 1
    back = rig.heartbeat(3.1)  # the request of 2.95 is younger than the timeout, yet must not drive
    assert overrides(back.out) == [(1500, 1500)] and texts(back.out) == ["RB: idle, wheels neutral"]
    out = rig.run_until(4.0, 3.1)
    assert set(overrides(out)) == {(1500, 1500)}
    assert overrides(rig.local(4.02, vx=0.5, mask=VEL_ONLY).out) == [(1739, 1739)]  # a fresh one does


def test_disarmed_holds_neutral_and_arming_needs_a_fresh_request() -> None:
    rig = ready(armed=False)
    assert state(rig) is CommandState.DISARMED
    reaction = rig.local(0.01, vx=0.5, mask=VEL_ONLY)
    assert reaction.consumed and overrides(reaction.out) == []
    assert rig.core.counters["dropped.disarmed"] == 1
    armed = rig.heartbeat(0.02, armed=True)
    assert overrides(armed.out) == [(1500, 1500)] and texts(armed.out) == ["RB: idle, wheels neutral"]
    assert overrides(rig.local(0.03, vx=0.5, mask=VEL_ONLY).out) == [(1739, 1739)]
    disarm = rig.heartbeat(0.04, armed=False)  # mid-motion: neutral at once, in the same call
    assert overrides(disarm.out) == [(1500, 1500)]
    assert texts(disarm.out) == ["RB: autopilot disarmed, neutral"]
    assert rig.core.commanded.v_m_s == 0.0
    rearm = rig.heartbeat(0.1, armed=True)  # the request of 0.03 is still young, yet must not drive
    assert overrides(rearm.out) == [(1500, 1500)]
    assert set(overrides(rig.run_until(0.5, 0.1))) == {(1500, 1500)}


def test_require_armed_off_drives_while_disarmed() -> None:
    rig = ready(profile(safety={"require_armed": False}), armed=False)
    assert overrides(rig.local(0.01, vx=0.5, mask=VEL_ONLY).out) == [(1739, 1739)]


def test_heartbeats_of_other_systems_do_not_keep_the_link() -> None:
    rig = ready()
    gcs_hb = Rig.wire(rig.gcs, mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))
    rig.feed(Link.AUTOPILOT, gcs_hb, 2.9)
    rig.core.tick(3.0)
    assert state(rig) is CommandState.LINK_LOST


def vehicle_heartbeat(src: tuple[int, int], mode: int = 15, armed: bool = True) -> MAVLinkMessage:
    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
    msg = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                            base, mode, mavlink.MAV_STATE_ACTIVE, 3)
    return Rig.wire(mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1]), msg)


def test_another_component_of_the_vehicle_is_not_its_autopilot() -> None:
    rig = ready()
    rig.heartbeat(0.5)
    assert overrides(rig.local(0.51, vx=0.5).out) == [(1739, 1739)]
    # A forged (or corrupted) vehicle heartbeat from another component: disarmed, HOLD. Not the autopilot's word.
    rig.feed(Link.AUTOPILOT, vehicle_heartbeat((1, 57), mode=4, armed=False), 0.52)
    assert state(rig) is CommandState.ACTIVE and rig.core.vehicle.armed
    for t in (1.5, 2.5, 3.4):  # nor does it keep the link alive
        rig.feed(Link.AUTOPILOT, vehicle_heartbeat((1, 57)), t)
    rig.core.tick(3.5)
    assert state(rig) is CommandState.LINK_LOST
    rig.feed(Link.AUTOPILOT, vehicle_heartbeat((1, 57)), 3.6)  # nor, heard twice, does it lose its place
    assert state(rig) is CommandState.LINK_LOST and rig.identity.autopilot_component_id == 1
    rig.heartbeat(3.7)
    assert state(rig) is CommandState.IDLE


def test_a_forged_first_heartbeat_lasts_only_until_it_falls_silent() -> None:
    rig = Rig()
    rig.feed(Link.AUTOPILOT, vehicle_heartbeat((57, 3)), 0.0)  # the first vehicle heartbeat: learnt
    assert rig.identity.vehicle_system_id == 57
    for t in (0.5, 1.5, 2.5):
        rig.heartbeat(t)  # the real autopilot (1:1), shut out while the other one counts as alive
    assert rig.identity.vehicle_system_id == 57 and rig.core.vehicle.last_heartbeat_s == 0.0
    rig.core.tick(3.0)
    assert state(rig) is CommandState.LINK_LOST
    rig.heartbeat(3.5)  # the other one is lost: the next vehicle heartbeat takes its place
    assert (rig.identity.vehicle_system_id, rig.identity.autopilot_component_id) == (1, 1)
    assert state(rig) is CommandState.IDLE
    assert overrides(rig.local(3.6, vx=0.5).out) == [(1739, 1739)]  # addressed to 1:1 (overrides checks)
    rig.feed(Link.AUTOPILOT, vehicle_heartbeat((57, 3)), 3.7)  # while the autopilot is alive: nobody
    assert rig.identity.vehicle_system_id == 1 and state(rig) is CommandState.ACTIVE


def test_a_forged_first_heartbeat_read_by_both_cores_is_still_one_frame() -> None:
    core = BridgeCore(profile())
    core.handle(Incoming(Link.AUTOPILOT, vehicle_heartbeat((57, 3))), 0.0)  # the command and estimate cores
    for t in (0.5, 1.5, 2.5):
        core.handle(Incoming(Link.AUTOPILOT, vehicle_heartbeat((1, 1))), t)
    core.tick(3.0)
    assert core.command.state is CommandState.LINK_LOST and core.identity.vehicle_system_id == 57
    core.handle(Incoming(Link.AUTOPILOT, vehicle_heartbeat((1, 1))), 3.5)
    assert core.identity.vehicle_system_id == 1 and core.command.state is CommandState.IDLE


def test_with_a_configured_system_id_only_its_components_take_a_lost_autopilots_place() -> None:
    rig = Rig(profile(mavlink={"vehicle_system_id": 1}))
    rig.feed(Link.AUTOPILOT, vehicle_heartbeat((1, 57)), 0.0)  # the system's first vehicle heartbeat: 1:57
    rig.heartbeat(0.5)
    assert rig.identity.autopilot_component_id == 57 and rig.core.vehicle.last_heartbeat_s == 0.0
    rig.core.tick(3.0)
    rig.feed(Link.AUTOPILOT, vehicle_heartbeat((2, 1)), 3.2)  # another system: never the configured vehicle
    rig.heartbeat(3.5)
    assert (rig.identity.vehicle_system_id, rig.identity.autopilot_component_id) == (1, 1)
    assert state(rig) is CommandState.IDLE


# ------------------------------------------------------------------ servo mode


def servo_cmds(out: tuple[Outgoing, ...] | list[Outgoing]) -> list[tuple[float, float]]:
    result = []
    for o in out:
        if o.msg.get_type() == "COMMAND_LONG":
            assert o.msg.command == 183 and (o.msg.target_system, o.msg.target_component) == (1, 1)
            assert (o.dest, o.src_system, o.src_component) == (Link.AUTOPILOT, 255, 191)
            result.append((o.msg.param1, o.msg.param2))
    return result


def test_servo_mode_commands_each_wheel_and_tracks_acks() -> None:
    rig = ready(profile(output={"mode": "servo"}))
    reaction = rig.local(0.01, vx=0.5, yaw_rate=0.3)
    assert servo_cmds(reaction.out) == [(1.0, 1760.0), (3.0, 1717.0)]
    assert rig.ack(0.02, mavlink.MAV_RESULT_ACCEPTED) == Reaction(consumed=True, out=())
    assert rig.core.counters["servo.accepted"] == 1
    # an ack for somebody else's command is not ours
    assert rig.ack(0.02, mavlink.MAV_RESULT_FAILED, target=(255, 190)).consumed is False
    assert state(rig) is CommandState.ACTIVE


def test_servo_refusal_is_reported_and_stops_the_wheels() -> None:
    rig = ready(profile(output={"mode": "servo"}))
    rig.local(0.01, vx=0.5, yaw_rate=0.3)
    refused = rig.ack(0.02, mavlink.MAV_RESULT_FAILED)
    assert refused.consumed
    assert texts(refused.out) == ["RB: DO_SET_SERVO result 4", "RB: DO_SET_SERVO refused, neutral"]
    assert servo_cmds(refused.out) == [(1.0, 1500.0), (3.0, 1500.0)]
    assert state(rig) is CommandState.REFUSED
    assert rig.core.counters["servo.refused"] == 1
    out = rig.run_until(0.5, 0.02)
    assert set(servo_cmds([o for _, o in out])) == {(1.0, 1500.0), (3.0, 1500.0)}
    assert state(rig) is CommandState.REFUSED
    assert servo_cmds(rig.local(0.5, vx=0.5, yaw_rate=0.3).out) == [(1.0, 1760.0), (3.0, 1717.0)]


def test_servo_shutdown_sends_trim_on_both_outputs() -> None:
    rig = ready(profile(output={"mode": "servo"}))
    rig.local(0.01, vx=0.5, mask=VEL_ONLY)
    out = rig.core.shutdown(0.02)
    assert servo_cmds(out) == [(1.0, 1500.0), (3.0, 1500.0)]
    assert [o.msg.get_type() for o in out] == ["COMMAND_LONG", "COMMAND_LONG", "TIMESYNC", "STATUSTEXT"]


# ------------------------------------------------------------------ shutdown


def test_shutdown_sends_neutral_then_release_on_ch1_8() -> None:
    rig = ready()
    rig.local(0.01, vx=0.5, mask=VEL_ONLY)
    out = rig.core.shutdown(0.02)
    assert [o.msg.get_type() for o in out] == ["RC_CHANNELS_OVERRIDE", "RC_CHANNELS_OVERRIDE", "TIMESYNC",
                                              "STATUSTEXT"]
    chans = [[int(getattr(o.msg, f"chan{i}_raw")) for i in range(1, 19)] for o in out[:2]]
    assert chans[0] == [1500, IGNORE, 1500, IGNORE, IGNORE, IGNORE, IGNORE, IGNORE] + [0] * 10
    assert chans[1] == [0, IGNORE, 0, IGNORE, IGNORE, IGNORE, IGNORE, IGNORE] + [0] * 10
    assert all((o.src_system, o.src_component, o.dest) == (255, 191, Link.AUTOPILOT) for o in out[:3])
    assert out[2].msg.tc1 == 0  # a TIMESYNC request: the autopilot answers it after parsing the two above
    assert texts(out) == ["RB: stopping, neutral sent, confirming"]
    assert state(rig) is CommandState.STOPPING and not rig.core.stop_settled
    # The answer (tc1 set, ts1 echoed) confirms the stop; nothing is sent after it.
    answer = Rig.wire(rig.ap, mavlink.MAVLink_timesync_message(tc1=123, ts1=out[2].msg.ts1))
    reaction = rig.feed(Link.AUTOPILOT, answer, 0.05)
    assert reaction.consumed and texts(reaction.out) == ["RB: stopped, autopilot confirmed release"]
    assert rig.core.stop_settled and rig.core.stop_confirmed is True
    assert rig.core.tick(0.5) == [] and rig.core.shutdown(0.6) == []
    assert rig.local(0.7, vx=0.5) == Reaction(consumed=False, out=())


def test_an_unanswered_stop_is_resent_then_given_up_and_said() -> None:
    rig = ready()
    rig.local(0.01, vx=0.5, mask=VEL_ONLY)
    first = rig.core.shutdown(0.02)
    resend_s = rig.core.next_deadline_s(0.02)
    assert resend_s == pytest.approx(0.12)  # the first resend
    assert rig.core.tick(0.05) == []
    resent = rig.core.tick(resend_s)
    assert [o.msg.get_type() for o in resent] == ["RC_CHANNELS_OVERRIDE", "RC_CHANNELS_OVERRIDE", "TIMESYNC"]
    assert resent[2].msg.ts1 != first[2].msg.ts1  # a new probe each time: any answer counts
    # Someone else's TIMESYNC (the autopilot's own request, or an answer to a GCS) is not ours.
    for msg in (mavlink.MAVLink_timesync_message(tc1=0, ts1=first[2].msg.ts1),
                mavlink.MAVLink_timesync_message(tc1=5, ts1=77)):
        assert not rig.feed(Link.AUTOPILOT, Rig.wire(rig.ap, msg), 0.15).consumed
    assert not rig.feed(Link.GCS, Rig.wire(rig.gcs, mavlink.MAVLink_timesync_message(5, first[2].msg.ts1)),
                        0.16).consumed  # only the autopilot's answer proves the autopilot's parse
    assert rig.core.tick(rig.core.next_deadline_s(0.2)) and not rig.core.stop_settled
    out = rig.core.tick(rig.core.next_deadline_s(0.3))
    assert texts(out) == ["RB: stop NOT confirmed by the autopilot"]
    assert rig.core.stop_settled and rig.core.stop_confirmed is False
    assert rig.core.counters["stop.sent"] == 3 and rig.core.counters["stop.unconfirmed"] == 1


def test_an_answer_to_an_earlier_probe_confirms_too() -> None:
    rig = ready()
    first = rig.core.shutdown(0.02)
    rig.core.tick(rig.core.next_deadline_s(0.02))  # resent: probe 2 in flight
    late = Rig.wire(rig.ap, mavlink.MAVLink_timesync_message(tc1=9, ts1=first[-2].msg.ts1))
    assert rig.feed(Link.AUTOPILOT, late, 0.13).consumed and rig.core.stop_confirmed is True


def test_shutdown_release_on_ch9_18() -> None:
    rig = ready(profile(output={"left_channel": 9, "right_channel": 10}))
    rig.local(0.01, vx=0.5, mask=VEL_ONLY)
    out = rig.core.shutdown(0.02)
    chans = [[int(getattr(o.msg, f"chan{i}_raw")) for i in range(1, 19)] for o in out[:2]]
    assert chans[0] == [IGNORE] * 8 + [1500, 1500] + [0] * 8
    assert chans[1] == [IGNORE] * 8 + [65534, 65534] + [0] * 8


def test_shutdown_before_the_vehicle_is_known_sends_no_override() -> None:
    rig = Rig()
    assert [o.msg.get_type() for o in rig.core.shutdown(0.0)] == ["STATUSTEXT"]
    assert rig.core.stop_settled and rig.core.stop_confirmed is None  # nothing to wait for


# ------------------------------------------------------------------ HOLD ([modes] stop)


def drive_with_requests(rig: Rig, t0: float, t1: float, vx: float) -> list[tuple[float, Outgoing]]:
    """A GCS streaming a request every 0.1 s from t0 to t1, the core ticked at its deadlines between."""
    out: list[tuple[float, Outgoing]] = []
    t = t0
    while t < t1 - 1e-9:
        out += [(t, o) for o in rig.local(t, vx=vx, mask=VEL_ONLY).out]
        out += rig.run_until(min(t + 0.1, t1) - 1e-9, t, heartbeat_every_s=None)
        t = round(t + 0.1, 9)
    return out


def test_hold_brakes_to_a_stop_holds_neutral_and_needs_a_fresh_request_after_it() -> None:
    rig = ready(profile(fast=False))
    drive_with_requests(rig, 0.0, 1.0, 0.5)
    assert rig.core.commanded.v_m_s == pytest.approx(0.5)
    reaction = rig.heartbeat(1.0, mode=mavlink.ROVER_MODE_HOLD)
    assert state(rig) is CommandState.HOLD and rig.core.request is None
    assert texts(reaction.out) == ["RB: autopilot in HOLD, braking, then neutral"]
    # Requests still streaming are refused (said once per source), the limiter brakes at max decel.
    out = drive_with_requests(rig, 1.0, 1.5, 0.5)
    assert rig.core.counters["dropped.hold"] == 5
    assert sum("in HOLD, request from 255:190 ignored" in t for t in texts(out)) == 1
    pwm = [left for left, _ in overrides(out)]
    assert pwm[0] < 1500 + 500 * 0.5 / 0.05 / 20.944 and pwm[-1] == 1500  # ramped down, then neutral
    assert all(a >= b for a, b in itertools.pairwise(pwm))  # never back up
    assert rig.core.commanded.v_m_s == 0.0
    # Back in GUIDED: the old request does not resume; a fresh one drives.
    rig.heartbeat(2.0, mode=15)
    assert state(rig) is CommandState.IDLE
    assert overrides(rig.core.tick(2.05)) == [(1500, 1500)]
    rig.local(2.1, vx=0.5, mask=VEL_ONLY)
    assert state(rig) is CommandState.ACTIVE


def _set_mode(rig: Rig, t: float, mode: int, via: str = "COMMAND_LONG") -> Reaction:
    custom = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if via == "SET_MODE":
        msg = mavlink.MAVLink_set_mode_message(1, custom, mode)
    else:
        msg = mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, custom, mode, 0, 0, 0, 0, 0)
    return rig.feed(Link.GCS, Rig.wire(rig.gcs, msg), t)


@pytest.mark.parametrize("via", ["COMMAND_LONG", "SET_MODE"])
def test_a_gcs_asking_for_hold_stops_at_once_before_the_heartbeat_reports_it(via: str) -> None:
    rig = ready()
    rig.local(0.01, vx=0.5, mask=VEL_ONLY)
    reaction = _set_mode(rig, 0.1, mavlink.ROVER_MODE_HOLD, via)
    assert not reaction.consumed  # forwarded to the autopilot, which decides
    assert state(rig) is CommandState.HOLD and "HOLD" in texts(reaction.out)[0]
    rig.heartbeat(0.5, mode=15)  # a heartbeat already in flight still says GUIDED: HOLD stays
    assert state(rig) is CommandState.HOLD
    rig.heartbeat(1.0, mode=mavlink.ROVER_MODE_HOLD)  # reported: from now on the heartbeat governs
    rig.heartbeat(2.0, mode=15)
    assert state(rig) is CommandState.IDLE


def test_a_refused_or_never_reported_hold_request_lets_the_heartbeat_govern_again() -> None:
    rig = ready()
    _set_mode(rig, 0.1, mavlink.ROVER_MODE_HOLD)
    refused = mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_RESULT_FAILED, 0, 0,
                                                 255, 190)
    rig.feed(Link.AUTOPILOT, Rig.wire(rig.ap, refused), 0.15)
    rig.heartbeat(0.2, mode=15)
    assert state(rig) is CommandState.IDLE
    _set_mode(rig, 1.0, mavlink.ROVER_MODE_HOLD)
    rig.heartbeat(1.5, mode=15)
    assert state(rig) is CommandState.HOLD
    rig.heartbeat(2.6, mode=15)  # 1.6 s later and still not reported: the autopilot's word wins
    assert state(rig) is CommandState.IDLE
    assert _set_mode(rig, 3.0, 15).out == () and state(rig) is CommandState.IDLE  # not a stop mode


def test_only_the_autopilots_own_ack_can_refuse_a_hold() -> None:
    rig = ready()
    _set_mode(rig, 0.1, mavlink.ROVER_MODE_HOLD)
    refused = mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_RESULT_FAILED, 0, 0,
                                                 255, 190)
    for src in ((1, 57), (2, 1)):  # another component of the vehicle, another system: forged or not, not its word
        rig.feed(Link.AUTOPILOT, Rig.wire(mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1]), refused),
                 0.15)
    rig.heartbeat(0.2, mode=15)  # perhaps sent before the autopilot read the request
    assert state(rig) is CommandState.HOLD
    rig.feed(Link.AUTOPILOT, Rig.wire(rig.ap, refused), 0.3)  # the autopilot's own
    rig.heartbeat(0.4, mode=15)
    assert state(rig) is CommandState.IDLE


def test_stop_modes_are_a_parameter() -> None:
    rig = ready(profile(modes={"stop": (), "gcs": (0, 1, 3, 4, 15)}))
    rig.heartbeat(0.02, mode=mavlink.ROVER_MODE_HOLD)
    rig.local(0.03, vx=0.5, mask=VEL_ONLY)
    assert state(rig) is CommandState.ACTIVE  # HOLD is not a stop mode here: requests drive in it
    rig = ready(profile(modes={"stop": (11,), "autopilot": (10,)}))  # RTL
    rig.heartbeat(0.02, mode=11)
    assert state(rig) is CommandState.HOLD


# ------------------------------------------------------------------ through the composed BridgeCore


def test_composed_core_consumes_the_request_and_shuts_down_neutral_then_release() -> None:
    core = BridgeCore(profile())
    ap = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    hb = Rig.wire(ap, mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
        mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 15, mavlink.MAV_STATE_ACTIVE, 3))
    assert core.handle(Incoming(Link.AUTOPILOT, hb), 0.0).consumed is False
    req = Rig.wire(gcs, mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, 8, VEL_YAW_RATE, 0, 0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0.3))
    reaction = core.handle(Incoming(Link.GCS, req), 0.01)
    assert reaction.consumed
    assert overrides(reaction.out) == [(1760, 1717)]
    out = core.shutdown(0.02)
    rc = [o for o in out if o.msg.get_type() == "RC_CHANNELS_OVERRIDE"]
    assert overrides(rc) == [(1500, 1500), (0, 0)]
    assert out.index(rc[0]) < out.index(rc[1])


# ------------------------------------------------------------------ a request shows in its answer

def test_a_request_just_after_an_output_still_moves_the_wheels_by_a_period_of_the_limits() -> None:
    # At the default 1 m/s^2 and 20 Hz, 1 ms of acceleration is 0.001 m/s: the same PWM. The answer steps
    # the limiter one period instead (0.05 m/s), so the request shows in the override that answers it.
    rig = ready(profile(fast=False))
    for k in range(30):  # a GCS streaming 0.2 m/s at 10 Hz: cruising
        rig.local(k * 0.1, vx=0.2, mask=VEL_ONLY)
        rig.run_until(k * 0.1 + 0.1, k * 0.1, heartbeat_every_s=1.0)
    assert rig.core.commanded.v_m_s == pytest.approx(0.2)
    last_output = max(t for t, o in rig.sent if o.msg.get_type() == "RC_CHANNELS_OVERRIDE")
    before = overrides(rig.sent)[-1]
    answer = rig.local(last_output + 0.001, vx=0.3, mask=VEL_ONLY)
    after = overrides(answer.out)
    assert len(after) == 1 and after[0][0] > before[0] and after[0][1] > before[1]
    assert rig.core.commanded.v_m_s == pytest.approx(0.2 + 1.0 * PERIOD_S)


def test_a_burst_of_requests_runs_the_command_at_most_one_period_ahead_of_the_limits() -> None:
    rig = ready(profile(fast=False))
    t = 0.0
    for _ in range(300):  # a request every millisecond for 0.3 s, from standstill
        t = round(t + 0.001, 6)
        rig.local(t, vx=0.8, mask=VEL_ONLY)
        assert rig.core.commanded.v_m_s <= 1.0 * (t + PERIOD_S) + 1e-9  # accel 1 m/s^2, one period early at most
        if rig.core.next_deadline_s(t) <= t:
            rig.core.tick(t)
    assert rig.core.commanded.v_m_s >= 1.0 * t - 1e-9  # and never behind the limit
