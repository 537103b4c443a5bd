"""A bridge feeding ArduPilot external navigation restarts mid-drive: ArduPilot's position must not run off.

Emulated autopilot set up as docs/ardupilot.md says (VISO_TYPE 1, EK3_SRC1_POSXY/VELXY/YAW = 6), with
sitl/extnav.py standing for ArduPilot's use of ODOMETRY: a new frame at (0, 0, yaw 0) with an unchanged
reset_counter is a jump it rejects while it fuses the new frame's velocity rotated by the new yaw.
With odometry.frame 'autopilot' (the default when ODOMETRY goes to the autopilot) the restarted bridge
anchors at the autopilot's LOCAL_POSITION_NED and heading and continues its frame; 'start' reproduces
what a real ArduPilot showed.
"""

from __future__ import annotations

import math

import pytest
from lockstep import Lockstep

from rover_bridge.params import profile_from_dict
from sitl import VehicleConfig

pytestmark = pytest.mark.e2e


def autopilot_error_m(ls: Lockstep) -> float:
    pos = ls.emu.autopilot.extnav.position()
    assert pos is not None, "the autopilot is not navigating on the bridge's ODOMETRY"
    return math.hypot(pos[0] - ls.emu.truth.x_m, pos[1] - ls.emu.truth.y_m)


@pytest.mark.parametrize("frame", ["auto", "start"])
def test_a_restart_mid_drive_keeps_the_autopilots_position(frame: str) -> None:
    profile = profile_from_dict({"odometry": {"targets": "both", "frame": frame}})
    ls = Lockstep(profile, VehicleConfig(external_nav=True), seed=5)
    try:
        ls.run_for(8.0)  # cold start of both: no LOCAL_POSITION_NED, the bridge starts at the origin
        assert ls.emu.autopilot.extnav.using
        drive = {"send": lambda: ls.send_body_velocity(0.6, 0.15)}  # a gentle right arc
        ls.run_for(10.0, **drive)
        before = autopilot_error_m(ls)
        assert before < 0.15
        ls.restart_bridge(profile)
        errors = []
        for _ in range(15):
            ls.run_for(1.0, **drive)
            errors.append(autopilot_error_m(ls))
        counters = ls.emu.autopilot.extnav.counters
        if frame == "auto":
            assert max(errors) < 0.3, errors
            assert counters["pos_rejected"] == 0 and counters["pos_resets"] == 0
            assert any("autopilot frame" in m.text for _, m in ls.view.of("STATUSTEXT"))
        else:  # what the real ArduPilot did: rejected, velocity fused in the wrong frame, far off
            assert max(errors) > 2.0, errors
            assert counters["pos_rejected"] > 100
    finally:
        ls.close()
