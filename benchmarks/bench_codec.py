"""Time per decode and pack of the hot messages: pymavlink vs rover_bridge.mavlink.fastcodec.

Prints two tables (median of REPEATS runs, microseconds per call). Decode: pymavlink's
`mav.decode(bytearray(frame))` as links.py calls it vs `fastcodec.decode(frame)` (both check the CRC).
Pack: `msg.pack(mav)` vs `fastcodec.pack(msg, ...)` for an existing pymavlink message, and building the
message and packing it vs fastcodec's field packer (no message object).
Run: python benchmarks/bench_codec.py. Not a test: timings depend on the machine.
"""

from __future__ import annotations

import math
import statistics
import timeit
from collections.abc import Callable
from typing import Any

from rover_bridge.mavlink import fastcodec
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink

REPEATS = 7
NUMBER = 20_000


def bench(fn: Callable[[], object]) -> float:
    """Median microseconds per call over REPEATS runs of NUMBER calls."""
    return statistics.median(r / NUMBER * 1e6 for r in timeit.repeat(fn, number=NUMBER, repeat=REPEATS))


def _mav(seq: int = 17, sysid: int = 1, compid: int = 1, sign: bool = False) -> Any:
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.seq = seq
    if sign:
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id = bytes(range(32)), True, 1
    return mav


COV = [1e-3 * (i + 1) for i in range(21)]
ODOMETRY = {"time_usec": 1_234_567_890, "frame_id": mavlink.MAV_FRAME_LOCAL_FRD,
            "child_frame_id": mavlink.MAV_FRAME_BODY_FRD, "x": 12.5, "y": -3.25, "z": 0.0,
            "q": [0.99, 0.0, 0.0, 0.14], "vx": 0.4, "vy": 0.0, "vz": 0.0, "rollspeed": 0.0, "pitchspeed": 0.0,
            "yawspeed": 0.2, "pose_covariance": COV, "velocity_covariance": COV, "reset_counter": 1,
            "estimator_type": 0, "quality": 90}
RC_CHANS = [1500, 0, 1600, 0, 0, 0, 0, 0] + [0] * 10
HEARTBEAT = {"type": mavlink.MAV_TYPE_ONBOARD_CONTROLLER, "autopilot": mavlink.MAV_AUTOPILOT_INVALID,
             "base_mode": 0, "custom_mode": 0, "system_status": mavlink.MAV_STATE_ACTIVE, "mavlink_version": 3}


def decode_messages() -> list[tuple[str, MAVLinkMessage]]:
    m = mavlink
    return [
        ("HEARTBEAT", m.MAVLink_heartbeat_message(10, 3, 0x81, 4, 4, 3)),
        ("SYSTEM_TIME", m.MAVLink_system_time_message(1_700_000_000_000_000, 123_456)),
        ("SCALED_IMU", m.MAVLink_scaled_imu_message(123_456, 10, -20, -1000, 5, -3, 100, 200, -150, 400, 3500)),
        ("RAW_IMU", m.MAVLink_raw_imu_message(123_456_789, 10, -20, -1000, 5, -3, 100, 200, -150, 400, 0, 3500)),
        ("ATTITUDE", m.MAVLink_attitude_message(123_456, 0.01, -0.02, 1.57, 0.001, -0.002, 0.2)),
        ("LOCAL_POSITION_NED", m.MAVLink_local_position_ned_message(123_456, 12.5, -3.25, 0.1, 0.4, 0.01, 0.0)),
        ("GLOBAL_POSITION_INT", m.MAVLink_global_position_int_message(123_456, 473_977_420, 85_455_940, 500_000,
                                                                      1_200, 40, -3, 0, 9_000)),
        ("MISSION_ACK", m.MAVLink_mission_ack_message(255, 190, 0, 0)),
        ("COMMAND_LONG", m.MAVLink_command_long_message(1, 1, m.MAV_CMD_DO_SET_SERVO, 0, 1, 1500, 0, 0, 0, 0, 0)),
        ("COMMAND_ACK", m.MAVLink_command_ack_message(m.MAV_CMD_DO_SET_MODE, 0, 0, 0, 255, 190)),
        ("TIMESYNC", m.MAVLink_timesync_message(1_700_000_000_123_456_789, 987_654_321)),
        ("WHEEL_DISTANCE", m.MAVLink_wheel_distance_message(123_456_789, 2, [101.25, 99.75] + [0.0] * 14)),
    ]


def decode_rows() -> list[tuple[str, float, float]]:
    rows = []
    for name, msg in decode_messages():
        for label, sign in ((name, False), (f"{name} signed", True)):
            if sign and name not in ("WHEEL_DISTANCE", "COMMAND_LONG"):
                continue
            frame = msg.pack(_mav(sign=sign))
            rx = _mav()
            assert fastcodec.decode(frame) is not None
            rows.append((label, bench(lambda rx=rx, frame=frame: rx.decode(bytearray(frame))),
                         bench(lambda frame=frame: fastcodec.decode(frame))))
    return rows


def pack_rows() -> list[tuple[str, float, float, float, float]]:
    m = mavlink
    cases: list[tuple[str, Callable[[], MAVLinkMessage], Callable[[], bytes] | None]] = [
        ("HEARTBEAT", lambda: m.MAVLink_heartbeat_message(**HEARTBEAT),
         lambda: fastcodec.pack_heartbeat(17, 1, 191, **HEARTBEAT)),
        ("TIMESYNC", lambda: m.MAVLink_timesync_message(0, 1_700_000_000_123_456_789),
         lambda: fastcodec.pack_timesync(17, 1, 191, 0, 1_700_000_000_123_456_789)),
        ("RC_CHANNELS_OVERRIDE", lambda: m.MAVLink_rc_channels_override_message(1, 1, *RC_CHANS),
         lambda: fastcodec.pack_rc_channels_override(17, 1, 191, 1, 1, RC_CHANS)),
        ("ODOMETRY", lambda: m.MAVLink_odometry_message(**ODOMETRY),
         lambda: fastcodec.pack_odometry(17, 1, 191, **ODOMETRY)),
        ("COMMAND_LONG", lambda: m.MAVLink_command_long_message(1, 1, m.MAV_CMD_DO_SET_SERVO, 0, 1, 1500, 0, 0, 0,
                                                                0, 0), None),
    ]
    rows = []
    for name, build, fields in cases:
        mav = _mav(17, 1, 191)
        msg = build()
        expected = msg.pack(mav)
        assert fastcodec.pack(msg, 17, 1, 191) == expected and (fields is None or fields() == expected)
        rows.append((name, bench(lambda msg=msg, mav=mav: msg.pack(mav)),
                     bench(lambda msg=msg: fastcodec.pack(msg, 17, 1, 191)),
                     bench(lambda build=build, mav=mav: build().pack(mav)),
                     math.nan if fields is None else bench(fields)))
    return rows


def main() -> None:
    print(f"decode, us per call (median of {REPEATS} x {NUMBER})")
    print(f"{'message':<28}{'pymavlink':>10}{'fastcodec':>10}{'speedup':>9}")
    for name, ref, fast in decode_rows():
        print(f"{name:<28}{ref:>10.2f}{fast:>10.2f}{ref / fast:>8.1f}x")
    print()
    print("pack, us per call: an existing message | building it too (pymavlink) vs fastcodec's field packer")
    print(f"{'message':<22}{'msg.pack':>9}{'fc.pack':>9}{'speedup':>9} |{'new+pack':>9}{'fields':>9}{'speedup':>9}")
    for name, ref, fast, ref_new, fast_fields in pack_rows():
        if math.isnan(fast_fields):  # no field packer for this one
            fields = f"{'-':>9}{'-':>9}"
        else:
            fields = f"{fast_fields:>9.2f}{ref_new / fast_fields:>8.1f}x"
        print(f"{name:<22}{ref:>9.2f}{fast:>9.2f}{ref / fast:>8.1f}x |{ref_new:>9.2f}{fields}")


if __name__ == "__main__":
    main()
