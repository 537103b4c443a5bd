"""SIGTERM during motion: how long until the autopilot's motor outputs are back at trim (the stop has
been parsed), and until the bridge process has exited (target: both within 200 ms).

Runs the real `python -m rover_bridge run` against the sitl emulator (in this process, wall clock)
and a scripted GCS on UDP loopback, drives forward at 0.5 m/s, then sends SIGTERM. The autopilot link
is UDP or TCP (the emulator then parses a step after it reads, and drops what a closing client sent,
as ArduPilot SITL does); the outputs are RC overrides or DO_SET_SERVO.

    python benchmarks/bench_shutdown.py [--trials 10] [--link udp|tcp|both] [--mode rc_override|servo|both]
"""

from __future__ import annotations

import argparse
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from rover_bridge.app.demo import free_udp_port
from rover_bridge.mavlink.dialect import mavlink, mavutil
from sitl import Emulator, VehicleConfig

REPO = Path(__file__).resolve().parents[1]
BODY_VEL_YAW_RATE_MASK = 0b0000_0101_1100_0111



def trial(seed: int, link: str, params: str) -> tuple[float, float, int]:
    """(ms until both motor outputs are at trim, ms until the process exited, exit code)."""
    ap_port, gcs_port = free_udp_port(), free_udp_port()
    emu = Emulator(VehicleConfig(start_armed=True), seed=seed)
    emu.open(f"udpin:127.0.0.1:{ap_port}" if link == "udp" else "tcpin:127.0.0.1:0")
    ap_url = f"udpout:127.0.0.1:{ap_port}" if link == "udp" else f"tcp:127.0.0.1:{emu.local_address[1]}"
    bridge = subprocess.Popen(
        [sys.executable, "-m", "rover_bridge", "run", "--params", params,
         "--autopilot", ap_url, "--gcs", f"udpin:127.0.0.1:{gcs_port}"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    gcs: Any = mavutil.mavlink_connection(f"udpout:127.0.0.1:{gcs_port}", source_system=255, source_component=190,
                                          dialect="ardupilotmega")
    try:
        last = start = time.monotonic()
        next_request = 0.0
        while emu.truth.v_m_s < 0.45:  # drive until the rover is really moving
            now = time.monotonic()
            if now - start > 60.0:
                raise RuntimeError("the bridge never drove the emulator")
            emu.step(max(0.001, now - last))
            last = now
            if now >= next_request:
                gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                gcs.mav.set_position_target_local_ned_send(0, 1, 1, mavlink.MAV_FRAME_BODY_NED,
                                                           BODY_VEL_YAW_RATE_MASK, 0, 0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0)
                next_request = now + 0.1
            while gcs.recv_msg() is not None:
                pass
            time.sleep(0.002)
        t_signal = time.monotonic()
        bridge.send_signal(signal.SIGTERM)
        released_s: float | None = None
        while time.monotonic() - t_signal < 5.0 and (released_s is None or bridge.poll() is None):
            now = time.monotonic()
            emu.step(max(0.0005, now - last))
            last = now
            if released_s is None and emu.servo_outputs[1] == 1500 and emu.servo_outputs[3] == 1500:
                released_s = now - t_signal
            time.sleep(0.0005)
        code = bridge.wait(timeout=5.0)
        exit_s = time.monotonic() - t_signal
        return (float("nan") if released_s is None else released_s * 1e3), exit_s * 1e3, code
    finally:
        if bridge.poll() is None:
            bridge.kill()
            bridge.wait()
        gcs.close()
        emu.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--link", choices=("udp", "tcp", "both"), default="both")
    parser.add_argument("--mode", choices=("rc_override", "servo", "both"), default="both")
    args = parser.parse_args()
    links = ("udp", "tcp") if args.link == "both" else (args.link,)
    modes = ("rc_override", "servo") if args.mode == "both" else (args.mode,)
    print(f"# SIGTERM during motion, {args.trials} trials each (target: outputs at trim and exit within 200 ms)")
    print(f"{'link':5s} {'mode':12s} | {'at trim median':>14s} {'max':>8s} | {'exited median':>13s} {'max':>8s} "
          "| codes")
    with tempfile.TemporaryDirectory() as tmp:
        for mode in modes:
            params = Path(tmp) / f"{mode}.toml"
            params.write_text(f'[output]\nmode = "{mode}"\n')
            for link in links:
                rows = [trial(seed, link, str(params)) for seed in range(args.trials)]
                stopped = [r[0] for r in rows]
                exited = [r[1] for r in rows]
                print(f"{link:5s} {mode:12s} | {statistics.median(stopped):11.1f} ms {max(stopped):5.1f} ms | "
                      f"{statistics.median(exited):10.1f} ms {max(exited):5.1f} ms | {sorted({r[2] for r in rows})}")


if __name__ == "__main__":
    main()
