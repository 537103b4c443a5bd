"""rover-bridge run: the process on the rover's companion computer.

On SIGINT / SIGTERM (and on any unexpected exception) it sends neutral, then releases the
overrides, waits for the autopilot to confirm them, then exits: 0 for a signal, 1 for an
exception. A stop guard thread (rover_bridge.app.guard) sends the stop itself when the loop is
stuck (signal, systemd's watchdog, safety.loop_watchdog_s); systemd is told READY=1, WATCHDOG=1
and STOPPING=1 (rover_bridge.app.systemd).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import time
from dataclasses import replace
from types import FrameType

from rover_bridge.app.commands import add_params_argument
from rover_bridge.app.composition import BridgeCore
from rover_bridge.app.guard import StopGuard
from rover_bridge.app.loop import Runner, TlogWriter
from rover_bridge.app.paths import output_problem
from rover_bridge.app.systemd import SystemdNotifier
from rover_bridge.command.core import EMERGENCY_PROBE_TS1, CommandState
from rover_bridge.command.modes import mode_name
from rover_bridge.errors import ConfigError
from rover_bridge.mavlink.links import Endpoint, check_url
from rover_bridge.mavlink.signing import SignatureVerifier, load_key, signing_timestamp
from rover_bridge.mavlink.wire import Link
from rover_bridge.params import load_profile, profile_warnings

NAME = "run"
HELP = "bridge an autopilot and ground stations: velocity requests in, wheel overrides and ODOMETRY out"

log = logging.getLogger("rover_bridge.run")

DEFAULT_AUTOPILOT = "tcp:127.0.0.1:5760"
DEFAULT_GCS = "udpout:127.0.0.1:14550"


# With no autopilot HEARTBEAT this long after the start, say so once (a udpout or serial link opens whether or
# not anything is there).
NO_AUTOPILOT_S = 5.0


def silent_autopilot_hint(url: str) -> str:
    """What to check when a link opened but the autopilot says nothing."""
    if url.startswith("udpout:"):
        return "is it running and listening at that address (e.g. SITL's or mavlink-router's udpin)?"
    if url.startswith(("udpin:", "udp:")):
        return "is it running and sending to this port (mavlink-router endpoint, SERIALn_PROTOCOL 2 on a radio)?"
    if url.startswith(("tcp:", "tcpin:")):
        return "the connection is up but nothing speaks MAVLink on it: is this the autopilot's MAVLink port?"
    return ("check the wiring (TX to RX), the baud rate after the comma, and that the autopilot's port speaks "
            "MAVLink 2 (SERIALn_PROTOCOL = 2, SERIALn_BAUD to match)")


def found_line(core: BridgeCore, url: str, again: bool) -> str:
    """The autopilot's heartbeat has been seen: which one, where, in which mode."""
    vehicle = core.command.vehicle
    return (f"autopilot {'back' if again else 'found'}: system {core.identity.vehicle_system_id}, component "
            f"{core.identity.autopilot_component_id} on {url}, {mode_name(vehicle.custom_mode)}, "
            f"{'armed' if vehicle.armed else 'disarmed'}")


def stop_line(why: str, confirmed: bool | None, output_mode: str) -> str:
    """Why the bridge stopped and what became of the outputs (runner.stop_safely's answer)."""
    what = "neutral and release sent" if output_mode == "rc_override" else "trim on both outputs sent"
    how = {True: f"{what}, confirmed by the autopilot", False: f"{what}, NOT confirmed by the autopilot",
           None: "nothing sent (no vehicle was known)"}[confirmed]
    return f"stopped ({why}): {how}"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_params_argument(parser)
    parser.add_argument("--autopilot", default=DEFAULT_AUTOPILOT,
                        help="autopilot link: /dev/ttyAMA0,921600 on a rover, tcp:127.0.0.1:5760 for ArduPilot SITL "
                             "(default %(default)s)")
    parser.add_argument("--gcs", action="append", default=None, metavar="URL",
                        help=f"ground-station link, repeatable (default {DEFAULT_GCS}: QGroundControl and MAVProxy "
                             "listen there); 'none' for no ground station")
    parser.add_argument("--tlog", default=None, metavar="PATH",
                        help="record every MAVLink frame seen and sent to this .tlog (MAVProxy/pymavlink format)")
    parser.add_argument("--stats-json", default=None, metavar="PATH",
                        help="on exit, write the bridge's counters (rejections, states, links) here as JSON")
    parser.add_argument("--key-file", default=None, metavar="PATH",
                        help="MAVLink 2 signing key for the ground-station links (overrides [security] key_file): "
                             "32 raw bytes, 64 hex characters or a MAVProxy passphrase; mode 600")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop safely after this many seconds (tests, demos)")


def main(args: argparse.Namespace) -> int:
    profile = load_profile(args.params)
    if getattr(args, "key_file", None):
        profile = replace(profile, security=replace(profile.security, key_file=args.key_file))
    # Read the key before opening any link: a missing or exposed key stops the start (exit 2).
    key = load_key(profile.security.key_file) if profile.security.key_file else None
    gcs_urls = [u for u in (args.gcs or [DEFAULT_GCS]) if u.lower() != "none"]
    problems = [p for p in (check_url(u) for u in [args.autopilot, *gcs_urls]) if p]
    if args.duration is not None and not args.duration > 0:
        problems.append(f"--duration: expected a positive number of seconds, got {args.duration}")
    # The files it will write, now: not a traceback at start (--tlog) or after the whole run (--stats-json).
    problems += [p for p in (output_problem(path, option) for option, path in
                             (("--tlog", args.tlog), ("--stats-json", args.stats_json)) if path) if p]
    if problems:
        raise ConfigError(problems)
    # Its own few lines (started, autopilot found, stopped) are what a person watching it needs: shown without -v.
    if not log.isEnabledFor(logging.INFO):
        log.setLevel(logging.INFO)
    for warning in profile_warnings(profile):
        log.warning("profile: %s", warning)
    core = BridgeCore(profile)
    own_sys, own_comp = core.identity.own_system_id, core.identity.component_id
    autopilot = Endpoint(args.autopilot, Link.AUTOPILOT, source_system=own_sys, source_component=own_comp)
    gcs = [Endpoint(u, Link.GCS, source_system=own_sys, source_component=own_comp) for u in gcs_urls]
    verifier = None
    if key is not None:
        # Wall-clock start: a replay recorded more than a minute before this start is refused.
        verifier = SignatureVerifier(key, signing_timestamp(time.time()))
        for link_id, ep in enumerate(gcs, start=1):
            ep.setup_signing(key, link_id=link_id, initial_timestamp=verifier.timestamp, verifier=verifier)
    tlog = TlogWriter(open(args.tlog, "wb")) if args.tlog else None  # noqa: SIM115 - closed by the runner
    runner = Runner(core, autopilot, gcs, tlog=tlog)

    stop_requested: list[int] = []
    # Two pipes: the interpreter writes every signal to the first the moment it arrives (whatever the
    # main thread is doing), the stop guard reads it and wakes the loop through the second.
    signal_r, signal_w = os.pipe()
    wake_r, wake_w = os.pipe()
    for fd in (signal_r, signal_w, wake_r, wake_w):
        os.set_blocking(fd, False)

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop_requested.append(signum)

    stop_signals = (signal.SIGINT, signal.SIGTERM, signal.SIGABRT)  # SIGABRT: systemd's WatchdogSignal
    old_handlers = {s: signal.signal(s, on_signal) for s in stop_signals}
    old_wakeup = signal.set_wakeup_fd(signal_w)
    guard = StopGuard(signal_r, wake_w, autopilot, profile.safety.stop_confirm_timeout_s,
                      stall_s=profile.safety.loop_watchdog_s, probe_ts1=EMERGENCY_PROBE_TS1)
    guard.start()
    notifier = SystemdNotifier()

    started: list[bool] = []
    told_silent: list[bool] = []
    alive = [False, False]  # the autopilot's heartbeat is fresh; it has been before

    def on_pass(now_s: float) -> None:
        if not started:
            # After the first pass (its HEARTBEAT is out): the filter, which imports filterpy and scipy
            # (about 0.65 s here). Before READY=1 and the first pass the watchdogs count: the loop waits
            # for it once, at start, never later.
            started.append(True)
            core.estimate.start_filter()
            now_s = time.monotonic()
            notifier.ready()
        guard.passed(now_s)
        guard.frames = runner.emergency_frames
        notifier.ping(now_s)
        if core.command.autopilot_alive is not alive[0]:
            alive[0] = not alive[0]
            if alive[0]:
                log.info("%s", found_line(core, args.autopilot, again=alive[1]))
                alive[1] = True
        if not told_silent and core.command.state is CommandState.WAITING and now_s - start >= NO_AUTOPILOT_S:
            told_silent.append(True)
            log.warning("no HEARTBEAT from the autopilot on %s after %.0f s: %s", args.autopilot, NO_AUTOPILOT_S,
                        silent_autopilot_hint(args.autopilot))

    start = time.monotonic()
    end = None if args.duration is None else start + args.duration
    log.info("rover-bridge running: autopilot %s, gcs %s, profile %s", args.autopilot,
             ", ".join(gcs_urls) or "none", args.params)
    code = 0
    confirmed: bool | None = None
    try:
        runner.run(lambda: bool(stop_requested) or (end is not None and time.monotonic() >= end),
                   wake_fd=wake_r, on_pass=on_pass)
    except Exception:
        log.exception("unexpected error: stopping the rover and exiting")
        code = 1
    finally:
        notifier.stopping()
        guard.stopping()
        try:
            confirmed = runner.stop_safely(time.monotonic)
        finally:
            guard.quit()
            runner.close()
            notifier.close()
            signal.set_wakeup_fd(old_wakeup)
            for s, h in old_handlers.items():
                signal.signal(s, h)
            guard.join(timeout=1.0)
            for fd in (signal_r, signal_w, wake_r, wake_w):
                os.close(fd)
    if args.stats_json:
        write_stats(args.stats_json, runner, verifier)
    if code:
        why = "an unexpected error, above"
    elif stop_requested:
        why = signal.Signals(stop_requested[0]).name
    else:
        why = f"--duration {args.duration:g} s over"
    log.log(logging.INFO if confirmed is not False else logging.WARNING, "%s",
            stop_line(why, confirmed, profile.output.mode))
    return code


def write_stats(path: str, runner: Runner, verifier: SignatureVerifier | None = None) -> None:
    """Counters of every part, for the demo's report and for post-mortems."""
    core = runner.core
    stats = {
        "command": dict(core.command.counters),
        "estimate": dict(core.estimate.counters),
        "runner": {"forwarded": runner.forwarded, "consumed": runner.consumed, "ticks": runner.ticks,
                   "early_ticks": runner.early_ticks, "pack_errors": runner.pack_errors,
                   "passes": runner.passes},
        "links": {ep.url: {"rx": ep.rx_frames, "rx_bad": ep.rx_bad, "tx": ep.tx_frames} for ep in runner.endpoints},
        "timing": runner.timing.stats(),
        "statustext_suppressed": dict(core.reporter.limiter.suppressed),
        "security": dict(core.gate.counters),
        "signatures": dict(verifier.counters) if verifier is not None else {},
    }
    with open(path, "w", encoding="utf-8") as f:
        json.dump(stats, f, indent=1, default=str)
