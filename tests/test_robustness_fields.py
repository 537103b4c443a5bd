"""Every numeric field of every accepted message at NaN, +-inf, extremes and out-of-range values.

The whole pure BridgeCore is set up so that a valid request WOULD drive (armed vehicle, fresh attitude,
wheel and gyro streams running). Then one message with one poisoned field arrives:
- a velocity request is rejected with a counted reason (`rejected.<reason>`), no request is held
  and every wheel output stays neutral;
- an estimator input is either rejected and counted, or harmless; the pose and every ODOMETRY
  field stay finite, and a valid request afterwards still drives normally (nothing latched).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from typing import Any

import pytest

from rover_bridge.app.composition import BridgeCore
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.wire import Incoming, Link, Outgoing
from rover_bridge.params import Profile

P = Profile()
TRIM = P.output.pwm_trim
INF, NAN = float("inf"), float("nan")
FLOAT_BAD = [NAN, INF, -INF, 3.4e38, -3.4e38, 1e30, -1e30]
DOUBLE_BAD = [NAN, INF, -INF, 1.7e308, -1.7e308, 1e30]
INT_LIMITS = {"uint8_t": (0, 255), "int8_t": (-128, 127), "uint16_t": (0, 65535), "int16_t": (-32768, 32767),
              "uint32_t": (0, 2**32 - 1), "int32_t": (-2**31, 2**31 - 1), "uint64_t": (0, 2**64 - 1),
              "int64_t": (-2**63, 2**63 - 1)}
BODY_VEL = 0b0000_0101_1100_0111
EARTH_VEL_YAW = 0b0000_1001_1100_0111  # vx, vy, vz, yaw


def field_type(cls: Any, name: str) -> str:
    return str(cls.fieldtypes[cls.fieldnames.index(name)])


def bad_values(cls: Any, name: str) -> list[Any]:
    t = field_type(cls, name)
    if t == "float":
        return FLOAT_BAD
    if t == "double":
        return DOUBLE_BAD
    lo, hi = INT_LIMITS[t]
    return sorted({lo, hi, lo + 1, hi - 1, 0})


class Rig:
    _warm: Rig | None = None

    @classmethod
    def warm(cls) -> Rig:
        """A copy of one rig after its healthy start (building each from scratch is most of the cost)."""
        if cls._warm is None:
            cls._warm = Rig()
        src = cls._warm
        rig = cls.__new__(cls)
        rig.core = copy.deepcopy(src.core)
        rig.ap, rig.gcs = mavlink.MAVLink(None, 1, 1), mavlink.MAVLink(None, 255, 190)
        rig.t_s, rig.i, rig.out = src.t_s, src.i, []
        return rig

    def __init__(self) -> None:
        self.core = BridgeCore(P)
        self.ap = mavlink.MAVLink(None, 1, 1)
        self.gcs = mavlink.MAVLink(None, 255, 190)
        self.t_s = 0.0
        self.i = 0
        self.out: list[Outgoing] = []
        for _ in range(60):  # 1.2 s of healthy telemetry: streams, clocks, a baseline
            self.telemetry()

    def _in(self, link: Link, msg: MAVLinkMessage) -> bool:
        mav = self.ap if link is Link.AUTOPILOT else self.gcs
        decoded = mavlink.MAVLink(None).decode(bytearray(msg.pack(mav)))
        reaction = self.core.handle(Incoming(link, decoded), self.t_s)
        self.out += reaction.out
        return reaction.consumed

    def telemetry(self, dt_s: float = 0.02) -> None:
        self.t_s = round(self.t_s + dt_s, 9)
        self.i += 1
        t_ms = 1000 + 20 * self.i
        self._in(Link.AUTOPILOT, mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 0,
            mavlink.MAV_STATE_ACTIVE, 3))
        self._in(Link.AUTOPILOT, mavlink.MAVLink_attitude_message(t_ms, 0.0, 0.0, 0.2, 0.0, 0.0, 0.0))
        self._in(Link.AUTOPILOT, mavlink.MAVLink_wheel_distance_message(t_ms * 1000, 2, [0.0] * 16))
        self._in(Link.AUTOPILOT, mavlink.MAVLink_system_time_message(0, t_ms))
        self.out += self.core.tick(self.t_s)

    def inject(self, link: Link, msg: MAVLinkMessage) -> None:
        self.out = []
        self._in(link, msg)
        for _ in range(10):
            self.telemetry()

    def wheels(self) -> list[tuple[int, int]]:
        return [(o.msg.chan1_raw, o.msg.chan3_raw) for o in self.out if o.msg.get_type() == "RC_CHANNELS_OVERRIDE"]

    def assert_finite_estimate(self) -> None:
        pose = self.core.estimate.pose_at(self.t_s)
        assert all(math.isfinite(v) for v in (pose.x_m, pose.y_m, pose.yaw_rad)), pose
        odo = self.core.estimate.odometry_message(self.t_s)
        values = [odo.x, odo.y, odo.z, *odo.q, odo.vx, odo.vy, odo.vz, odo.yawspeed, *odo.pose_covariance,
                  *odo.velocity_covariance]
        assert all(math.isfinite(v) for v in values)

    def still_drives(self) -> None:
        """A valid forward request after the poison still drives (nothing latched)."""
        self.out = []
        for _ in range(10):  # 0.2 s: the limiter ramps up
            self._in(Link.GCS, spt_local(vx=0.5))
            self.telemetry()
        assert self.core.command.request is not None
        assert self.wheels() and self.wheels()[-1][0] > TRIM and self.wheels()[-1][1] > TRIM


def spt_local(**changes: Any) -> MAVLinkMessage:
    values: dict[str, Any] = dict(time_boot_ms=0, target_system=1, target_component=1, coordinate_frame=8,
                                  type_mask=BODY_VEL, x=0.0, y=0.0, z=0.0, vx=0.3, vy=0.0, vz=0.0, afx=0.0, afy=0.0,
                                  afz=0.0, yaw=0.0, yaw_rate=0.1)
    values.update(changes)
    return mavlink.MAVLink_set_position_target_local_ned_message(**values)


def spt_global(**changes: Any) -> MAVLinkMessage:
    values: dict[str, Any] = dict(time_boot_ms=0, target_system=1, target_component=1, coordinate_frame=6,
                                  type_mask=EARTH_VEL_YAW, lat_int=0, lon_int=0, alt=0.0, vx=0.3, vy=0.1, vz=0.0,
                                  afx=0.0, afy=0.0, afz=0.0, yaw=0.5, yaw_rate=0.0)
    values.update(changes)
    return mavlink.MAVLink_set_position_target_global_int_message(**values)


def manual(**changes: Any) -> MAVLinkMessage:
    values: dict[str, Any] = dict(target=1, x=300, y=0, z=500, r=100, buttons=0)
    values.update(changes)
    return mavlink.MAVLink_manual_control_message(**values)


# Request fields the decoder reads under the masks used; every bad value must be refused.
REQUEST_CASES: list[tuple[str, Callable[..., MAVLinkMessage], Any, str]] = []
for _field in ("vx", "vy", "yaw_rate"):
    REQUEST_CASES += [("local_body", spt_local, _field, v) for v in FLOAT_BAD]
for _field in ("vx", "vy", "yaw"):
    REQUEST_CASES += [("global", spt_global, _field, v) for v in FLOAT_BAD]
REQUEST_CASES += [("local_earth_yaw", lambda **c: spt_local(coordinate_frame=1, type_mask=EARTH_VEL_YAW, **c),
                   f, v) for f in ("vx", "vy", "yaw") for v in FLOAT_BAD]
REQUEST_CASES += [("manual", manual, f, v) for f in ("x", "r") for v in (-32768, -1001, 1001, 32767 - 1)]
REQUEST_CASES += [("manual_both_invalid", lambda **c: manual(x=0x7FFF, **c), "r", 0x7FFF)]
REQUEST_CASES += [("local_frame", spt_local, "coordinate_frame", v) for v in (2, 13, 21, 255)]
REQUEST_CASES += [("global_frame", spt_global, "coordinate_frame", v) for v in (1, 2, 8, 255)]
REQUEST_CASES += [("local_mask", spt_local, "type_mask", v) for v in (0, 0xFFFF, 0b0000_1111_1111_1111)]


@pytest.mark.parametrize(("kind", "factory", "field", "value"), REQUEST_CASES,
                         ids=[f"{k}-{f}-{v!r}" for k, _, f, v in REQUEST_CASES])
def test_poisoned_request_field_is_rejected_counted_and_never_reaches_a_wheel(
        kind: str, factory: Callable[..., MAVLinkMessage], field: str, value: Any) -> None:
    rig = Rig.warm()
    # A mask using x and y makes a position target: refused too here (the autopilot is not in GUIDED).
    refusals = ("rejected.", "goto.refused.")
    before = sum(n for k, n in rig.core.command.counters.items() if k.startswith(refusals))
    rig.inject(Link.GCS, factory(**{field: value}))
    rejected = sum(n for k, n in rig.core.command.counters.items() if k.startswith(refusals))
    assert rejected == before + 1, rig.core.command.counters
    assert "requests.accepted" not in rig.core.command.counters
    assert rig.core.command.request is None
    assert rig.wheels() and all(w == (TRIM, TRIM) for w in rig.wheels())
    rig.still_drives()


def test_the_unpoisoned_requests_do_drive() -> None:
    # Guards the table above: each base message is accepted when not poisoned.
    for factory in (spt_local, spt_global, manual,
                    lambda: spt_local(coordinate_frame=1, type_mask=EARTH_VEL_YAW)):
        rig = Rig.warm()
        rig.inject(Link.GCS, factory())
        assert rig.core.command.counters.get("requests.accepted") == 1
        assert any(w != (TRIM, TRIM) for w in rig.wheels())


# ------------------------------------------------------------------------------- estimator inputs

def _attitude(**c: Any) -> MAVLinkMessage:
    v: dict[str, Any] = dict(time_boot_ms=1500, roll=0.0, pitch=0.0, yaw=0.2, rollspeed=0.0, pitchspeed=0.0,
                             yawspeed=0.0)
    v.update(c)
    return mavlink.MAVLink_attitude_message(**v)


def _scaled_imu(**c: Any) -> MAVLinkMessage:
    v: dict[str, Any] = dict(time_boot_ms=1500, xacc=0, yacc=0, zacc=-1000, xgyro=0, ygyro=0, zgyro=0, xmag=0,
                             ymag=0, zmag=0, temperature=0)
    v.update(c)
    return mavlink.MAVLink_scaled_imu_message(**v)


def _raw_imu(**c: Any) -> MAVLinkMessage:
    v: dict[str, Any] = dict(time_usec=1_500_000, xacc=0, yacc=0, zacc=-1000, xgyro=0, ygyro=0, zgyro=0, xmag=0,
                             ymag=0, zmag=0, id=0, temperature=0)
    v.update(c)
    return mavlink.MAVLink_raw_imu_message(**v)


def _wheels(**c: Any) -> MAVLinkMessage:
    v: dict[str, Any] = dict(time_usec=2_300_000, count=2, distance=[0.0] * 16)
    v.update(c)
    return mavlink.MAVLink_wheel_distance_message(**v)


def _system_time(**c: Any) -> MAVLinkMessage:
    v: dict[str, Any] = dict(time_unix_usec=0, time_boot_ms=2300)
    v.update(c)
    return mavlink.MAVLink_system_time_message(**v)


def _heartbeat(**c: Any) -> MAVLinkMessage:
    v: dict[str, Any] = dict(type=mavlink.MAV_TYPE_GROUND_ROVER, autopilot=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                             base_mode=mavlink.MAV_MODE_FLAG_SAFETY_ARMED, custom_mode=0,
                             system_status=mavlink.MAV_STATE_ACTIVE, mavlink_version=3)
    v.update(c)
    return mavlink.MAVLink_heartbeat_message(**v)


def _ack(**c: Any) -> MAVLinkMessage:
    v: dict[str, Any] = dict(command=mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, result=0, progress=0, result_param2=0,
                             target_system=1, target_component=191)
    v.update(c)
    return mavlink.MAVLink_command_ack_message(**v)


def _estimator_cases() -> list[tuple[str, Callable[..., MAVLinkMessage], str, Any]]:
    cases: list[tuple[str, Callable[..., MAVLinkMessage], str, Any]] = []
    for name, factory, cls in (("attitude", _attitude, mavlink.MAVLink_attitude_message),
                               ("scaled_imu", _scaled_imu, mavlink.MAVLink_scaled_imu_message),
                               ("raw_imu", _raw_imu, mavlink.MAVLink_raw_imu_message),
                               ("system_time", _system_time, mavlink.MAVLink_system_time_message),
                               ("heartbeat", _heartbeat, mavlink.MAVLink_heartbeat_message),
                               ("command_ack", _ack, mavlink.MAVLink_command_ack_message)):
        for field in cls.fieldnames:
            cases += [(name, factory, field, v) for v in bad_values(cls, field)]
    cases += [("wheel_distance", _wheels, "time_usec", v) for v in bad_values(mavlink.MAVLink_wheel_distance_message,
                                                                              "time_usec")]
    cases += [("wheel_distance", _wheels, "count", v) for v in (0, 1, 17, 255)]
    for index in (0, 1):
        for v in DOUBLE_BAD:
            distance = [0.0] * 16
            distance[index] = v
            cases.append(("wheel_distance", _wheels, "distance", distance))
    return cases


ESTIMATOR_CASES = _estimator_cases()
# Poison in these fields must show up in a rejection counter (other fields are unused or harmless).
MUST_COUNT = {("attitude", "yawspeed"), ("attitude", "yaw"), ("wheel_distance", "distance")}


@pytest.mark.parametrize(("kind", "factory", "field", "value"), ESTIMATOR_CASES,
                         ids=[f"{k}-{f}-{i}" for i, (k, _, f, _v) in enumerate(ESTIMATOR_CASES)])
def test_poisoned_autopilot_field_keeps_the_estimate_finite_and_the_wheels_neutral(
        kind: str, factory: Callable[..., MAVLinkMessage], field: str, value: Any) -> None:
    rig = Rig.warm()
    counted = {**rig.core.estimate.counters, **rig.core.command.counters}
    rig.inject(Link.AUTOPILOT, factory(**{field: value}))
    rig.assert_finite_estimate()
    assert rig.core.command.request is None
    assert all(w == (TRIM, TRIM) for w in rig.wheels())
    after = {**rig.core.estimate.counters, **rig.core.command.counters}
    if (kind, field) in MUST_COUNT and not (isinstance(value, float) and math.isfinite(value)
                                           and kind == "attitude" and field == "yaw"):
        rejections = ("gyro_rejected", "wheel_bad", "wheel_spikes", "attitude.non_finite", "wheel_resyncs")
        assert any(after.get(k, 0) > counted.get(k, 0) for k in rejections), (after, counted)
    rig.still_drives()


@pytest.mark.parametrize("param", [(INF, 0.0, 0.0), (0.0, -INF, 0.0), (0.0, 0.0, INF), (3.4e38, 0.0, 0.0),
                                   (0.0, 0.0, 3.4e38)])
def test_pose_reset_with_poisoned_params_is_denied_and_the_pose_stays_finite(
        param: tuple[float, float, float]) -> None:
    rig = Rig.warm()
    msg = mavlink.MAVLink_command_long_message(1, 191, mavlink.MAV_CMD_USER_1, 0, *param, 0, 0, 0, 0)
    rig.inject(Link.GCS, msg)
    rig.assert_finite_estimate()
    acks = [o.msg for o in rig.out if o.msg.get_type() == "COMMAND_ACK"]
    assert acks and acks[0].result == mavlink.MAV_RESULT_DENIED
    assert rig.core.estimate.reset_counter == 0
    assert rig.core.estimate.counters["pose_resets_denied"] == 1
