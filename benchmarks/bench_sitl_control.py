"""Speed, turn and go-to control on a real ArduPilot Rover 4.7 SITL (rover-skid), judged by the simulator's truth.

One run boots `ardurover` (rover.parm + rover-skid.parm + deploy/ardupilot-rover.parm, SITL's wheel encoders as
tests/test_ardupilot_sitl.py sets them), starts `rover-bridge run` on its SERIAL0 and plays a request table from a
ground station on the bridge's UDP port, in GUIDED: SET_POSITION_TARGET_LOCAL_NED in BODY_NED, type_mask 1479 (vx
and yaw rate, clockwise +) at 10 Hz:

    steps 0 -> 0.5 -> 1.0 -> 1.5 m/s -> stop (4 s each), an arc 0.8 m/s + 0.4 rad/s, a spin 0.8 rad/s,
    a turn 1.0 m/s + 0.3 rad/s (stops between), then a go-to 8 m ahead (BODY_OFFSET_NED, position only, once)

A monitor on SERIAL1 reads the truth: SIM_STATE (vn, ve, yaw, zgyro) and SIMSTATE (lat, lng) at 40 Hz, and the
motor outputs (SERVO_OUTPUT_RAW). `--alone` plays the same table against ArduPilot alone in another SITL
instance (rover-skid.parm's SERVO1/3_FUNCTION 73/74: its own skid mixer, GUIDED, the same messages sent to it
directly; the go-to as a position target) for a side-by-side column. Each run takes about 2 minutes of wall time.

Profile: by default the SITL kit's profile (params/ardupilot-sitl-skid.toml: geometry, limits, outputs, encoders,
modes, demand) with any [control] section removed, so the speed loop runs on the packaged defaults as a new
owner's would (the shipped profile sets no loop gains either); `--profile PATH` runs another (a calibrated one).

Rows: overshoot of each step in % of the step, steady error in % (mean of the last 1.5 s of the step), the mean
forward speed and the yaw-rate error in % of the request in the arc, spin and turn (mean of the last 2.5 s), the
speed ripple of the steps (sd about each step's own mean over its last 2.5 s) and their yaw-rate rms (deg/s), the
path length of the bridge's ODOMETRY against the truth's (whole table, both sampled at 5 Hz), the go-to: time from
the request until the rover is at rest (truth speed below 0.05 m/s for good), the final distance from the target and
the largest distance past it; and SITL's clock against the wall clock (below 1: SITL was starved).

    ROVER_BRIDGE_ARDUROVER=/work/shared/ardupilot-sitl/build/sitl/bin/ardurover \\
        python benchmarks/bench_sitl_control.py [--profile P] [--alone] [--no-bridge] [--tlog run.tlog] [--out DIR]
    python benchmarks/bench_sitl_control.py --samples DIR/samples-bridge.json DIR/samples-alone.json

--tlog records the bridge's frames (for `rover-bridge replay`); --out keeps the SITL and bridge logs there and
writes samples-bridge.json / samples-alone.json (truth, outputs, ODOMETRY, the table's times), which --samples
turns into the table again without a run. Default SITL instances 21 and 22 (ports 5970-5982): the tests use 4-6.
"""

from __future__ import annotations

import argparse
import bisect
import itertools
import json
import math
import os
import re
import socket
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from ardupilot_rig import EARTH_RADIUS_M, PARM, PROFILE, Bridge, Link, Sitl

from rover_bridge.mavlink.dialect import mavlink

MANUAL, GUIDED = 0, 15
BODY_VELOCITY_MASK = 1479  # vx, vy, vz and yaw rate used
POSITION_ONLY_MASK = 0x0FF8
COMMON = "ARMING_CHECK 0\nSERIAL1_PROTOCOL 2\n"
BRIDGE_PARAMS = COMMON + "WENC_TYPE 10\nWENC2_TYPE 10\nWENC_POS_Y 0.8185\nWENC2_POS_Y -0.8185\n"
STREAMS = {mavlink.MAVLINK_MSG_ID_SIMSTATE: 25_000, mavlink.MAVLINK_MSG_ID_SIM_STATE: 25_000,
           mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW: 25_000}
STEPS = (("step 0->0.5", 0.5, 0.0, 4.0), ("step 0.5->1.0", 1.0, 0.0, 4.0), ("step 1.0->1.5", 1.5, 0.0, 4.0),
         ("stop", 0.0, 0.0, 3.0), ("arc", 0.8, 0.4, 6.0), ("stop", 0.0, 0.0, 3.0), ("spin", 0.0, 0.8, 5.0),
         ("stop", 0.0, 0.0, 3.0), ("turn", 1.0, 0.3, 6.0), ("stop", 0.0, 0.0, 3.0))
GOTO_M = 8.0
GOTO_TIMEOUT_S = 40.0
REST_M_S = 0.05
STEADY_S, TURN_STEADY_S = 1.5, 2.5


@dataclass(frozen=True)
class Segment:
    name: str
    vx_m_s: float
    yaw_rate_cw_rad_s: float
    t0: float
    t1: float


@dataclass
class Recording:
    """The table's times and what the monitor and the ground station saw (monotonic seconds)."""

    segments: list[Segment] = field(default_factory=list)
    truth: list[tuple[float, float, float, float, float]] = field(default_factory=list)  # t, n, e, fwd, zgyro
    outputs: list[tuple[float, int, int]] = field(default_factory=list)  # t, servo1, servo3
    autopilot_s: list[tuple[float, float]] = field(default_factory=list)  # t, SERVO_OUTPUT_RAW.time_usec (s)
    odometry: list[tuple[float, float, float]] = field(default_factory=list)  # t, x, y (LOCAL_FRD)
    goto_t: float = math.nan
    goto_start: tuple[float, float, float] = (0.0, 0.0, 0.0)  # n, e, yaw
    end_t: float = math.nan


def default_profile(workdir: Path) -> Path:
    """The SITL kit's profile without its [control] section (module docstring)."""
    text = PROFILE.read_text()
    cut = re.sub(r"^\[control\]\n(?:(?!\[).*\n)*", "", text, flags=re.MULTILINE)
    assert "[control]" not in cut and "kp =" not in cut
    path = workdir / "default-geometry.toml"
    path.write_text(cut)
    return path


def port_free(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) != 0


class Driver:
    """A ground station's requests, to the bridge or to ArduPilot directly (the same messages either way)."""

    def __init__(self, name: str, sitl: Sitl, gcs: Link) -> None:
        self.name, self.sitl, self.gcs = name, sitl, gcs

    def set_mode(self, mode: int, tries: int = 90) -> None:
        for _ in range(tries):
            self.gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, mode)
            if self.sitl.monitor.wait(lambda: self.sitl.mode() == mode, 1.0):
                return
        raise RuntimeError(f"{self.name}: mode {mode} refused ({self.sitl.monitor.texts()[-5:]})")

    def arm(self) -> None:
        if self.gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, 21196) != mavlink.MAV_RESULT_ACCEPTED:
            raise RuntimeError(f"{self.name}: arming refused ({self.sitl.monitor.texts()[-5:]})")

    def velocity(self, vx_m_s: float, yaw_rate_cw_rad_s: float) -> None:
        mav = self.gcs.conn.mav
        self.gcs.each = lambda: mav.set_position_target_local_ned_send(
            0, 1, 1, mavlink.MAV_FRAME_BODY_NED, BODY_VELOCITY_MASK, 0, 0, 0, vx_m_s, 0, 0, 0, 0, 0, 0,
            yaw_rate_cw_rad_s)

    def goto_ahead(self, forward_m: float) -> None:
        self.gcs.each = None
        with self.gcs.lock:
            self.gcs.conn.mav.set_position_target_local_ned_send(
                0, 1, 1, mavlink.MAV_FRAME_BODY_OFFSET_NED, POSITION_ONLY_MASK, forward_m, 0, 0, 0, 0, 0, 0, 0, 0,
                0, 0)


def wait_ready(sitl: Sitl) -> None:
    """GPS and EKF: GUIDED needs a position (about 25-45 s after boot)."""
    if not sitl.monitor.wait(lambda: any("is using GPS" in t for t in sitl.monitor.texts()), 120.0):
        raise RuntimeError(f"no GPS: {sitl.monitor.texts()[-5:]}")
    time.sleep(3.0)


def play(driver: Driver) -> Recording:
    """The request table, then the go-to; the recording is cut from the monitor's messages afterwards."""
    rec = Recording()
    driver.set_mode(MANUAL)
    driver.arm()
    driver.set_mode(GUIDED)
    driver.velocity(0.0, 0.0)
    time.sleep(1.5)
    begin = time.monotonic()
    for name, vx, wz, hold_s in STEPS:
        t0 = time.monotonic()
        driver.velocity(vx, wz)
        time.sleep(hold_s)
        rec.segments.append(Segment(name, vx, wz, t0, time.monotonic()))
    driver.gcs.each = None
    time.sleep(1.0)
    sim = driver.sitl.monitor.of("SIM_STATE", time.monotonic() - 0.5)[-1]
    rec.goto_start = (*driver.sitl.truth(), float(sim.yaw))
    rec.goto_t = time.monotonic()
    driver.goto_ahead(GOTO_M)
    moved = driver.sitl.monitor.wait(lambda: not driver.sitl.stopped(), 5.0)
    end = time.monotonic() + GOTO_TIMEOUT_S
    while moved and time.monotonic() < end:
        if driver.sitl.monitor.wait(driver.sitl.stopped, end - time.monotonic()):
            time.sleep(3.0)  # at rest for good, or only a pause?
            if driver.sitl.stopped():
                break
    rec.end_t = time.monotonic()
    record(driver, rec, begin)
    return rec


def record(driver: Driver, rec: Recording, since: float) -> None:
    mon = driver.sitl.monitor
    assert driver.sitl.origin_deg is not None
    lat0, lon0 = driver.sitl.origin_deg
    position: tuple[float, float] | None = None
    for t, m in list(mon.messages):
        if t < since:
            continue
        kind = m.get_type()
        if kind == "SIMSTATE":
            position = (math.radians(m.lat * 1e-7 - lat0) * EARTH_RADIUS_M,
                        math.radians(m.lng * 1e-7 - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0)))
        elif kind == "SIM_STATE" and position is not None:
            fwd = m.vn * math.cos(m.yaw) + m.ve * math.sin(m.yaw)
            rec.truth.append((t, position[0], position[1], fwd, float(m.zgyro)))
        elif kind == "SERVO_OUTPUT_RAW":
            rec.outputs.append((t, int(m.servo1_raw), int(m.servo3_raw)))
            rec.autopilot_s.append((t, m.time_usec * 1e-6))
    if driver.name != "ArduPilot alone":
        rec.odometry = [(t, float(m.x), float(m.y)) for t, m in list(driver.gcs.messages)
                        if t >= since and m.get_type() == "ODOMETRY"]


# ----------------------------------------------------------------- figures


def _window(rec: Recording, t0: float, t1: float) -> list[tuple[float, float, float, float, float]]:
    return [s for s in rec.truth if t0 <= s[0] <= t1]


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else math.nan


def _path_m(points: list[tuple[float, float, float]], t0: float, t1: float) -> float:
    """Length of a (t, a, b) track sampled at 5 Hz between t0 and t1 (the position nearest each grid time)."""
    times = [p[0] for p in points]
    grid = [t0 + 0.2 * k for k in range(int((t1 - t0) / 0.2) + 1)]
    picked = []
    for g in grid:
        i = bisect.bisect_left(times, g)
        if 0 < i < len(times) and g - times[i - 1] < times[i] - g:
            i -= 1
        if i < len(times):
            picked.append(points[i])
    return sum(math.hypot(b[1] - a[1], b[2] - a[2]) for a, b in itertools.pairwise(picked))


def figures(rec: Recording) -> dict[str, float]:
    out: dict[str, float] = {}
    before = 0.0
    straight_rates: list[float] = []
    ripple: list[float] = []  # speed about each step's own mean over its last 2.5 s
    for seg in rec.segments:
        w = _window(rec, seg.t0, seg.t1)
        if seg.name.startswith("step"):
            fwd = [s[3] for s in w]
            peak = max(fwd)
            steady = _mean([s[3] for s in w if s[0] >= seg.t1 - STEADY_S])
            out[f"{seg.name} overshoot %"] = 100.0 * (peak - seg.vx_m_s) / (seg.vx_m_s - before)
            out[f"{seg.name} steady error %"] = 100.0 * (steady - seg.vx_m_s) / seg.vx_m_s
            straight_rates += [s[4] for s in w if s[0] >= seg.t0 + 0.5]
            late = [s[3] for s in w if s[0] >= seg.t1 - TURN_STEADY_S]
            ripple += [v - _mean(late) for v in late]
        elif seg.name in ("arc", "spin", "turn"):
            tail = [s for s in w if s[0] >= seg.t1 - TURN_STEADY_S]
            rate = _mean([s[4] for s in tail])
            out[f"{seg.name} yaw-rate error %"] = 100.0 * (rate - seg.yaw_rate_cw_rad_s) / seg.yaw_rate_cw_rad_s
            out[f"{seg.name} yaw rate rad/s"] = rate
            out[f"{seg.name} speed m/s"] = _mean([s[3] for s in tail])
        before = seg.vx_m_s
    out["steps speed ripple sd m/s"] = math.sqrt(_mean([r * r for r in ripple]))
    out["straights yaw-rate rms deg/s"] = math.degrees(math.sqrt(_mean([r * r for r in straight_rates])))
    t0, t1 = rec.segments[0].t0, rec.end_t
    truth_pts = [(s[0], s[1], s[2]) for s in rec.truth]
    true_m = _path_m(truth_pts, t0, t1)
    out["true path m"] = true_m
    if rec.odometry:
        out["ODOMETRY path error %"] = 100.0 * (_path_m(rec.odometry, t0, t1) - true_m) / true_m
    n0, e0, yaw0 = rec.goto_start
    tn, te = n0 + GOTO_M * math.cos(yaw0), e0 + GOTO_M * math.sin(yaw0)
    after = [s for s in rec.truth if s[0] >= rec.goto_t]
    moving = [s[0] for s in after if abs(s[3]) > REST_M_S]
    out["go-to at rest after s"] = (moving[-1] - rec.goto_t) if moving else math.nan
    last = after[-1]
    out["go-to final error m"] = math.hypot(last[1] - tn, last[2] - te)
    along = [(s[1] - n0) * math.cos(yaw0) + (s[2] - e0) * math.sin(yaw0) for s in after]
    out["go-to max past target m"] = max(0.0, max(along) - GOTO_M)
    # Below 1: SITL ran slower than the wall clock (starved: the requests' timing no longer means what it says).
    if len(rec.autopilot_s) > 1:
        (w0, a0), (w1, a1) = rec.autopilot_s[0], rec.autopilot_s[-1]
        out["SITL clock / wall clock"] = (a1 - a0) / (w1 - w0)
    return out


def save(rec: Recording, path: Path) -> None:
    path.write_text(json.dumps({
        "segments": [vars(s) for s in rec.segments], "goto_t": rec.goto_t, "goto_start": rec.goto_start,
        "end_t": rec.end_t, "truth": rec.truth, "outputs": rec.outputs, "odometry": rec.odometry,
        "autopilot_s": rec.autopilot_s}))


def load(path: Path) -> Recording:
    d = json.loads(path.read_text())
    return Recording([Segment(**s) for s in d["segments"]], [tuple(x) for x in d["truth"]],
                     [tuple(x) for x in d["outputs"]], [tuple(x) for x in d.get("autopilot_s", [])],
                     [tuple(x) for x in d["odometry"]], d["goto_t"], tuple(d["goto_start"]), d["end_t"])


# ----------------------------------------------------------------- runs


def run_bridge(binary: str, instance: int, workdir: Path, profile: Path, tlog: str | None) -> Recording:
    sitl = Sitl(binary, instance, BRIDGE_PARAMS, workdir / "bridge-sitl", (PARM,), STREAMS)
    bridge: Bridge | None = None
    try:
        bridge = Bridge(sitl, workdir, profile, extra_args=("--tlog", tlog) if tlog else ())
        wait_ready(sitl)
        rec = play(Driver("bridge", sitl, bridge.gcs))
        save(rec, workdir / "samples-bridge.json")
        return rec
    finally:
        if bridge is not None:
            bridge.gcs.each = None
            if bridge.proc.poll() is None:
                bridge.stop()
            bridge.close()
        sitl.close()


def run_alone(binary: str, instance: int, workdir: Path) -> Recording:
    sitl = Sitl(binary, instance, COMMON, workdir / "alone-sitl", (), STREAMS)
    gcs = sitl.gcs_on_serial0()
    try:
        wait_ready(sitl)
        rec = play(Driver("ArduPilot alone", sitl, gcs))
        save(rec, workdir / "samples-alone.json")
        return rec
    finally:
        gcs.close()
        sitl.close()


def print_table(columns: list[tuple[str, dict[str, float]]]) -> None:
    rows: list[str] = []
    for _, figs in columns:
        rows += [r for r in figs if r not in rows]
    width = max(len(r) for r in rows) + 2
    print("".ljust(width) + "".join(name.rjust(24) for name, _ in columns))
    for r in rows:
        print(r.ljust(width) + "".join(f"{figs.get(r, math.nan):24.3f}" for _, figs in columns))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ardurover", default=os.environ.get("ROVER_BRIDGE_ARDUROVER", ""),
                        help="the ardurover binary (default: $ROVER_BRIDGE_ARDUROVER)")
    parser.add_argument("--profile", type=Path, default=None,
                        help="the bridge's profile (default: the SITL kit's without its [control] section)")
    parser.add_argument("--alone", action="store_true", help="also run ArduPilot alone (another SITL instance)")
    parser.add_argument("--no-bridge", action="store_true", help="skip the bridge's run (with --alone)")
    parser.add_argument("--tlog", default=None, help="the bridge's --tlog")
    parser.add_argument("--out", type=Path, default=None, help="keep logs and samples.json in this folder")
    parser.add_argument("--instance", type=int, default=21, help="SITL instance of the bridge's run (alone: +1)")
    parser.add_argument("--samples", type=Path, nargs="*", default=None,
                        help="no run: the table from samples-*.json written by earlier runs (--out)")
    args = parser.parse_args(argv)
    if args.samples:
        print_table([(f"{p.parent.name}/{p.stem}", figures(load(p))) for p in args.samples])
        return 0
    if not args.ardurover or not Path(args.ardurover).is_file():
        parser.error("name the ardurover binary: --ardurover or ROVER_BRIDGE_ARDUROVER")
    for port in (5760 + 10 * args.instance, 5762 + 10 * args.instance, 5770 + 10 * args.instance,
                 5772 + 10 * args.instance):
        if not port_free(port):
            parser.error(f"port {port} is in use (another SITL?): choose another --instance")
    with tempfile.TemporaryDirectory(prefix="bench_sitl_control_") as tmp:
        workdir = args.out or Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        columns: list[tuple[str, dict[str, float]]] = []
        print(f"load before: {os.getloadavg()[0]:.2f} (2 cores shared: a starved SITL shows in the figures)")
        if not args.no_bridge:
            profile = args.profile or default_profile(workdir)
            label = "bridge " + (args.profile.stem if args.profile else "default+geometry")
            columns.append((label, figures(run_bridge(args.ardurover, args.instance, workdir, profile, args.tlog))))
        if args.alone:
            columns.append(("ArduPilot alone", figures(run_alone(args.ardurover, args.instance + 1, workdir))))
        print(f"load after: {os.getloadavg()[0]:.2f}")
        print_table(columns)
    return 0


if __name__ == "__main__":
    sys.exit(main())
