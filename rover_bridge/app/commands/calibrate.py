"""rover-bridge calibrate: a guided bring-up against the live autopilot (see rover_bridge.app.calibration).

The rover drives by itself for about a minute (`--quick`: about half a minute): it needs to be on
the ground with a couple of metres of room around it, and armed. It asks for confirmation (`--yes`
skips it), shows its progress, and stops safely (neutral, release, confirmed) on Ctrl-C, on link
loss, on a disarm or a stop mode, and on any wiring fault it finds. It prints what it identified
and writes a profile patch (never the profile itself). Exit 0 done, 1 aborted, 2 bad usage.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import time
from pathlib import Path
from types import FrameType

from rover_bridge.app.calibration import Calibration, CalibrationResult
from rover_bridge.app.commands import add_params_argument
from rover_bridge.app.composition import BridgeCore
from rover_bridge.app.loop import RUN_BATCH, Runner
from rover_bridge.app.paths import output_problem
from rover_bridge.command.core import CommandState
from rover_bridge.errors import ConfigError
from rover_bridge.kinematics import MeasuredWheels
from rover_bridge.mavlink.links import Endpoint, check_url
from rover_bridge.mavlink.wire import Link
from rover_bridge.params import load_profile

NAME = "calibrate"
HELP = ("bring-up: drive a short scripted sequence and identify each wheel's PWM->speed map and deadband, the "
        "effective track width and the radius ratio; writes a profile patch")

log = logging.getLogger("rover_bridge.calibrate")

READY_TIMEOUT_S = 20.0
STREAMS_TIMEOUT_S = 10.0
PROGRESS_S = 0.5
ABORT_STATES = {CommandState.LINK_LOST: "the autopilot's heartbeat was lost",
                CommandState.DISARMED: "the autopilot was disarmed",
                CommandState.HOLD: "the autopilot went to a stop mode (HOLD)",
                CommandState.FAULT: "a wiring fault"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_params_argument(parser)
    parser.add_argument("--autopilot", default="tcp:127.0.0.1:5760", help="autopilot link (default %(default)s)")
    parser.add_argument("--gcs", action="append", default=None, metavar="URL",
                        help="ground-station link to forward to, repeatable (default: none)")
    parser.add_argument("--out", default="calibration-patch.toml", metavar="PATH",
                        help="where to write the profile patch (default %(default)s); the profile is not changed")
    parser.add_argument("--quick", action="store_true", help="fewer PWM steps (about half the time)")
    parser.add_argument("--yes", action="store_true", help="do not ask for confirmation before driving")


def main(args: argparse.Namespace) -> int:
    profile = load_profile(args.params)
    gcs_urls = [u for u in (args.gcs or []) if u.lower() != "none"]
    problems = [p for p in (check_url(u) for u in [args.autopilot, *gcs_urls]) if p]
    if out_problem := output_problem(args.out, "--out"):  # found now, not after a minute of driving
        problems.append(out_problem)
    if problems:
        raise ConfigError(problems)
    cal = Calibration(profile, quick=args.quick)
    print(f"rover-bridge calibrate: the rover will drive by itself for about {cal.total_s:.0f} s: PWM steps on "
          "each wheel (it pivots), straight runs forward and back, spins both ways. Put it on the ground with "
          "2 m of room around it. Ctrl-C stops it at any time.", file=sys.stderr)
    if not args.yes:
        if not sys.stdin.isatty():
            raise ConfigError(["calibrate: confirm with --yes when there is no terminal to ask on"])
        if input("Drive now? [y/N] ").strip().lower() not in ("y", "yes"):
            print("not started", file=sys.stderr)
            return 1
    core = BridgeCore(profile)
    ids = {"source_system": core.identity.own_system_id, "source_component": core.identity.component_id}
    autopilot = Endpoint(args.autopilot, Link.AUTOPILOT, **ids)
    runner = Runner(core, autopilot, [Endpoint(u, Link.GCS, **ids) for u in gcs_urls])
    stop: list[int] = []

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.append(signum)

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    est = core.estimate

    def observe(sample: MeasuredWheels, now_s: float) -> None:
        gyro = est.last_gyro
        cal.sample(sample, None if gyro is None else gyro[1] - est.state.gyro_bias_rad_s, now_s)

    core.wheel_observers.append(observe)
    try:
        reason = _run(runner, cal, stop)
    finally:
        runner.stop_safely(time.monotonic)
        runner.close()
        for s, h in old.items():
            signal.signal(s, h)
    if reason is not None or cal.result is None:
        print(f"\ncalibration aborted: {reason or cal.error}; the rover was stopped", file=sys.stderr)
        return 1
    print("\n" + table(cal.result, profile.robot.max_wheel_rad_s))
    header = (f"rover-bridge calibrate {time.strftime('%Y-%m-%d %H:%M')}: {args.autopilot}, profile {args.params}\n"
              "copy these keys into the profile (its other keys stay as they are)")
    Path(args.out).write_text(cal.result.patch_toml(header), encoding="utf-8")
    print(f"\nprofile patch: {args.out}")
    return 0


def _run(runner: Runner, cal: Calibration, stop: list[int]) -> str | None:
    """Drive the sequence; the reason it ended early, or None when it finished."""
    core = runner.core
    clock = time.monotonic
    start = clock()
    streams_since: float | None = None
    last_pwm = None
    next_progress = 0.0
    shown = ""
    ready: list[Endpoint] | None = None
    while True:
        now = clock()
        runner.step(now, RUN_BATCH, ready)
        if stop:
            return "interrupted"
        state = core.command.state
        vehicle_known = core.identity.vehicle_system_id is not None and core.command.autopilot_alive
        if last_pwm is None:  # not driving yet: the vehicle, armed, streams flowing
            if not vehicle_known:
                if now - start > READY_TIMEOUT_S:
                    return f"no heartbeat from an autopilot on the link within {READY_TIMEOUT_S:.0f} s"
            elif state is CommandState.DISARMED:
                return "the vehicle is not armed: arm it (ARMING_CHECK may need adjusting for passthrough outputs)"
            else:
                streams_since = now if streams_since is None else streams_since
                fresh = core.command.loop is not None and core.command.loop.fresh(now)
                if not (fresh and core.estimate.last_gyro is not None):
                    if now - streams_since > STREAMS_TIMEOUT_S:
                        return "no WHEEL_DISTANCE or gyro from the autopilot (WENC_* and the stream rates?)"
                    ready = runner.wait(clock)
                    continue
        elif state in ABORT_STATES:
            cal.abort(ABORT_STATES[state])
        if cal.error is not None:
            return cal.error
        if last_pwm is not None or vehicle_known:
            pwm = cal.tick(now)
            if pwm != last_pwm:
                runner.send_all(core.command.set_direct(pwm, now))
                last_pwm = pwm
            if pwm is None:
                return cal.error
        step = cal.step
        if step is not None and sys.stderr.isatty() and now >= next_progress:
            next_progress = now + PROGRESS_S
            done = min(1.0, cal.elapsed_s(now) / cal.total_s)
            print(f"\r[{'#' * round(20 * done):20s}] {100 * done:3.0f} %  {step.name:24s}", end="",
                  file=sys.stderr, flush=True)
        elif step is not None and step.kind != "settle" and step.name != shown:
            shown = step.name  # a log, not a terminal: one line per step
            print(f"calibrate: {step.name} ({cal.elapsed_s(now):.0f} of {cal.total_s:.0f} s)", file=sys.stderr)
        ready = runner.wait(clock)


def table(res: CalibrationResult, top_rad_s: float) -> str:
    rows = [("", "left", "right"),
            ("gain forward (top speed / profile's)", f"{res.left.gain_forward:.3f}", f"{res.right.gain_forward:.3f}"),
            ("gain reverse", f"{res.left.gain_reverse:.3f}", f"{res.right.gain_reverse:.3f}"),
            ("deadband edges, us from trim (fitted)",
             f"{res.left.deadband_us[0]:+.0f} / {res.left.deadband_us[1]:+.0f}",
             f"{res.right.deadband_us[0]:+.0f} / {res.right.deadband_us[1]:+.0f}"),
            ("top speed forward / reverse, rad/s",
             f"{res.left.speed_rad_s[-1]:.2f} / {res.left.speed_rad_s[0]:.2f}",
             f"{res.right.speed_rad_s[-1]:.2f} / {res.right.speed_rad_s[0]:.2f}")]
    lines = [f"{a:40s} {b:>16s} {c:>16s}" for a, b, c in rows]
    lines += [f"{'effective track width':40s} {res.track_width_m:.4f} m",
              f"{'radius ratio right / left':40s} {res.radius_ratio:.4f} "
              f"(radii {res.left_radius_m:.5f} / {res.right_radius_m:.5f} m)",
              f"(the profile's top wheel speed: {top_rad_s:.2f} rad/s)"]
    if res.tuning is None:
        lines.append("the speed loop's gains: not identified (a run did not settle); the defaults stay")
    else:
        lines += [f"{a:40s} {b}" for a, b in res.tuning.report_rows()]
        lines.append("(gains by the SIMC rule on each motion's lag and delay: rover_bridge/app/loop_tuning.py)")
    return "\n".join(lines)
