"""ArduPilot DataFlash .bin logs through replay and the fleet report: one written here from an emulated rover
(its truth known), and one from a real ArduPilot Rover SITL (tests/data, see its README)."""

from __future__ import annotations

import struct
import sys
from pathlib import Path
from typing import Any

import pytest

from rover_bridge.app.replay import replay
from rover_bridge.fleet.analysis import LogReport, analyse_log, fleet_profile
from rover_bridge.params import Profile
from sitl import Emulator

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_fleet as bench

HEAD = b"\xa3\x95"
# Our own formats (a DataFlash log describes its messages in its FMT messages; DFReader reads them): the
# fields rover-bridge reads, under ArduPilot's names.
FORMATS = {
    "PARM": (129, "QNf", "TimeUS,Name,Value"),
    "MODE": (130, "QBB", "TimeUS,Mode,ModeNum"),
    "WENC": (131, "QfBfB", "TimeUS,Dist0,Qual0,Dist1,Qual1"),
    "IMU": (132, "QBfff", "TimeUS,I,GyrX,GyrY,GyrZ"),
    "ATT": (133, "Qff", "TimeUS,Roll,Yaw"),
    "GPS": (134, "QBBIHBfLLf", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt"),
    "RCOU": (135, "QHHHH", "TimeUS,C1,C2,C3,C4"),
}
STRUCT = {"Q": "Q", "N": "16s", "f": "f", "B": "B", "I": "I", "H": "H", "L": "i"}
GPS_WEEK, GPS_MS = 2430, 100_000_000  # a Thursday in 2026


def _fmt_messages() -> bytes:
    out = b""
    for name, (mtype, fmt, cols) in FORMATS.items():
        length = 3 + struct.calcsize("<" + "".join(STRUCT[c] for c in fmt))
        out += HEAD + bytes([128]) + struct.pack("<BB4s16s64s", mtype, length, name.encode(), fmt.encode(),
                                                 cols.encode())
    return out


def _msg(name: str, *values: Any) -> bytes:
    mtype, fmt, _ = FORMATS[name]
    return HEAD + bytes([mtype]) + struct.pack("<" + "".join(STRUCT[c] for c in fmt), *values)


def write_dataflash(path: Path, rover: bench.EmulatedRover, seed: int, duration_s: float) -> None:
    """What ArduPilot would log on the emulated rover: the emulator's frames as DataFlash messages."""
    emu = Emulator(vehicle=rover.vehicle(), seed=seed, system_id=rover.system_id, record_sent=True)
    pilot = bench.mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    sent = emu.sent_log
    assert sent is not None
    out = bytearray(_fmt_messages() + _msg("PARM", 0, b"SYSID_THISMAV", float(rover.system_id))
                    + _msg("MODE", 1000, 0, 0))
    for seconds, left, right in bench.drive_script(seed, duration_s):
        for i in range(round(seconds / 0.02)):
            if i % 10 == 0:
                emu.handle_message(pilot.rc_channels_override_encode(rover.system_id, 1, left, 0, right, 0, 0, 0,
                                                                     0, 0), src_system=255)
            emu.step(0.02)
            for _, m in sent:
                kind = m.get_type()
                if kind == "WHEEL_DISTANCE":
                    out += _msg("WENC", m.time_usec, m.distance[0], 100, m.distance[1], 100)
                elif kind == "ATTITUDE":
                    t_us = m.time_boot_ms * 1000
                    out += _msg("IMU", t_us, 0, 0.0, 0.0, m.yawspeed) + _msg("ATT", t_us, 0.0, m.yaw * 57.29578)
                elif kind == "GLOBAL_POSITION_INT" and m.lat != 0:
                    out += _msg("GPS", m.time_boot_ms * 1000, 0, 3, GPS_MS + m.time_boot_ms, GPS_WEEK, 12, 0.8,
                                m.lat, m.lon, 584.0)
                elif kind == "SERVO_OUTPUT_RAW":
                    out += _msg("RCOU", m.time_usec, m.servo1_raw, m.servo2_raw, m.servo3_raw, m.servo4_raw)
            sent.clear()
    path.write_bytes(bytes(out))


ROVER = bench.FLEET[3]  # track 5 % narrower, right wheel 3 % larger than the profile says
PROFILE = fleet_profile(Profile())


@pytest.fixture(scope="module")
def emulated_bin(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("df") / "00000042.BIN"
    write_dataflash(path, ROVER, 4, 60.0)
    return path


def test_an_emulated_dataflash_log_gives_the_rovers_truth(emulated_bin: Path) -> None:
    result = replay(emulated_bin, PROFILE)
    assert result.log.kind == "dataflash" and result.log.trailing_bytes == 0 and result.log.bad_bytes == 0
    assert result.calibration.track_scale == pytest.approx(ROVER.track_scale, rel=0.005)
    assert result.calibration.radius_ratio == pytest.approx(ROVER.radius_ratio, rel=0.005)
    r = analyse_log(str(emulated_bin), PROFILE, "df")
    assert r.used and r.kind == "dataflash" and r.system_id == ROVER.system_id
    # GPS week and milliseconds, less the 18 leap seconds, less the boot time of the first fix.
    assert r.start_unix_s == pytest.approx(315_964_800 + GPS_WEEK * 604_800 + GPS_MS / 1000 - 18, abs=1.0)
    assert r.drift_pct < 1.0 and r.gps_fixes > 50
    assert r.duration_s == pytest.approx(60.0, abs=0.5)
    assert r.wiring == "" and r.stalls == 0


def test_a_damaged_dataflash_log_says_why(emulated_bin: Path, tmp_path: Path) -> None:
    data = emulated_bin.read_bytes()
    cases = {"cut.bin": data[: len(data) // 2 + 5], "empty.bin": b"",
             "garbage.bin": data[: len(data) // 3] + bytes(range(256)) * 40 + data[len(data) // 3:],
             "noise.bin": bytes((i * 7919) % 251 for i in range(5000))}
    reports: dict[str, LogReport] = {}
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        reports[name] = analyse_log(str(tmp_path / name), PROFILE, "df")
    assert reports["cut.bin"].reason.startswith("truncated: ends mid-frame")
    assert reports["empty.bin"].reason == "empty: 0 bytes"
    assert reports["garbage.bin"].reason.startswith("corrupt:")
    assert reports["noise.bin"].reason.split(":")[0] in ("corrupt", "unreadable")
    assert not any(r.used for r in reports.values())


# ---------------------------------------------------------------------------- a real ArduPilot Rover SITL

SITL_BIN = Path(__file__).resolve().parent / "data" / "ardurover-skid-wenc.bin"
SITL_PROFILE = Path(__file__).resolve().parents[1] / "params" / "ardupilot-sitl-skid.toml"
SITL_CALIBRATE_TRACK_M = 1.6333  # `rover-bridge calibrate` live on the same SITL (tests/data/README.md)


def test_a_real_ardupilot_log_gives_calibrates_track_and_follows_its_gps() -> None:
    from rover_bridge.params import load_profile

    profile = fleet_profile(load_profile(SITL_PROFILE))
    r = analyse_log(str(SITL_BIN), profile, "sitl")
    assert r.used and r.kind == "dataflash" and r.note == "", r.reason
    assert r.system_id == 1
    assert r.duration_s > 150.0 and r.distance_m > 100.0
    track_m = profile.robot.track_width_m * r.track_scale
    assert track_m == pytest.approx(SITL_CALIBRATE_TRACK_M, rel=0.02)
    assert r.track_scale_sigma < 0.005
    assert r.radius_ratio == pytest.approx(1.0, abs=0.01)  # SITL's two encoders share one radius
    assert r.gps_fixes > 500 and r.drift_pct < 1.0
    assert (r.stalls, r.wiring, r.slip_events, r.log_gaps, r.clock_jumps) == (0, "", 0, 0, 0)
    assert 1.7e9 < r.start_unix_s < 2.1e9  # from the GPS week: the SITL's (simulated) date
    # replay alone: the same figures (the fleet's per-log work is replay's)
    alone = replay(SITL_BIN, profile)
    assert alone.calibration.track_scale == r.track_scale and alone.rows[-1].x_m == r.final_x_m
