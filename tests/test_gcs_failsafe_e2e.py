"""ArduPilot's GCS failsafe through the bridge, end to end (issue 29): the emulator is the truth.

ArduPilot counts every RC_CHANNELS_OVERRIDE from MAV_GCS_SYSID as its ground station alive (GCS_Common.cpp
handle_rc_channels_override -> sysid_mygcs_seen; the emulator does the same, sitl/incoming.py), so a bridge that
overrides without a pause would keep the failsafe from ever firing. Here the ground station (pymavlink, system
255) goes silent, no heartbeat at all, and the emulator's own GCS failsafe must fire and act through the bridge
(rover_bridge.command.gcs_failsafe), or, with FS_GCS_ENABLE 2 in AUTO, the mission must go on.
"""

from __future__ import annotations

import pytest
from navrig import WAYPOINTS, BridgeRig

from rover_bridge.command.drivers import CommandState
from sitl.modes import MODE_AUTO, MODE_GUIDED, MODE_HOLD, MODE_MANUAL, MODE_RTL

pytestmark = pytest.mark.e2e

TIMEOUT_S, FS_TIMEOUT_S = 5.0, 1.5  # FS_GCS_TIMEOUT, FS_TIMEOUT: Rover's defaults


def emulator_texts(rig: BridgeRig) -> list[str]:
    return rig.emu.statustexts_sent


@pytest.mark.parametrize(("start_mode", "action", "expect"), [(MODE_MANUAL, 1, MODE_RTL),
                                                              (MODE_GUIDED, 2, MODE_HOLD)])
def test_a_silent_gcs_lets_the_autopilots_gcs_failsafe_act(start_mode: int, action: int, expect: int) -> None:
    rig = BridgeRig(FS_GCS_ENABLE=1, FS_ACTION=action)
    try:
        rig.set_mode(MODE_MANUAL)
        assert rig.run_until(lambda: rig.from_home_m() >= 6.0, 20.0, rig.drive(1.5))  # out, so RTL has a way home
        assert rig.run_until(rig.stopped, 5.0, rig.drive(0.0))
        rig.set_mode(start_mode)
        assert "RB: GCS failsafe 1 (5 s): overrides pause for it" in rig.texts()
        rig.run(1.0)
        rig.gcs_alive = False
        quiet_from = rig.ls.t_s
        assert rig.run_until(lambda: rig.emu.mode == expect, 3 * TIMEOUT_S)
        fired_after_s = rig.ls.t_s - quiet_from
        assert "GCS Failsafe" in emulator_texts(rig)
        assert "RB: GCS silent, overrides released for failsafe" in rig.texts()
        # Bridge silent at TIMEOUT_S, the emulator's clock restarts at its last override: TIMEOUT_S +
        # TIMEOUT_S + FS_TIMEOUT_S after the last heartbeat (sent up to 1 s before quiet_from), checked at 10 Hz.
        assert 2 * TIMEOUT_S + FS_TIMEOUT_S - 1.0 <= fired_after_s <= 2 * TIMEOUT_S + FS_TIMEOUT_S + 0.3
        if expect == MODE_RTL:
            # The mode table rules again: RTL drives home through the bridge while the GCS is still silent.
            assert rig.run_until(lambda: "Reached destination" in rig.texts(), 40.0)
            assert rig.run_until(rig.stopped, 10.0)
            assert rig.from_home_m() <= 1.0
        else:
            rig.run(2.0)
            assert rig.stopped() and rig.ls.core.command.state is CommandState.HOLD
        assert rig.ls.core.command.counters["gcs_failsafe.silent"] == 1
    finally:
        rig.close()
    print(f"\nGCS silent in mode {start_mode}: the emulator's failsafe fired {fired_after_s:.1f} s later")


def test_the_gcs_back_before_the_failsafe_hands_the_wheels_back() -> None:
    rig = BridgeRig(FS_GCS_ENABLE=1, FS_ACTION=2)
    try:
        rig.set_mode(MODE_MANUAL)
        rig.gcs_alive = False
        assert rig.run_until(lambda: rig.ls.core.command.state is CommandState.GCS_SILENT, TIMEOUT_S + 1.5)
        sent = rig.ls.core.command.counters.get("outputs.sent", 0)
        rig.run(2.0)
        assert rig.ls.core.command.counters.get("outputs.sent", 0) == sent  # silent: no override at all
        rig.gcs_alive = True
        rig.run(3.0, rig.drive(1.0))  # the GCS speaks (heartbeat) and drives again
        assert rig.emu.mode == MODE_MANUAL and "GCS Failsafe" not in emulator_texts(rig)
        assert rig.emu.truth.v_m_s > 0.5
    finally:
        rig.close()


def test_with_fs_gcs_enable_2_the_mission_goes_on_without_the_gcs() -> None:
    rig = BridgeRig(FS_GCS_ENABLE=2, FS_ACTION=2)
    try:
        assert rig.upload(WAYPOINTS) == 0
        rig.set_mode(MODE_AUTO)
        rig.run(1.0)
        rig.gcs_alive = False
        assert rig.run_until(lambda: len(rig.reached()) >= len(WAYPOINTS), 60.0)
        assert rig.emu.mode == MODE_AUTO and rig.reached() == [1, 2, 3]
        assert "gcs_failsafe.silent" not in rig.ls.core.command.counters  # the bridge drove on
    finally:
        rig.close()


def test_with_fs_gcs_enable_1_a_mission_without_the_gcs_takes_the_failsafe_action() -> None:
    rig = BridgeRig(FS_GCS_ENABLE=1, FS_ACTION=1)
    try:
        assert rig.upload(WAYPOINTS) == 0
        rig.set_mode(MODE_AUTO)
        rig.run(1.0)
        rig.gcs_alive = False
        assert rig.run_until(lambda: rig.emu.mode == MODE_RTL, 3 * TIMEOUT_S)
        assert "GCS Failsafe" in emulator_texts(rig) and len(rig.reached()) < len(WAYPOINTS)
        assert rig.run_until(lambda: "Reached destination" in rig.texts(), 40.0)
        assert rig.run_until(rig.stopped, 10.0) and rig.from_home_m() <= 1.0
    finally:
        rig.close()
