"""`rover-bridge demo`: the emulator and the bridge as separate processes on UDP loopback, a
scripted ground station driving a route through the bridge, and a report against ground truth.

The `goto` scenario drives no velocity route: the ground station puts the autopilot in GUIDED and
sends five "go here" targets, each once, the way ground stations and planners send them
(MISSION_ITEM_INT current=2 as Mission Planner's "Fly to here" and MAVProxy's `guided`, DO_REPOSITION as
QGroundControl and MAVSDK, SET_POSITION_TARGET_* from a script), the next when the bridge reported the
last reached and the rover stopped; the report adds each target's arrival error by ground truth.

The `obstacles` scenario (rover_bridge.app.demo_obstacles) gives the emulator a wall, a post and a proximity
sensor, drives at each in GUIDED with velocity requests, and reports how close the bridge's avoidance let the
rover come to each (demo-obstacles.png: rover_bridge.app.demo_obstacles_picture).

Processes: `python -m sitl` (the autopilot, ground truth) <-> `python -m rover_bridge run`
<-> this process (the GCS). The GCS sees everything through the bridge, as a real ground
station would: ODOMETRY from the bridge, and the emulator's telemetry forwarded (its
ground-truth LOCAL_POSITION_NED/SIMSTATE, and WHEEL_DISTANCE from which raw wheel odometry
is integrated here, for comparison).
"""

from __future__ import annotations

import bisect
import contextlib
import ctypes
import functools
import itertools
import json
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from rover_bridge.app import demo_obstacles as obstacles
from rover_bridge.app.demo_route import Phase, aimed, body, earth
from rover_bridge.app.demo_series import GotoLeg, Series
from rover_bridge.frames import EARTH_RADIUS_M
from rover_bridge.mavlink.dialect import mavlink, mavutil
from rover_bridge.odometry import WheelOdometry

GCS_SYSID = 255
GCS_COMPID = 190
REQUEST_RATE_HZ = 10.0


def route(scale: float = 1.0) -> list[Phase]:
    """Straight run, spin in place, a square (earth-frame legs), a figure eight, a stop."""
    s = scale
    spin_rate = 1.5
    eight_v, eight_w = 0.4, 1.0
    leg_v, leg_s = 0.4, 3.2 * s
    # A rover stands still for a moment after power-up: the estimator learns the gyro bias there,
    # where the wheels are exact, not from miscalibrated wheels in motion.
    phases = [Phase("standstill", 2.0, body(0.0, 0.0)),
              Phase("straight", 4.0 * s, body(0.5, 0.0)),
              Phase("spin", 2.0 * math.pi / spin_rate * max(s, 0.5), body(0.0, spin_rate))]
    for name, (vn, ve) in (("square N", (leg_v, 0.0)), ("square E", (0.0, leg_v)),
                           ("square S", (-leg_v, 0.0)), ("square W", (0.0, -leg_v))):
        phases.append(Phase(name, leg_s, earth(vn, ve)))
    phases += [Phase("eight left", 2.0 * math.pi / eight_w * max(s, 0.5), body(eight_v, eight_w)),
               Phase("eight right", 2.0 * math.pi / eight_w * max(s, 0.5), body(eight_v, -eight_w)),
               Phase("stop", 1.0, body(0.0, 0.0)),
               Phase("timeout", 1.5, None)]
    return phases


# The goto scenario's course (north, east in metres of the autopilot's frame, times the scale) and how each
# target is sent; lat/lon ones are placed as a map click would: from the vehicle's GPS position.
GOTO_COURSE = ((3.0, 0.0, "MISSION_ITEM_INT"), (3.0, 2.0, "DO_REPOSITION"), (1.5, 3.0, "LOCAL_NED"),
               (0.0, 2.0, "GLOBAL_INT"), (0.0, 0.0, "MISSION_ITEM_INT"))
GOTO_TIMEOUT_S = 30.0
POSITION_MASK = 0x0DF8  # SET_POSITION_TARGET_*: x, y (z) used; velocity, acceleration, yaw ignored


@dataclass(frozen=True)
class Summary:
    distance_m: float
    wheel_final_m: float
    wheel_max_m: float
    ekf_final_m: float
    ekf_max_m: float
    wheel_heading_max_deg: float
    ekf_heading_max_deg: float
    latency_p50_ms: float
    latency_p99_ms: float
    latency_samples: int
    rejected: int
    odometry_rate_hz: float

    def table(self) -> str:
        rows = [("distance driven", f"{self.distance_m:.2f} m", ""),
                ("final position error", f"{self.wheel_final_m:.3f} m", f"{self.ekf_final_m:.3f} m"),
                ("max position error", f"{self.wheel_max_m:.3f} m", f"{self.ekf_max_m:.3f} m"),
                ("max heading error", f"{self.wheel_heading_max_deg:.2f} deg", f"{self.ekf_heading_max_deg:.2f} deg"),
                (*latency_row(self.latency_p50_ms, self.latency_p99_ms, self.latency_samples), ""),
                ("ODOMETRY rate at the GCS", f"{self.odometry_rate_hz:.1f} Hz", ""),
                ("requests rejected by the bridge", str(self.rejected), "")]
        width = max(len(a) for a, _, _ in rows)
        out = [f"{'':{width}s} {'wheel odometry':>18s} {'EKF (published)':>18s}"]
        out += [f"{a:{width}s} {b:>18s} {c:>18s}" for a, b, c in rows]
        return "\n".join(out)

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.__dict__.items()}


def latency_row(p50_ms: float, p99_ms: float, samples: int) -> tuple[str, str]:
    """A latency row's name and value, saying how many samples it rests on: the goto scenario sends one
    request, and the p99 of fewer than 100 samples is only their largest (percentile() is nearest-rank)."""
    name = "request->override latency"
    if samples == 0:
        return name, "no requests"
    if samples == 1:
        return f"{name}, 1 sample", f"{p50_ms:.2f} ms"
    upper = "p99" if samples >= 100 else "max"
    return f"{name} p50/{upper}, {samples} samples", f"{p50_ms:.2f} / {p99_ms:.2f} ms"


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    return port


SCENARIOS: dict[str, tuple[str, str]] = {
    # name: (vehicle TOML for the emulator, scenario TOML events); the bridge is told nominal geometry.
    "clean": ("", ""),
    "miscalibrated": ("true_right_radius_m = 0.051\ntrue_track_width_m = 0.309\n", ""),
    "slip": ("", '[[event]]\nkind = "slip"\nwheel = "left"\nratio = 0.3\nstart_s = 6.0\nduration_s = 4.0\n'
                 '[[event]]\nkind = "slip"\nwheel = "right"\nratio = 0.25\nstart_s = 18.0\nduration_s = 3.0\n'),
    "gyro-bias": ("gyro_bias_rad_s = 0.02\n", ""),
    "goto": ("", ""),  # targets, not a route (Demo._goto)
    "obstacles": ("", obstacles.scenario_toml()),  # and a proximity sensor, GUIDED (demo_obstacles)
}
# What each scenario shows (`demo --help`).
SCENARIO_HELP: dict[str, str] = {
    "clean": "the route on an exact robot",
    "miscalibrated": "the right wheel 2 %% large, the track 3 %% wide: what the gyro corrects",
    "slip": "each wheel slips for a few seconds: caught by the gyro",
    "gyro-bias": "a 0.02 rad/s gyro bias: learnt at the standstill",
    "goto": "five go-here targets from the GCS (GUIDED), each arrival error",
    "obstacles": "a wall and a post, a proximity sensor: GUIDED velocity requests at each, and the bridge "
                 "stops the rover AVOID_MARGIN short",
}


def picture_name(scenario: str) -> str:
    """Each scenario's own picture: demo.png for the clean route, demo-SCENARIO.png otherwise."""
    return "demo.png" if scenario == "clean" else f"demo-{scenario}.png"


def _wrap(a: float) -> float:
    return math.remainder(a, 2.0 * math.pi)


def _interp(series: list[tuple[float, float, float, float]], t: float) -> tuple[float, float, float] | None:
    """Linear interpolation of (a, b, yaw) at time t (yaw across the wrap); None outside the series."""
    if not series or t < series[0][0] or t > series[-1][0]:
        return None
    i = bisect.bisect_left(series, (t, -math.inf, -math.inf, -math.inf))
    if series[i][0] == t or i == 0:
        return series[i][1], series[i][2], series[i][3]
    (t0, a0, b0, y0), (t1, a1, b1, y1) = series[i - 1], series[i]
    f = (t - t0) / (t1 - t0) if t1 > t0 else 1.0
    return a0 + f * (a1 - a0), b0 + f * (b1 - b0), y0 + f * _wrap(y1 - y0)


def _interp_yaw(samples: list[tuple[float, float]], t: float) -> float | None:
    if not samples or t < samples[0][0] or t > samples[-1][0]:
        return None
    i = bisect.bisect_left(samples, (t, -math.inf))
    if samples[i][0] == t or i == 0:
        return samples[i][1]
    (t0, y0), (t1, y1) = samples[i - 1], samples[i]
    return y0 + (t - t0) / (t1 - t0) * _wrap(y1 - y0) if t1 > t0 else y1


def _error_at(estimate: list[tuple[float, float, float, float]], t: float, series: Series
              ) -> tuple[float, float] | None:
    """(position error, heading error in degrees) of the estimate's sample nearest t, against the truth at that
    sample's own stamp; None outside the estimate's or the truth's time span. An estimate is judged where it
    was published, not between its samples: the EKF's ODOMETRY is 33-48 ms apart in real time, and a straight
    line drawn across such a gap while a turn's rate changed put 0.05 deg on it that no message carried
    (the wheels, at the truth yaw's own 20 ms stamps, drew none)."""
    if not estimate or t < estimate[0][0] or t > estimate[-1][0]:
        return None
    i = bisect.bisect_left(estimate, (t, -math.inf, -math.inf, -math.inf))
    if i == len(estimate) or (i > 0 and t - estimate[i - 1][0] < estimate[i][0] - t):
        i -= 1
    ts, a, b, yaw = estimate[i]
    truth = _interp(series.truth, ts)
    if truth is None:
        return None
    true_yaw = _interp_yaw(series.truth_yaw, ts) if series.truth_yaw else truth[2]
    if true_yaw is None:
        return None
    return math.hypot(a - truth[0], b - truth[1]), abs(math.degrees(_wrap(yaw - true_yaw)))


def errors_over_time(series: Series) -> list[tuple[float, float, float, float, float]]:
    """(t since the first truth sample, wheel position error, EKF position error, wheel and EKF heading
    errors in degrees), at each ground-truth sample inside both estimates' time spans (each estimate's
    nearest sample, against the truth at its stamp: _error_at)."""
    out = []
    t0 = series.truth[0][0] if series.truth else 0.0
    for t, *_ in series.truth:
        w = _error_at(series.wheel, t, series)
        k = _error_at(series.ekf, t, series)
        if w is None or k is None:
            continue
        out.append((t - t0, w[0], k[0], w[1], k[1]))
    return out


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    idx = min(len(ordered) - 1, max(0, math.ceil(q / 100.0 * len(ordered)) - 1))
    return ordered[idx]


def latencies_from_tlog(path: Path) -> list[float]:
    """Request -> override latency inside the bridge, from its own .tlog (frames in and out, timestamped)."""
    if not path.exists():
        return []
    log: Any = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    pending: float | None = None
    out: list[float] = []
    while True:
        msg = log.recv_match(type=["SET_POSITION_TARGET_LOCAL_NED", "RC_CHANNELS_OVERRIDE"])
        if msg is None:
            break
        if msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
            pending = msg._timestamp
        elif pending is not None:
            out.append((msg._timestamp - pending) * 1000.0)
            pending = None
    log.close()
    return out


def send_target(gcs: Any, fix: tuple[float, float, float, float], north: float, east: float, how: str) -> None:
    """One go-here target, sent as ``how`` says; ``fix``: a GPS position and where the truth was then."""
    lat0, lon0, n0, e0 = fix  # a map click: the target's offset from where the GPS puts the rover
    lat = lat0 + math.degrees((north - n0) / EARTH_RADIUS_M)
    lon = lon0 + math.degrees((east - e0) / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
    lat_e7, lon_e7 = round(lat * 1e7), round(lon * 1e7)
    if how == "MISSION_ITEM_INT":
        gcs.mav.mission_item_int_send(1, 1, 0, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                      mavlink.MAV_CMD_NAV_WAYPOINT, 2, 0, 0, 0, 0, 0, lat_e7, lon_e7, 0.0, 0)
    elif how == "DO_REPOSITION":
        gcs.mav.command_int_send(1, 1, mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_CMD_DO_REPOSITION, 0, 0, -1,
                                 mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, math.nan, lat_e7, lon_e7, 0.0)
    elif how == "LOCAL_NED":
        gcs.mav.set_position_target_local_ned_send(0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, POSITION_MASK, north,
                                                   east, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    else:
        gcs.mav.set_position_target_global_int_send(0, 1, 1, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                    POSITION_MASK, lat_e7, lon_e7, 0, 0, 0, 0, 0, 0, 0, 0, 0)


_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def _die_with_parent(parent_pid: int) -> None:
    """In a child before exec: SIGTERM when the demo's thread that started it dies, however it dies
    (Linux prctl PR_SET_PDEATHSIG; elsewhere nothing, and the demo's own stop is all there is)."""
    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent_pid:  # the demo died before the request took hold: nothing would signal us
        os._exit(1)


class Demo:
    def __init__(self, scenario: str = "clean", scale: float = 1.0, seed: int = 1,
                 progress: TextIO | None = sys.stderr, workdir: Path | None = None) -> None:
        if scenario not in SCENARIOS:
            raise ValueError(f"unknown scenario {scenario!r}; choose from {', '.join(SCENARIOS)}")
        self.scenario = scenario
        self.scale = scale
        self.seed = seed
        self.progress = progress
        self.workdir = workdir
        self.procs: list[subprocess.Popen[bytes]] = []
        self.series = Series()
        self._last_yaw = 0.0
        self._yaw_waiting: float | None = None  # a SIMSTATE yaw waiting for its step's WHEEL_DISTANCE
        self._last_progress_s = -1.0
        self._last_phase = ""
        self._fix: tuple[float, float, float, float] | None = None  # GLOBAL_POSITION_INT lat, lon at north, east
        self._speed_m_s = 0.0
        self._mode: int | None = None
        self._reached = 0

    @contextlib.contextmanager
    def _processes(self, tmp: Path) -> Iterator[Any]:
        ap_port, gcs_port = free_udp_port(), free_udp_port()
        vehicle_toml, scenario_toml = SCENARIOS[self.scenario]
        vehicle = tmp / "vehicle.toml"
        # SCHED_LOOP_RATE 100: the bridge's 50 Hz WHEEL_DISTANCE and ATTITUDE are granted (Rover's default 50
        # caps every stream at 40 Hz, and deploy/ardupilot-rover.parm says so).
        params = {"SCHED_LOOP_RATE": 100.0, **(obstacles.VEHICLE_PARAMS if self.scenario == "obstacles" else {})}
        vehicle.write_text(vehicle_toml + "[params]\n" + "".join(f"{k} = {v}\n" for k, v in params.items()))
        profile = tmp / "profile.toml"
        profile.write_text('[odometry]\ntargets = "gcs"\n'
                           + (obstacles.PROFILE_TOML if self.scenario == "obstacles" else ""))
        sitl_cmd = [sys.executable, "-m", "sitl", "--connect", f"udpin:127.0.0.1:{ap_port}", "--seed",
                    str(self.seed), "--start-armed", "--vehicle", str(vehicle)]
        if scenario_toml:
            (tmp / "scenario.toml").write_text(scenario_toml)
            sitl_cmd += ["--scenario", str(tmp / "scenario.toml")]
        bridge_cmd = [sys.executable, "-m", "rover_bridge", "run", "--params", str(profile),
                      "--autopilot", f"udpout:127.0.0.1:{ap_port}", "--gcs", f"udpin:127.0.0.1:{gcs_port}",
                      "--tlog", str(tmp / "bridge.tlog"), "--stats-json", str(tmp / "stats.json")]
        # Own process groups: a terminal's Ctrl-C reaches only the demo, which then stops them in order.
        # A demo that dies without stopping them (SIGKILL, SIGTERM, a closed terminal's SIGHUP) takes
        # them with it: the kernel sends each one SIGTERM (the bridge then stops the rover as always).
        for cmd, log_name in ((sitl_cmd, "sitl.log"), (bridge_cmd, "bridge.log")):
            with open(tmp / log_name, "wb") as log_file:
                self.procs.append(subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT,
                                                   start_new_session=True,
                                                   preexec_fn=functools.partial(_die_with_parent, os.getpid())))
        gcs: Any = mavutil.mavlink_connection(f"udpout:127.0.0.1:{gcs_port}", source_system=GCS_SYSID,
                                              source_component=GCS_COMPID, dialect="ardupilotmega")
        try:
            yield gcs
        finally:
            gcs.close()
            self.stop_processes()

    def stop_processes(self) -> None:
        """SIGTERM the bridge first (it releases the overrides), then the emulator; SIGKILL stragglers."""
        for proc in reversed(self.procs):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=5.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()

    def run(self) -> tuple[Summary, list[tuple[float, float, float, float, float]], dict[str, Any]]:
        with tempfile.TemporaryDirectory(prefix="rover-bridge-demo-") as tmp_name:
            tmp = Path(tmp_name) if self.workdir is None else self.workdir
            tmp.mkdir(parents=True, exist_ok=True)
            with self._processes(tmp) as gcs:
                self._wait_ready(gcs)
                if self.scenario == "goto":
                    self._goto(gcs)
                elif self.scenario == "obstacles":
                    self._guided(gcs, WheelOdometry(track_width_m=0.30), {"next_hb": 0.0}, ("AVOID_MARGIN",))
                    self._drive(gcs, obstacles.obstacle_route())
                else:
                    self._drive(gcs, route(self.scale))
            for proc, name in zip(self.procs, ("sitl", "bridge"), strict=True):
                if proc.returncode not in (0, -signal.SIGTERM):
                    text = (tmp / f"{name}.log").read_text(errors="replace")[-2000:]
                    raise RuntimeError(f"{name} exited with {proc.returncode}:\n{text}")
            stats: dict[str, Any] = {}
            if (tmp / "stats.json").exists():
                stats = json.loads((tmp / "stats.json").read_text())
            latencies = latencies_from_tlog(tmp / "bridge.tlog")
        errs = errors_over_time(self.series)
        return self._summarise(errs, latencies, stats), errs, stats

    def _say(self, text: str, phase: str = "") -> None:
        """A live line on a terminal (5 Hz); one line per phase when the output is a log file."""
        if self.progress is None:
            return
        now = time.monotonic()
        if self.progress.isatty():
            if now - self._last_progress_s >= 0.2:
                self._last_progress_s = now
                self.progress.write("\r" + text.ljust(79)[:79])
                self.progress.flush()
        elif phase != self._last_phase:
            self._last_phase = phase
            self.progress.write(text.rstrip() + "\n")
            self.progress.flush()

    def _wait_ready(self, gcs: Any, timeout_s: float = 15.0) -> None:
        """Until the bridge forwards the autopilot's heartbeat and publishes ODOMETRY."""
        deadline = time.monotonic() + timeout_s
        seen_ap = seen_odom = False
        next_hb = 0.0
        while not (seen_ap and seen_odom):
            now = time.monotonic()
            if now > deadline:
                raise RuntimeError("the emulator and the bridge did not come up within "
                                   f"{timeout_s:.0f} s (autopilot heartbeat: {seen_ap}, odometry: {seen_odom})")
            for proc in self.procs:
                if proc.poll() is not None:
                    raise RuntimeError(f"{proc.args!r} exited early with {proc.returncode}")
            if now >= next_hb:
                gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                next_hb = now + 0.5
            msg = gcs.recv_match(blocking=True, timeout=0.1)
            if msg is None:
                continue
            if msg.get_type() == "HEARTBEAT" and msg.get_srcComponent() == 1 and not seen_ap:
                seen_ap = True
                # Ground truth at 20 Hz from the emulator, asked for through the bridge like any GCS would
                # (the true yaw, SIMSTATE, comes with the bridge's WHEEL_DISTANCE: Series).
                gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                          mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 50_000, 0, 0, 0, 0, 0)
            if msg.get_type() == "ODOMETRY":
                seen_odom = True
            self._say(f"starting: autopilot {'up' if seen_ap else '...'}, bridge {'up' if seen_odom else '...'}",
                      f"start {seen_ap} {seen_odom}")

    def _drive(self, gcs: Any, phases: list[Phase]) -> None:
        total_s = sum(p.duration_s for p in phases)
        wheel = WheelOdometry(track_width_m=0.30)
        start = time.monotonic()
        next_req = next_hb = 0.0
        phase_end = 0.0
        for phase in phases:
            phase_end += phase.duration_s
            self.series.mark(phase.name)
            request = phase.request
            if request is not None and phase.aim_ne is not None and self.series.truth:
                request = aimed(request, self.series.truth[-1][1:3], phase.aim_ne)
            while (t := time.monotonic() - start) < phase_end:
                if t >= next_hb:
                    gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                    next_hb += 1.0
                if request is not None and t >= next_req:
                    r = request
                    gcs.mav.set_position_target_local_ned_send(
                        int(t * 1000), 1, 1, r.frame, r.type_mask, 0, 0, 0, r.vx_m_s, r.vy_m_s, 0, 0, 0, 0,
                        r.yaw_cw_rad, r.yaw_rate_cw_rad_s)
                    if self.series.truth:
                        self.series.requested.append((self.series.truth[-1][0], r.speed_m_s))
                    next_req = t + 1.0 / REQUEST_RATE_HZ
                msg = gcs.recv_match(blocking=True, timeout=0.01)
                while msg is not None:
                    self._collect(msg, wheel)
                    msg = gcs.recv_match(blocking=False)
                self._say(self._progress_line(phase.name, t, total_s), phase.name)
        if self.progress is not None and self.progress.isatty():
            self.progress.write("\n")

    def _pump(self, gcs: Any, wheel: WheelOdometry, state: dict[str, float]) -> None:
        """Heartbeat at 1 Hz, take in what arrived for 10 ms."""
        now = time.monotonic()
        if now >= state["next_hb"]:
            gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            state["next_hb"] = now + 1.0
        msg = gcs.recv_match(blocking=True, timeout=0.01)
        while msg is not None:
            self._collect(msg, wheel)
            msg = gcs.recv_match(blocking=False)

    def _guided(self, gcs: Any, wheel: WheelOdometry, state: dict[str, float], params: tuple[str, ...] = ()
                ) -> None:
        """GUIDED, a GPS position and ground truth; and the autopilot's ``params`` (asked for once a second)."""
        start = time.monotonic()
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                                  15, 0, 0, 0, 0, 0)
        asked = -1.0
        while (self._mode != 15 or self._fix is None or not self.series.truth
               or any(p not in self.series.params for p in params)):
            if time.monotonic() - start > 10.0:
                raise RuntimeError(f"the autopilot did not report GUIDED, a GPS position and {params} within 10 s")
            if time.monotonic() - asked >= 1.0:
                asked = time.monotonic()
                for p in params:
                    gcs.mav.param_request_read_send(1, 1, p.encode(), -1)
            self._pump(gcs, wheel, state)

    def _goto(self, gcs: Any) -> None:
        """The goto scenario: GUIDED, then each target of GOTO_COURSE once (module doc)."""
        wheel = WheelOdometry(track_width_m=0.30)
        state = {"next_hb": 0.0}
        self._guided(gcs, wheel, state)
        for n, (north, east, how) in enumerate(GOTO_COURSE):
            north, east = north * self.scale, east * self.scale
            reached_before, sent = self._reached, time.monotonic()
            self.series.mark(f"go here {n + 1}")
            assert self._fix is not None
            send_target(gcs, self._fix, north, east, how)
            while not (self._reached > reached_before and self._speed_m_s < 0.01):
                if time.monotonic() - sent > GOTO_TIMEOUT_S:
                    raise RuntimeError(f"target {n + 1} ({north:.1f} N, {east:.1f} E) not reached in "
                                       f"{GOTO_TIMEOUT_S:.0f} s")
                self._pump(gcs, wheel, state)
                pose = self.series.truth[-1]
                self._say(f"go here {n + 1}/{len(GOTO_COURSE)} ({how}): {north:+.1f} N {east:+.1f} E, now "
                          f"N {pose[1]:+6.2f} E {pose[2]:+6.2f}", f"goto {n}")
            pose = self.series.truth[-1]
            self.series.goto.append(GotoLeg(north, east, how, math.hypot(pose[1] - north, pose[2] - east),
                                            time.monotonic() - sent))
        end = time.monotonic() + 1.0
        while time.monotonic() < end:  # the last ODOMETRY and telemetry of the stop
            self._pump(gcs, wheel, state)
        if self.progress is not None and self.progress.isatty():
            self.progress.write("\n")

    def _progress_line(self, phase: str, t: float, total_s: float) -> str:
        done = int(20 * min(1.0, t / total_s))
        pose = self.series.truth[-1] if self.series.truth else (0.0, 0.0, 0.0, 0.0)
        return (f"[{'#' * done}{'.' * (20 - done)}] {t:5.1f}/{total_s:4.1f} s {phase:12s} "
                f"N {pose[1]:+6.2f} E {pose[2]:+6.2f} yaw {math.degrees(pose[3]):+7.1f}")

    def _collect(self, msg: Any, wheel: WheelOdometry) -> None:
        kind = msg.get_type()
        if kind == "LOCAL_POSITION_NED":
            t = msg.time_boot_ms * 1e-3
            if not self.series.truth or t > self.series.truth[-1][0]:
                self.series.truth.append((t, float(msg.x), float(msg.y), self._last_yaw))
            self._speed_m_s = math.hypot(float(msg.vx), float(msg.vy))
            along = float(msg.vx) * math.cos(self._last_yaw) + float(msg.vy) * math.sin(self._last_yaw)
            if not self.series.speed or t > self.series.speed[-1][0]:
                self.series.speed.append((t, along))
        elif kind == "PARAM_VALUE":
            self.series.params[str(msg.param_id)] = float(msg.param_value)
        elif kind == "GLOBAL_POSITION_INT" and (msg.lat or msg.lon) and self.series.truth:
            self._fix = (msg.lat * 1e-7, msg.lon * 1e-7, self.series.truth[-1][1], self.series.truth[-1][2])
        elif kind == "HEARTBEAT" and msg.get_srcComponent() == 1:
            self._mode = int(msg.custom_mode)
        elif kind == "MISSION_ITEM_REACHED":
            self._reached += 1
        elif kind == "SIMSTATE":
            self._last_yaw = self._yaw_waiting = float(msg.yaw)
        elif kind == "ODOMETRY":
            self.series.odometry_msgs += 1
            w, _, _, z = msg.q
            t = msg.time_usec * 1e-6
            if not self.series.ekf or t > self.series.ekf[-1][0]:
                self.series.ekf.append((t, float(msg.x), float(msg.y), 2.0 * math.atan2(z, w)))
        elif kind == "WHEEL_DISTANCE" and msg.count >= 2:
            pose = wheel.update(left_m=float(msg.distance[0]), right_m=float(msg.distance[1]))
            # Our pose is x forward / y left / yaw CCW; truth and ODOMETRY are y right, yaw CW.
            t = msg.time_usec * 1e-6
            if not self.series.wheel or t > self.series.wheel[-1][0]:
                self.series.wheel.append((t, pose.x_m, -pose.y_m, -pose.yaw_rad))
            if self._yaw_waiting is not None and (not self.series.truth_yaw or t > self.series.truth_yaw[-1][0]):
                self.series.truth_yaw.append((t, self._yaw_waiting))
            self._yaw_waiting = None
        elif kind == "STATUSTEXT":
            self.series.statustext.append(str(msg.text))

    def _summarise(self, errs: list[tuple[float, float, float, float, float]], latencies: list[float],
                   stats: dict[str, Any]) -> Summary:
        truth = self.series.truth
        distance = sum(math.hypot(b[1] - a[1], b[2] - a[2]) for a, b in itertools.pairwise(truth))
        counters = stats.get("command", {}) if isinstance(stats.get("command"), dict) else {}
        rejected = sum(int(v) for k, v in counters.items() if k.startswith("rejected"))
        ekf_times = [e[0] for e in self.series.ekf]
        rate = (len(ekf_times) - 1) / (ekf_times[-1] - ekf_times[0]) if len(ekf_times) > 1 else 0.0
        nan = float("nan")
        return Summary(
            distance_m=distance,
            wheel_final_m=errs[-1][1] if errs else nan, wheel_max_m=max((e[1] for e in errs), default=nan),
            ekf_final_m=errs[-1][2] if errs else nan, ekf_max_m=max((e[2] for e in errs), default=nan),
            wheel_heading_max_deg=max((e[3] for e in errs), default=nan),
            ekf_heading_max_deg=max((e[4] for e in errs), default=nan),
            latency_p50_ms=percentile(latencies, 50), latency_p99_ms=percentile(latencies, 99),
            latency_samples=len(latencies),
            rejected=rejected, odometry_rate_hz=rate)


def run_demo(scenario: str, scale: float, seed: int, plot_path: Path | None,
             out: Callable[[str], None] = print) -> Summary:
    demo = Demo(scenario=scenario, scale=scale, seed=seed)
    try:
        summary, errs, _stats = demo.run()
    finally:
        demo.stop_processes()
    return report(demo, summary, errs, plot_path, out)


def report(demo: Demo, summary: Summary, errs: list[tuple[float, float, float, float, float]],
           plot_path: Path | None, out: Callable[[str], None] = print) -> Summary:
    """What a finished run prints and draws; a RuntimeError (after both) if the rover touched an obstacle."""
    scenario = demo.scenario
    out(f"\nrover-bridge demo: scenario {scenario!r}, {len(demo.series.truth)} truth samples, "
        f"{demo.series.odometry_msgs} ODOMETRY messages\n")
    out(summary.table())
    if demo.series.goto:
        out("\n" + GotoLeg.table(demo.series.goto))
    legs = obstacles.obstacle_legs(demo.series, demo.series.params.get("AVOID_MARGIN", math.nan))
    if legs:
        out("\nfrom the rover's centre to each obstacle, by ground truth:\n" + obstacles.ObstacleLeg.table(legs))
    if plot_path is not None:
        try:
            title = f"rover-bridge demo ({scenario})"
            if scenario == "obstacles":
                from rover_bridge.app.demo_obstacles_picture import plot_obstacles

                plot_obstacles(demo.series, legs, plot_path, title)
            else:
                from rover_bridge.app.demo_picture import plot

                plot(demo.series, errs, plot_path, title)
            out(f"\npicture: {plot_path}")
        except ImportError:
            out("\npicture skipped: matplotlib is not installed (pip install matplotlib)")
    if os.environ.get("ROVER_BRIDGE_DEMO_JSON"):
        data: dict[str, Any] = {**summary.as_dict(), "obstacles": [leg.as_dict() for leg in legs]}
        Path(os.environ["ROVER_BRIDGE_DEMO_JSON"]).write_text(json.dumps(data))
    if touched := [leg.obstacle for leg in legs if leg.touched]:
        raise RuntimeError(f"the rover touched the {' and the '.join(touched)}: avoidance did not stop it")
    return summary
