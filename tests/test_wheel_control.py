"""The wheel speed loop and the wiring-fault detector on their own, then through the command core.

Units: wheel speeds in rad/s; the default profile's wheels top out at 20.944 rad/s (200 rpm).
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
import sys
import tomllib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.command.outputs import OutputMap, SpeedCurve
from rover_bridge.command.wheel_control import (
    HANDOVER_S,
    SpeedWindow,
    WheelSpeedLoop,
    WiringFault,
    WiringMonitor,
)
from rover_bridge.kinematics import MeasuredWheels, WheelSpeeds
from rover_bridge.params import ControlParams, Profile, profile_from_dict
from sitl import VehicleConfig

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_control as bench

TOP = Profile().robot.max_wheel_rad_s
RANGE = (-TOP, TOP)


def loop(**changes: float) -> WheelSpeedLoop:
    """The loop with these gains; kp and ki_1_s given alone stand for both motions (driving and turning). Its
    measurement is each sample alone (speed_window_s 0) unless given: the loop's own behaviour, sample by sample."""
    for name in ("kp", "ki_1_s"):
        if name in changes:
            changes.setdefault(f"turn_{name}", changes[name])
    changes.setdefault("speed_window_s", 0.0)
    return WheelSpeedLoop(dataclasses.replace(ControlParams(), **changes), RANGE, RANGE)  # type: ignore[arg-type]


def feed(lp: WheelSpeedLoop, t: float, left: float, right: float) -> None:
    lp.measure(MeasuredWheels(t, WheelSpeeds(left, right)), t)


def run(lp: WheelSpeedLoop, target: WheelSpeeds, measured: tuple[float, float], t0: float, seconds: float,
        **kw: bool) -> tuple[float, list[WheelSpeeds]]:
    """Constant measurement, outputs every 50 ms: the loop's own behaviour, no plant."""
    out = []
    t = t0
    for _ in range(round(seconds / 0.05)):
        t = round(t + 0.05, 9)
        feed(lp, t, *measured)
        out.append(lp.command(target, 0.05, t, **kw).command)
    return t, out


def test_feedforward_alone_when_the_wheels_do_what_they_are_told() -> None:
    lp = loop()
    _, out = run(lp, WheelSpeeds(10.0, 10.0), (10.0, 10.0), 0.0, 2.0)
    assert out[-1] == WheelSpeeds(pytest.approx(10.0, abs=1e-6), pytest.approx(10.0, abs=1e-6))
    assert lp.integral == [pytest.approx(0.0, abs=1e-6), pytest.approx(0.0, abs=1e-6)]


def test_a_weak_wheel_gets_more_command_through_the_integrator_up_to_its_limit() -> None:
    lp = loop(ki_1_s=10.0, integrator_max_fraction=0.25)
    _, out = run(lp, WheelSpeeds(8.0, 8.0), (6.0, 8.0), 0.0, 5.0)
    assert out[-1].left_rad_s > 10.0 and out[-1].right_rad_s == pytest.approx(8.0, abs=0.01)
    assert lp.integral[0] == pytest.approx(0.25 * TOP)  # clamped


def test_anti_windup_no_integration_while_saturated_and_both_wheels_scaled_together() -> None:
    lp = loop(ki_1_s=10.0)
    # The right wheel cannot reach 20 rad/s (it does 15): the loop asks for more than the top speed.
    _, out = run(lp, WheelSpeeds(10.0, 20.0), (10.0, 15.0), 0.0, 3.0)
    last = out[-1]
    assert last.right_rad_s == pytest.approx(TOP)
    assert last.left_rad_s < 10.0  # scaled down with the right one (one factor: the curvature is kept)
    assert lp.integral[1] < 0.25 * TOP  # stopped growing once saturated
    # Targets the kinematics already scaled down: the integrators do not grow either.
    lp2 = loop(ki_1_s=10.0)
    run(lp2, WheelSpeeds(10.0, 10.0), (8.0, 8.0), 0.0, 1.0, pre_scaled=True)
    assert lp2.integral == [0.0, 0.0]


def test_zero_targets_reset_and_never_kick_backwards() -> None:
    lp = loop()
    run(lp, WheelSpeeds(8.0, 8.0), (5.0, 5.0), 0.0, 1.0)
    assert lp.integral[0] > 0.0
    feed(lp, 1.05, 6.0, 6.0)
    assert lp.command(WheelSpeeds(0.0, 0.0), 0.05, 1.05).command == WheelSpeeds(0.0, 0.0)
    assert lp.integral == [0.0, 0.0]
    # Braking: the wheel is faster than its (smaller) target; the command never goes negative.
    lp2 = loop(kp=5.0)
    _, out = run(lp2, WheelSpeeds(1.0, 1.0), (8.0, 8.0), 0.0, 0.5)
    assert all(o.left_rad_s >= 0.0 and o.right_rad_s >= 0.0 for o in out)


def test_a_wheel_held_at_zero_does_not_wind_its_integrator_backwards() -> None:
    # A rover coasting down slower than the limiter ramps (a handover from the autopilot's demand at speed to a
    # slow request): the wheel is faster than its target for a while and the command is held at zero. Once it
    # is down to the target the command is the target again, not held at zero by a wound-up integrator.
    lp = loop(kp=1.0, ki_1_s=10.0)
    t, out = run(lp, WheelSpeeds(2.0, 2.0), (8.0, 8.0), 0.0, 1.0)
    assert out[-1].left_rad_s == 0.0  # held at zero (never the other direction)
    assert lp.integral[0] > -2.0  # it stopped winding once held at zero: less than the target
    feed(lp, t + 0.05, 2.0, 2.0)
    assert lp.command(WheelSpeeds(2.0, 2.0), 0.05, t + 0.05).command.left_rad_s > 0.0


def test_a_loop_taking_over_a_moving_wheel_cuts_it_no_faster_than_the_limiter_and_lets_it_grow() -> None:
    # The loop has just taken over moving wheels: when they run ahead of the target (a rover coasting down
    # slower than the limiter's ramp) its correction would cut the command at once; for HANDOVER_S it shrinks
    # by at most max_step_rad_s2 per second, then the loop corrects as hard as it asks. A command that grows
    # (a weak wheel behind its target) is not held back.
    lp = WheelSpeedLoop(dataclasses.replace(ControlParams(), kp=2.0, ki_1_s=0.0), RANGE, RANGE, max_step_rad_s2=40.0)
    t = 0.0
    out: list[tuple[float, float]] = []
    for _ in range(40):
        t = round(t + 0.05, 9)
        ahead = 5.0 if 0.3 < t <= 0.8 or t > HANDOVER_S + 0.3 else 0.0  # the wheels 5 rad/s faster than asked
        feed(lp, t, 15.0 + ahead, 15.0 + ahead)
        out.append((t, lp.command(WheelSpeeds(15.0, 15.0), 0.05, t).command.left_rad_s))
    steps = [(t, a - b) for (_, a), (t, b) in itertools.pairwise(out)]
    assert all(d <= 40.0 * 0.05 + 1e-9 for t, d in steps if t <= HANDOVER_S)
    assert max(d for t, d in steps if t <= HANDOVER_S) == pytest.approx(40.0 * 0.05)  # it did bind
    assert max(d for t, d in steps if t > HANDOVER_S) > 2 * 40.0 * 0.05  # then free
    weak = WheelSpeedLoop(dataclasses.replace(ControlParams(), kp=2.0), RANGE, RANGE, max_step_rad_s2=40.0)
    grown = []
    for i in range(6):
        feed(weak, 0.05 * (i + 1), 2.0, 2.0)  # a stalled-looking weak wheel far behind 8 rad/s
        grown.append(weak.command(WheelSpeeds(8.0, 8.0), 0.05, 0.05 * (i + 1)).command.left_rad_s)
    assert max(b - a for a, b in itertools.pairwise(grown)) > 40.0 * 0.05  # growth is not slewed


def test_stale_encoders_hold_the_learnt_correction_and_resume_without_a_jump() -> None:
    lp = loop(encoder_timeout_s=0.5, ki_1_s=5.0, kp=1.0)
    t, out = run(lp, WheelSpeeds(8.0, 8.0), (7.5, 7.5), 0.0, 1.0)
    before, learnt, held = out[-1], list(lp.integral), lp.wheel_integral()
    assert 1.0 < held[0] < lp.i_max  # the loop learnt a correction for the slow wheels (not clamped)
    stale = lp.command(WheelSpeeds(8.0, 8.0), 0.05, t + 0.6)
    assert not stale.closed and stale.command == WheelSpeeds(8.0 + held[0], 8.0 + held[1])  # target + what it learnt
    assert stale.command.left_rad_s <= before.left_rad_s + 1e-9  # no P on an old measurement: not harder
    other = copy.deepcopy(lp)
    slower = other.command(WheelSpeeds(4.0, 4.0), 0.05, t + 0.65)  # the correction scales with the target ...
    assert slower.command.left_rad_s == pytest.approx(4.0 + 0.5 * held[0])
    faster = other.command(WheelSpeeds(12.0, 12.0), 0.05, t + 0.7)  # ... and never grows past what it was
    assert faster.command.left_rad_s == pytest.approx(12.0 + held[0])
    backwards = other.command(WheelSpeeds(-4.0, -4.0), 0.05, t + 0.75)  # ... and turns with it
    assert backwards.command.left_rad_s == pytest.approx(-4.0 - 0.5 * held[0])
    assert lp.command(WheelSpeeds(8.0, 8.0), 0.05, t + 0.7).command == stale.command
    assert lp.integral == learnt == other.integral  # not reset, not grown
    feed(lp, t + 0.75, 7.5, 7.5)  # the first sample after the silence spans it: not a measurement
    assert not lp.command(WheelSpeeds(8.0, 8.0), 0.05, t + 0.75).closed and lp.integral == learnt
    feed(lp, t + 0.8, 7.5, 7.5)
    resumed = lp.command(WheelSpeeds(8.0, 8.0), 0.05, t + 0.8)
    assert resumed.closed and abs(resumed.command.left_rad_s - before.left_rad_s) < 0.5


def test_an_overdue_measurement_is_not_acted_on_before_the_encoders_are_stale() -> None:
    lp = loop(encoder_timeout_s=0.5)
    t, _ = run(lp, WheelSpeeds(8.0, 8.0), (7.5, 7.5), 0.0, 1.0)  # a sample every 50 ms
    held = list(lp.integral)
    one_lost = lp.command(WheelSpeeds(8.0, 8.0), 0.05, t + 0.1)  # one sample missing: still acted on
    assert one_lost.closed and lp.integral[0] > held[0]
    grown = list(lp.integral)
    # 150 ms without a sample (more than 2.5 intervals), still fresh: hold, the integrators frozen, even on a
    # ramp of the target (P on the old measurement would push harder as the reference moved away from it).
    for k in range(1, 6):
        overdue = lp.command(WheelSpeeds(8.0 + k, 8.0 + k), 0.05, t + 0.1 + 0.05 * k)
        assert overdue.closed and lp.integral == grown
        assert overdue.command.left_rad_s == pytest.approx(8.0 + k + grown[0])


def test_a_stalled_wheel_does_not_wind_up() -> None:
    lp = loop()
    t, _ = run(lp, WheelSpeeds(8.0, 8.0), (8.0, 8.0), 0.0, 1.0)
    _, out = run(lp, WheelSpeeds(8.0, 8.0), (0.0, 8.0), t, 3.0)  # left held still for 3 s
    assert lp.integral[0] < 8.0 * 15.0 * 0.05  # integrated only until it was seen stalled (at once)
    assert out[-1].left_rad_s < 8.0 + 1.5 * 8.0  # reference reseeded: no P on a full error


def test_slip_freezes_the_integrators() -> None:
    lp = loop()
    run(lp, WheelSpeeds(8.0, 8.0), (6.0, 6.0), 0.0, 1.0, freeze=True)
    assert lp.integral == [0.0, 0.0]


@settings(derandomize=True, deadline=None, max_examples=200)
@given(left=st.floats(-30, 30), right=st.floats(-30, 30), ml=st.floats(-30, 30), mr=st.floats(-30, 30))
def test_the_command_stays_in_range_keeps_direction_and_curvature(left: float, right: float, ml: float,
                                                                 mr: float) -> None:
    lp = loop(kp=3.0)
    target = WheelSpeeds(left, right).desaturate(TOP)
    feed(lp, 0.05, ml, mr)
    out = lp.command(target, 0.05, 0.05).command
    assert abs(out.left_rad_s) <= TOP + 1e-9 and abs(out.right_rad_s) <= TOP + 1e-9
    for o, t in ((out.left_rad_s, target.left_rad_s), (out.right_rad_s, target.right_rad_s)):
        assert o * t >= 0.0  # never the other way
        if t == 0.0:
            assert o == 0.0 or (target.left_rad_s, target.right_rad_s) != (0.0, 0.0)


def test_the_speed_window_averages_the_distance_over_its_span_and_restarts_after_a_gap() -> None:
    w = SpeedWindow(0.1, max_interval_s=0.5)
    assert w.update(MeasuredWheels(1.0, WheelSpeeds(0.0, 0.0))) is None  # the first: its span is not known
    assert w.update(MeasuredWheels(1.02, WheelSpeeds(10.0, 0.0))) == WheelSpeeds(10.0, 0.0)
    # ArduPilot's send-time stamps: a message with no new encoder reading, then one with two.
    assert w.update(MeasuredWheels(1.04, WheelSpeeds(0.0, 0.0))) == WheelSpeeds(5.0, 0.0)
    both = w.update(MeasuredWheels(1.06, WheelSpeeds(20.0, 0.0)))
    assert both is not None and both.left_rad_s == pytest.approx(10.0) and w.interval_s == pytest.approx(0.02)
    for k in range(4, 9):  # the window keeps the newest samples spanning at least 0.1 s
        w.update(MeasuredWheels(1.0 + 0.02 * k, WheelSpeeds(4.0, 0.0)))
    assert w.value is not None and w.value.left_rad_s == pytest.approx(4.0) and w.span_s == pytest.approx(0.1)
    assert w.update(MeasuredWheels(5.0, WheelSpeeds(3.0, 3.0))) is None  # the mean over a gap: not a speed
    assert w.update(MeasuredWheels(5.05, WheelSpeeds(4.0, 4.0))) == WheelSpeeds(4.0, 4.0)  # starts again
    assert w.update(MeasuredWheels(1.0, WheelSpeeds(2.0, 2.0))) is None  # a clock restart


# ------------------------------------------------------------------ wiring faults


def monitor() -> WiringMonitor:
    return WiringMonitor(ControlParams(fault_time_s=1.0), RANGE, RANGE)


@pytest.mark.parametrize(("target", "measured", "fault"), [
    ((10.0, 10.0), (-8.0, 10.0), WiringFault("left", "backwards")),
    ((10.0, 10.0), (10.0, 0.0), WiringFault("right", "still")),
    ((12.0, 7.0), (7.0, 12.0), WiringFault("both", "swapped")),
    ((-9.0, 9.0), (9.0, -9.0), WiringFault("both", "swapped")),
    ((8.0, 8.0), (8.0, 19.0), WiringFault("right", "runaway")),
])
def test_each_wiring_fault_is_named_after_it_lasted(target: tuple[float, float], measured: tuple[float, float],
                                                   fault: WiringFault) -> None:
    m = monitor()
    t, m_speeds = WheelSpeeds(*target), WheelSpeeds(*measured)
    assert m.check(t, m_speeds, 0.0) is None
    assert m.check(t, m_speeds, 0.9) is None
    assert m.check(t, m_speeds, 1.0) == fault
    assert all(len(text) <= 50 for text in fault.texts)


def test_no_fault_for_small_commands_or_when_it_clears_in_time() -> None:
    m = monitor()
    assert m.check(WheelSpeeds(2.0, 2.0), WheelSpeeds(0.0, 0.0), 0.0) is None  # below fault_min_fraction
    assert m.check(WheelSpeeds(2.0, 2.0), WheelSpeeds(0.0, 0.0), 5.0) is None
    m.check(WheelSpeeds(10.0, 10.0), WheelSpeeds(0.0, 10.0), 6.0)
    m.check(WheelSpeeds(10.0, 10.0), WheelSpeeds(5.0, 10.0), 6.5)  # it started turning
    assert m.check(WheelSpeeds(10.0, 10.0), WheelSpeeds(0.0, 10.0), 7.2) is None  # a new episode begins


def test_a_measured_curve_is_the_feedforward_and_defines_the_range() -> None:
    curve = SpeedCurve((1000.0, 1300.0, 1460.0, 1540.0, 1700.0, 2000.0), (-16.0, -9.0, 0.0, 0.0, 9.0, 17.0))
    out = OutputMap("rc_override", 1, 3, 1000, 1500, 2000, TOP, left_curve=curve)
    assert out.speed_range(left=True) == (-16.0, 17.0) and out.speed_range(left=False) == RANGE
    pwm = out.to_pwm(WheelSpeeds(9.0, 10.0))
    assert pwm.left_us == 1700 and pwm.right_us == round(1500 + 500 * 10.0 / TOP)
    assert out.to_pwm(WheelSpeeds(0.001, 0.0)).left_us == 1540  # the deadband's edge, not trim + a little
    assert out.to_pwm(WheelSpeeds(0.0, 0.0)).left_us == 1500


# ------------------------------------------------------------------ through the command core, on the emulator
# (benchmarks/bench_control.py's lockstep rig: the whole core and the emulator, no sockets)


@pytest.fixture(scope="module")
def calibrated() -> Profile:
    """The closed loop as `rover-bridge calibrate` leaves it on the weak, curved motor: its PWM maps and the gains
    its rule gives for the lags and delays it measured (the sequence in lockstep on the same vehicle)."""
    cal, _ = bench.calibrate(bench.bench_profile("closed_loop"))
    assert cal.result is not None and cal.result.tuning is not None, cal.error
    patched = bench.bench_profile("closed_loop")
    data = tomllib.loads(cal.result.patch_toml())
    return profile_from_dict({"control": {"mode": "closed_loop", **data["control"]}, "robot": data["robot"],
                              "estimator": {"stream_rate_hz": patched.estimator.stream_rate_hz}})


def test_closed_loop_drives_a_weak_curved_motor_at_the_requested_speed_and_open_loop_does_not(
        calibrated: Profile) -> None:
    opened = bench.straight(bench.bench_profile("open_loop"))
    assert opened["speed_error_pct"] < -20.0 and opened["heading_drift_deg"] > 20.0
    # Uncalibrated (the default gains: integrator only, slow): the speed right, the heading drifting while the
    # integrator finds the weak wheel's command, far less than open loop's.
    closed = bench.straight(bench.bench_profile("closed_loop"))
    assert abs(closed["speed_error_pct"]) < 3.0 and closed["heading_drift_deg"] < 12.0
    tuned = bench.straight(calibrated)
    assert abs(tuned["speed_error_pct"]) < 1.0 and tuned["heading_drift_deg"] < 1.0


@pytest.mark.parametrize("tuned", [False, True], ids=["default gains", "calibrated"])
def test_closed_loop_step_stall_and_spin_targets(tuned: bool, calibrated: Profile) -> None:
    profile = calibrated if tuned else bench.bench_profile("closed_loop")
    step = bench.step_response(profile)
    # Slower is fine until calibrated; overshoot is not.
    assert step["t90_s"] < (1.0 if tuned else 2.0) and step["overshoot_pct"] <= 10.0
    assert bench.stall(profile)["overshoot_pct"] <= 10.0
    spin = bench.spin(profile)
    assert abs(spin["yaw_rate_error_pct"]) < 5.0 and spin["max_abs_v_m_s"] < 0.03
    load = bench.load_recovery(profile)
    assert load["recovered_s"] < 1.5


def _faulty(vehicle: VehicleConfig, **profile: object) -> bench.Rig:
    rig = bench.Rig(profile_from_dict({"control": {"mode": "closed_loop"}, **profile}), vehicle)
    rig.start()
    rig.drive(3.0, 0.5, 0.0)
    return rig


@pytest.mark.parametrize(("vehicle", "profile", "first_line"), [
    (VehicleConfig(start_armed=True, left_reversed=True), {}, "RB: FAULT left wheel turns backwards"),
    (VehicleConfig(start_armed=True), {"encoders": {"right_reversed": True}}, "RB: FAULT right wheel turns backwards"),
    (VehicleConfig(start_armed=True, left_function=53, right_function=51), {}, None),  # swapped: a spin shows it
    (VehicleConfig(start_armed=True, left_function=0), {}, "RB: FAULT left wheel does not turn"),
])
def test_wiring_faults_on_the_emulator_stop_the_rover_and_say_what_to_check(
        vehicle: VehicleConfig, profile: dict[str, object], first_line: str | None) -> None:
    rig = _faulty(vehicle, **profile)
    if first_line is None:  # swapped channels look right driving straight: a spin tells them apart
        rig.drive(3.0, 0.0, 3.0)  # fast enough for the check: 9 rad/s per wheel
        first_line = "RB: FAULT wheels swapped (or both reversed)"
    assert first_line in rig.texts, rig.texts
    assert rig.core.command.state.value == "fault"
    rig.drive(1.0, 0.5, 0.0)  # requests keep coming: refused, the rover stands
    assert abs(rig.emu.truth.v_m_s) < 0.02 and math.isfinite(rig.emu.truth.x_m)
    assert rig.core.command.counters["dropped.fault"] >= 5
    rig.emu.set_armed(False)  # the operator disarms: the fault is cleared
    rig.drive(1.5)
    assert rig.core.command.state.value != "fault"


def test_slip_compensation_holds_the_wheel_targets_until_slip_ends_and_can_be_turned_off() -> None:
    from rover_bridge.command.core import CommandCore
    from rover_bridge.mavlink.dialect import mavlink
    from rover_bridge.mavlink.identity import Identity
    from rover_bridge.mavlink.report import Reporter
    from rover_bridge.mavlink.wire import Incoming, Link

    def run(compensate: bool) -> tuple[list[int], list[str], CommandCore]:
        # Open loop isolates the hold (the closed loop would also answer the fake, instant wheel speeds).
        prof = profile_from_dict({"control": {"slip_compensation": compensate, "mode": "open_loop"}})
        ident = Identity.from_profile(prof)
        core = CommandCore(prof, ident, Reporter(ident))
        ap = mavlink.MAVLink(None, 1, 1)
        gcs = mavlink.MAVLink(None, 255, 190)
        hb = mavlink.MAVLink_heartbeat_message(10, 3, mavlink.MAV_MODE_FLAG_SAFETY_ARMED | 1, 15, 4, 3)
        core.handle(Incoming(Link.AUTOPILOT, ap.decode(bytearray(hb.pack(ap)))), 0.0)
        pwm, texts = [], []
        t = 0.0
        for i in range(40):  # 2 s: a request every 0.1 s ramping the rover up at the limiter's 1 m/s^2
            t = 0.05 * (i + 1)
            core.on_wheels(MeasuredWheels(t, WheelSpeeds(*(2 * [core.commanded.v_m_s / 0.05]))), t)
            core.set_slipping(0.5 <= t < 1.5)
            if i % 2 == 0:
                req = mavlink.MAVLink_set_position_target_local_ned_message(0, 1, 1, 8, 0b0101_1100_0111, 0, 0, 0,
                                                                            0.8, 0, 0, 0, 0, 0, 0, 0)
                out = list(core.handle(Incoming(Link.GCS, gcs.decode(bytearray(req.pack(gcs)))), t).out)
            else:
                out = core.tick(t)
            texts += [o.msg.text for o in out if o.msg.get_type() == "STATUSTEXT"]
            pwm += [int(o.msg.chan1_raw) for o in out if o.msg.get_type() == "RC_CHANNELS_OVERRIDE"]
        return pwm, texts, core

    held, texts, core = run(True)
    during = held[len(held) * 12 // 40: len(held) * 28 // 40]  # about t 0.6 .. 1.4 s
    assert max(during) - min(during) <= 2  # held: no further acceleration while slipping
    assert held[-1] > max(during) + 20  # released when the wheels and the gyro agree again
    assert "RB: wheel slip: holding wheel speeds" in texts and core.counters["slip.limited"] == 1
    free, _, _ = run(False)
    assert free[len(free) * 28 // 40] > max(during) + 20  # off: it kept accelerating


def test_silent_encoders_never_push_a_weak_curved_motor_harder_and_the_loop_returns_cleanly() -> None:
    """Left motor 20 % weak, a 40 us deadband, speed = command^1.5 (bench_control's rover), straight at
    0.5 m/s in closed loop; WHEEL_DISTANCE stops for 2 s while ATTITUDE and the rest go on."""
    from rover_bridge.command.outputs import OutputMap
    from rover_bridge.kinematics import DiffDrive, Twist2D

    profile = bench.bench_profile("closed_loop")
    rig = bench.Rig(profile)
    rig.start()
    rig.drive(4.0, 0.5)
    start, end = rig.t + 1.0, rig.t + 3.0
    emu_step, log = rig.emu.step, rig.emu.sent_log
    assert log is not None

    def muted_step(dt_s: float = bench.STEP_S) -> None:  # the emulator's WHEEL_DISTANCE lost in the window
        n = len(log)
        emu_step(dt_s)
        log[n:] = [(t, m) for t, m in log[n:] if not (m.get_type() == "WHEEL_DISTANCE" and start <= t < end)]

    rig.emu.step = muted_step  # type: ignore[method-assign]
    trace: list[tuple[float, int, int, float]] = []  # (time, left / right PWM above trim, true speed)

    def sample(r: bench.Rig) -> None:
        pwm = r.core.command.last_wheel_pwm
        assert pwm is not None
        trace.append((r.t, pwm.left_us - 1500, pwm.right_us - 1500, r.emu.truth.v_m_s))

    rig.drive(6.0, 0.5, sample=sample)
    open_loop = OutputMap.from_profile(profile).to_pwm(DiffDrive.from_params(profile.robot).to_wheel_speeds(
        Twist2D(0.5, 0.0)))
    for k, open_us in ((1, open_loop.left_us - 1500), (2, open_loop.right_us - 1500)):
        before = max(row[k] for row in trace if start - 1.0 <= row[0] < start)
        during = max(row[k] for row in trace if start <= row[0] < end + 0.1)  # until a sample is acted on
        assert during <= max(before + 50, open_us + 100), (k, during, before, open_us)
        assert before > open_us + 50  # the loop was compensating this wheel: the case that matters
    speeds_during = [v for t, _, _, v in trace if start <= t < end]
    assert all(abs(v - 0.5) <= 0.1 for v in speeds_during), (min(speeds_during), max(speeds_during))
    after = [v for t, _, _, v in trace if t >= end]
    assert max(after) <= 0.55  # no overshoot above 10 %
    assert all(abs(v - 0.5) <= 0.015 for t, _, _, v in trace if t >= end + 2.0)  # back within 3 % in 2 s
    assert "RB: no wheel encoders: feedforward only" in rig.texts  # said once, and the return too
    assert rig.texts.count("RB: wheel encoders back: speed loop closed") >= 1
