"""Regenerate tests/data/ardurover-skid-wenc.bin: a real ArduPilot Rover SITL with wheel encoders, driven by a
script, its DataFlash log cut to what rover-bridge reads; then `rover-bridge calibrate` live on the same SITL.

    python tests/data/make_sitl_bin.py --ardurover PATH/build/sitl/bin/ardurover [--drive-s 150] [--instance 7]

ArduPilot runs the rover-skid model with per-wheel RC passthrough (SERVO1/3_FUNCTION = 51/53), SITL's wheel
encoders (WENC_TYPE 10) at the profile's effective track (params/ardupilot-sitl-skid.toml) and a small
LOG_BITMASK. A ground station on SERIAL1 (system id 255, the one whose overrides ArduPilot obeys) waits for a
3-D GPS fix and the EKF's position, arms (forced: passthrough outputs fail the pre-arm check), drives a seeded
sequence of straight runs, arcs and spins in MANUAL with RC overrides of channels 1 (left) and 3 (right) for
--drive-s seconds, stops and disarms; ArduPilot closes that log. Then it arms again and `rover-bridge calibrate
--quick --yes` runs on SERIAL0, against the same simulated rover, and its track width is printed. The log is
cut to the messages rover-bridge reads (FMT/UNIT/MULT/FMTU, a few PARM, MODE, WENC, IMU and GPS instance 0, ATT,
RCIN, RCOU), every one kept whole and in order, up to the first disarm, and written to --out.
"""

from __future__ import annotations

import argparse
import random
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
import ardupilot_rig  # noqa: E402

PROFILE = REPO / "params" / "ardupilot-sitl-skid.toml"
EXTRA_PARAMS = ardupilot_rig.EXTRA_PARAMS + """LOG_DISARMED 0
LOG_FILE_DSRMROT 1
LOG_BITMASK 16518
"""  # LOG_BITMASK: ATTITUDE_MED (ATT 10 Hz), GPS, IMU, RC (RCIN, RCOU, WENC 10 Hz); a new log file at each arming
KEEP = {"FMT", "FMTU", "UNIT", "MULT", "MODE", "WENC", "ATT", "RCIN", "RCOU"}
KEEP_INSTANCE_0 = {"IMU", "GPS"}
KEEP_PARAMS = {"SYSID_THISMAV", "WENC_TYPE", "WENC2_TYPE", "WENC_POS_Y", "WENC2_POS_Y", "WENC_RADIUS", "WENC2_RADIUS",
               "WENC_CPR", "WENC2_CPR", "SERVO1_FUNCTION", "SERVO3_FUNCTION", "LOG_BITMASK"}
TRIM = 1500


def drive_script(seed: int, duration_s: float) -> list[tuple[float, int, int]]:
    """(seconds, left PWM, right PWM): straight runs both ways, arcs and spins, stops between."""
    rng = random.Random(seed)
    out: list[tuple[float, int, int]] = []
    total = 0.0
    while total < duration_s:
        kind = rng.choice(("straight", "straight", "arc", "arc", "spin"))
        base = rng.choice((-1, 1, 1)) * rng.randint(120, 250)
        if kind == "straight":
            left = right = base
        elif kind == "arc":
            turn = rng.choice((-1, 1)) * rng.randint(40, 120)
            left, right = base - turn, base + turn
        else:
            s = rng.choice((-1, 1)) * rng.randint(80, 200)
            left, right = -s, s
        d = rng.uniform(3.0, 7.0)
        out += [(d, TRIM + left, TRIM + right), (1.0, TRIM, TRIM)]
        total += d + 1.0
    return out


class Gcs:
    """SERIAL1 as system 255: heartbeats, arming, overrides; watches the fix and the heartbeat."""

    def __init__(self, port: int) -> None:
        from rover_bridge.mavlink.dialect import mavutil

        self.conn: Any = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255, source_component=190,
                                                    dialect="ardupilotmega")
        self.fix = 0
        self.armed = False
        self.last_hb = 0.0

    def pump(self, for_s: float = 0.0) -> None:
        from rover_bridge.mavlink.dialect import mavlink

        end = time.monotonic() + for_s
        while True:
            m = self.conn.recv_match(blocking=for_s > 0, timeout=0.05)
            if m is not None:
                if m.get_type() == "GPS_RAW_INT":
                    self.fix = int(m.fix_type)
                elif m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 1 and m.get_srcComponent() == 1:
                    self.armed = bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            if time.monotonic() - self.last_hb > 1.0:
                self.last_hb = time.monotonic()
                self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                self.conn.mav.request_data_stream_send(1, 1, mavlink.MAV_DATA_STREAM_ALL, 2, 1)
            if time.monotonic() >= end and (m is None or for_s == 0):
                return

    def arm(self, on: bool) -> None:
        from rover_bridge.mavlink.dialect import mavlink

        self.conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1 if on else 0, 21196,
                                        0, 0, 0, 0, 0)

    def override(self, left: int, right: int) -> None:
        self.conn.mav.rc_channels_override_send(1, 1, left, 0, right, 0, 0, 0, 0, 0)


def cut(source: Path, out: Path) -> None:
    """Copy the messages rover-bridge reads, whole and in file order, up to the first disarm (the scripted
    drive; ArduPilot goes on logging into the same file after it), into a new DataFlash log."""
    from pymavlink import DFReader

    log: Any = DFReader.DFReader_binary(str(source))
    data = source.read_bytes()
    end = len(data)
    if "ARM" in log.name_to_id:
        for ofs in log.offsets[log.name_to_id["ARM"]]:
            log.offset = ofs
            if int(log._parse_next().ArmState) == 0:
                end = ofs
                break
    keep: list[int] = []
    for mtype, all_offsets in enumerate(log.offsets):
        fmt = log.formats.get(mtype)
        if fmt is None or not all_offsets:
            continue
        offsets = [ofs for ofs in all_offsets if ofs + fmt.len <= len(data) and (ofs < end or fmt.name == "FMT")]
        if fmt.name in KEEP:
            keep += offsets
        elif fmt.name in KEEP_INSTANCE_0 or fmt.name == "PARM":
            for ofs in offsets:
                log.offset = ofs
                m = log._parse_next()
                if (fmt.name == "PARM" and m.Name in KEEP_PARAMS) or (fmt.name != "PARM" and int(m.I) == 0):
                    keep.append(ofs)
    lengths = {ofs: log.formats[data[ofs + 2]].len for ofs in keep}
    out.write_bytes(b"".join(data[ofs:ofs + lengths[ofs]] for ofs in sorted(keep)))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ardurover", required=True)
    parser.add_argument("--drive-s", type=float, default=150.0)
    parser.add_argument("--instance", type=int, default=7)
    parser.add_argument("--seed", type=int, default=32)
    parser.add_argument("--out", default=str(Path(__file__).resolve().parent / "ardurover-skid-wenc.bin"))
    args = parser.parse_args()
    binary = Path(args.ardurover).resolve()
    params = binary.parents[3] / "Tools" / "autotest" / "default_params"
    work = Path(tempfile.mkdtemp(prefix="sitl-bin-"))
    (work / "extra.parm").write_text(EXTRA_PARAMS)
    defaults = ",".join(str(p) for p in (params / "rover.parm", params / "rover-skid.parm", work / "extra.parm"))
    serial0, serial1 = 5760 + 10 * args.instance, 5762 + 10 * args.instance
    with open(work / "ardurover.out", "wb") as sink:
        proc = subprocess.Popen([str(binary), "--model", "rover-skid", "--defaults", defaults, "-I",
                                 str(args.instance), "--serial0", "tcp:0", "-w"], cwd=work, stdout=sink,
                                stderr=subprocess.STDOUT)
    try:
        time.sleep(3.0)
        gcs = Gcs(serial1)
        start = time.monotonic()
        while gcs.fix < 3 or time.monotonic() - start < 30.0:  # GPS and the EKF's origin: ~25 s after boot
            gcs.pump(0.5)
            assert time.monotonic() - start < 120.0, "no 3-D fix from SITL"
        while not gcs.armed:
            gcs.arm(True)
            gcs.pump(1.0)
        print(f"armed; driving {args.drive_s:.0f} s", file=sys.stderr)
        for seconds, left, right in drive_script(args.seed, args.drive_s):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                gcs.override(left, right)
                gcs.pump(0.1)
        gcs.override(TRIM, TRIM)
        gcs.pump(2.0)
        while gcs.armed:
            gcs.arm(False)
            gcs.pump(1.0)
        gcs.pump(2.0)
        logs = sorted((work / "logs").glob("*.BIN"), key=lambda p: p.stat().st_mtime)
        assert logs, "ArduPilot wrote no DataFlash log"
        driven = logs[-1]
        gcs.override(0, 0)  # released: calibrate drives from SERIAL0 now
        while not gcs.armed:
            gcs.arm(True)
            gcs.pump(1.0)
        patch = work / "calibration-patch.toml"
        calibrate = subprocess.run([sys.executable, "-m", "rover_bridge", "calibrate", "--quick", "--yes", "--params",
                                    str(PROFILE), "--autopilot", f"tcp:127.0.0.1:{serial0}", "--out", str(patch)],
                                   cwd=REPO, capture_output=True, text=True, timeout=300)
        print(calibrate.stdout[-3000:], calibrate.stderr[-3000:], file=sys.stderr)
        if patch.exists():
            track = tomllib.loads(patch.read_text())["robot"]["track_width_m"]
            print(f"calibrate live: track_width_m = {track}")
        cut(driven, Path(args.out))
        print(f"{driven} ({driven.stat().st_size} bytes) cut to {args.out} ({Path(args.out).stat().st_size} bytes)")
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
