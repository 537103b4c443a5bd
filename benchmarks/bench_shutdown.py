"""SIGTERM during motion: how long until the autopilot sees the overrides released, and until the
bridge process has exited (target: neutral, release and exit within 200 ms).

Runs the real `python -m rover_bridge run` against the sitl emulator (in this process, wall clock)
and a scripted GCS on UDP loopback, drives forward at 0.5 m/s, then sends SIGTERM.

    python benchmarks/bench_shutdown.py [--trials 10]
"""

from __future__ import annotations

import argparse
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from rover_bridge.app.demo import free_udp_port
from rover_bridge.mavlink.dialect import mavlink, mavutil
from sitl import Emulator, VehicleConfig

REPO = Path(__file__).resolve().parents[1]
BODY_VEL_YAW_RATE_MASK = 0b0000_0101_1100_0111



def trial(seed: int) -> tuple[float, float, int]:
    """(ms until the emulator sees channel 1 released, ms until the process exited, exit code)."""
    ap_port, gcs_port = free_udp_port(), free_udp_port()
    emu = Emulator(VehicleConfig(start_armed=True), seed=seed)
    emu.open(f"udpin:127.0.0.1:{ap_port}")
    bridge = subprocess.Popen(
        [sys.executable, "-m", "rover_bridge", "run", "--params", str(REPO / "params" / "default.toml"),
         "--autopilot", f"udpout:127.0.0.1:{ap_port}", "--gcs", f"udpin:127.0.0.1:{gcs_port}"],
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
            if released_s is None and not emu.autopilot.has_override(1, emu.sim_time_us):
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
    args = parser.parse_args()
    rows = [trial(seed) for seed in range(args.trials)]
    released = [r[0] for r in rows]
    exited = [r[1] for r in rows]
    print(f"# SIGTERM during motion, {args.trials} trials (target: release and exit within 200 ms)")
    print(f"{'':28s} {'median':>8s} {'max':>8s}")
    print(f"{'release seen by autopilot':28s} {statistics.median(released):8.1f} {max(released):8.1f} ms")
    print(f"{'process exited':28s} {statistics.median(exited):8.1f} {max(exited):8.1f} ms")
    print(f"exit codes: {sorted({r[2] for r in rows})}")


if __name__ == "__main__":
    main()
