"""Let ArduPilot's GCS failsafe see a silent ground station (pure).

ArduPilot counts every RC_CHANNELS_OVERRIDE from its GCS id (MAV_GCS_SYSID) as the ground station being alive,
as it counts that id's HEARTBEAT and MANUAL_CONTROL (GCS_Common.cpp: handle_rc_channels_override,
handle_heartbeat and handle_manual_control all call sysid_mygcs_seen; Rover.cpp gcs_failsafe_check fails safe
FS_GCS_TIMEOUT s after the last of them). The bridge's overrides, 20-40 a second as that id, would keep the
failsafe from ever firing. So the bridge watches the GCS itself, as ArduPilot would without it:

- it reads FS_GCS_ENABLE, FS_GCS_TIMEOUT and FS_OPTIONS (PARAM_REQUEST_READ at the first heartbeat and when the
  heartbeat comes back after a gap or a reboot; a PARAM_VALUE for them at any time, e.g. after a GCS's
  PARAM_SET, is taken too, and one that changes a value, or comes unasked, is asked for again: a single frame
  (a corrupted or forged one: FS_GCS_TIMEOUT 0 would pause the overrides for good) lasts only until the
  autopilot's answer replaces it, and a value the autopilot does not confirm in a few requests is
  dropped);
- the GCS is seen by a HEARTBEAT or MANUAL_CONTROL from the override's system id;
- with FS_GCS_ENABLE set, once the GCS has been seen and then silent for FS_GCS_TIMEOUT, in a mode where ArduPilot
  would fail safe (Rover/failsafe.cpp failsafe_trigger: not RTL, not HOLD unless FS_OPTIONS bit 0; with
  FS_GCS_ENABLE 2 AUTO continues, so the bridge keeps driving there), the bridge sends neutral and release once
  and then nothing from that id;
- that silence ends when the GCS is seen again, when the autopilot changes mode (the failsafe's action, or a
  pilot), or when ArduPilot says "GCS Failsafe" or "Radio Failsafe" (its GCS failsafe's words, see
  AUTOPILOT_FAILSAFE_TEXTS; with FS_ACTION 0 there is no mode change): the mode table rules
  again, and the next silence needs the GCS seen once more (else the bridge would stop RTL, which ArduPilot
  goes on with while the GCS is still silent). It also ends when the parameters, as now known, no longer call
  for it (the autopilot's answer replaced a value it never had): then the GCS is watched again as before.

ArduPilot's own clock then starts at the bridge's last override: the failsafe fires about FS_GCS_TIMEOUT +
FS_GCS_TIMEOUT + FS_TIMEOUT s after the GCS's last message, not FS_GCS_TIMEOUT + FS_TIMEOUT. Servo output mode
(DO_SET_SERVO) sends no overrides: nothing to do there.
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

from rover_bridge.command.param_reader import ParamReader
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Link, Outgoing

log = logging.getLogger("rover_bridge.command")

# ArduPilot Rover's custom modes the failsafe treats apart (Rover/mode.h): FS_GCS_ENABLE is ArduPilot's only.
ROVER_HOLD, ROVER_AUTO, ROVER_RTL = 4, 10, 11
FS_OPTION_ACTIVE_IN_HOLD = 1
CONTINUE_MISSION = 2  # FS_GCS_ENABLE 2: "Enabled Continue with Mission in Auto"
# Rover/failsafe.cpp says "%s Failsafe" with the name of whichever check ran the trigger: the GCS bit is often
# set by gcs_failsafe_check (10 Hz) and acted on in radio_failsafe_check (50 Hz), which says "Radio" (measured on
# the real SITL: the GCS failsafe said "Radio Failsafe"). Either means the autopilot acted and cleared overrides.
AUTOPILOT_FAILSAFE_TEXTS = frozenset({"GCS Failsafe", "Radio Failsafe"})
PARAM_NAMES = ("FS_GCS_ENABLE", "FS_GCS_TIMEOUT", "FS_OPTIONS")


@dataclass(frozen=True)
class FailsafeParams:
    """ArduPilot's GCS failsafe settings, as read from the autopilot."""

    enable: int = 0  # FS_GCS_ENABLE: 0 off, 1 on, 2 on but AUTO continues
    timeout_s: float = 5.0  # FS_GCS_TIMEOUT
    options: int = 0  # FS_OPTIONS (bit 0: active in HOLD)

    def fails_safe_in(self, mode: int) -> bool:
        """Whether ArduPilot's GCS failsafe would act in `mode` (Rover failsafe_trigger's conditions)."""
        if self.enable == 0 or mode == ROVER_RTL:
            return False
        if mode == ROVER_HOLD and not self.options & FS_OPTION_ACTIVE_IN_HOLD:
            return False
        return not (mode == ROVER_AUTO and self.enable == CONTINUE_MISSION)

    @classmethod
    def from_values(cls, values: dict[str, float]) -> FailsafeParams | None:
        """From the values a ParamReader holds; None until FS_GCS_ENABLE is known (nothing to watch before)."""
        if "FS_GCS_ENABLE" not in values:
            return None
        return cls(int(values["FS_GCS_ENABLE"]), values.get("FS_GCS_TIMEOUT", 5.0), int(values.get("FS_OPTIONS", 0)))


class Phase(enum.Enum):
    UNSEEN = "unseen"  # no GCS yet: ArduPilot does not fail safe for a GCS it never saw
    WATCHING = "watching"  # seen: silent for FS_GCS_TIMEOUT is a failsafe
    SILENT = "silent"  # the bridge sends nothing, so ArduPilot can see the silence
    SPENT = "spent"  # the autopilot acted (or a mode changed): drive as the mode table says until seen again


class GcsSilence:
    """When the bridge must stop overriding so that ArduPilot's GCS failsafe can act (module doc)."""

    def __init__(self) -> None:
        self.phase = Phase.UNSEEN
        self.last_seen_s: float | None = None
        # When WATCHING may turn SILENT at the earliest; -inf while SILENT: one cheap check on every output.
        self.due_s = math.inf
        self._silent_mode: int | None = None

    def seen(self, now_s: float, params: FailsafeParams | None) -> bool:
        """The GCS spoke (HEARTBEAT or MANUAL_CONTROL from the override's id): True if this ends a silence."""
        ended = self.phase is Phase.SILENT
        self.phase, self.last_seen_s = Phase.WATCHING, now_s
        self.rearm(params)
        return ended

    def rearm(self, params: FailsafeParams | None) -> None:
        """Params read or changed: when WATCHING may turn SILENT."""
        last = self.last_seen_s
        if self.phase is Phase.WATCHING and params is not None and params.enable != 0 and last is not None:
            self.due_s = last + params.timeout_s
        elif self.phase is not Phase.SILENT:
            self.due_s = math.inf

    def silent(self, now_s: float, mode: int | None, params: FailsafeParams | None) -> bool:
        """Whether the bridge must be silent now (WATCHING turns SILENT here when due)."""
        if self.phase is Phase.SILENT:
            last = self.last_seen_s
            if (params is not None and self._silent_mode is not None and params.fails_safe_in(self._silent_mode)
                    and last is not None and now_s >= last + params.timeout_s):
                return True
            # The parameters it rested on were replaced (the autopilot's answer to a forged or corrupted
            # PARAM_VALUE): watching again, as if never silent.
            self.phase = Phase.WATCHING
            self.rearm(params)
        if now_s < self.due_s or params is None or mode is None or not params.fails_safe_in(mode):
            return False
        # due_s -inf: the gate's one comparison keeps asking while silent
        self.phase, self._silent_mode, self.due_s = Phase.SILENT, mode, -math.inf
        return True

    def on_mode(self, mode: int | None) -> bool:
        """The autopilot's mode (each heartbeat): True if a change ends a silence."""
        if self.phase is Phase.SILENT and mode != self._silent_mode:
            self.phase, self.due_s = Phase.SPENT, math.inf
            return True
        return False

    def autopilot_acted(self) -> bool:
        """ArduPilot said it failed safe: True if this ends a silence."""
        ended = self.phase is Phase.SILENT
        if self.phase is not Phase.UNSEEN:
            self.phase, self.due_s = Phase.SPENT, math.inf
        return ended


class GcsFailsafeWatch:
    """The wiring: which messages feed the reader and the silence, and what the bridge sends for them."""

    def __init__(self, identity: Identity, reporter: Reporter, overrides: bool, count: Callable[[str], None]) -> None:
        self.identity = identity
        self.reporter = reporter
        self.active = overrides  # only overrides mask the failsafe (servo mode sends none)
        self._count = count
        self.reader = ParamReader(PARAM_NAMES)
        self.silence = GcsSilence()

    def autopilot_back(self, now_s: float) -> None:
        """The first heartbeat, or the first after a gap (a reboot resets what it was told): read again."""
        if self.active:
            self.reader.restart(now_s)

    def tick(self, now_s: float) -> list[Outgoing]:
        vehicle = self.identity.vehicle_system_id
        if not self.reader.due(now_s) or vehicle is None:
            return []
        msgs = self.reader.requests(now_s, vehicle, self.identity.autopilot_component_id)
        self.silence.rearm(FailsafeParams.from_values(self.reader.values))  # an unconfirmed value may have been dropped
        return [Outgoing(Link.AUTOPILOT, m, self.identity.own_system_id, self.identity.component_id) for m in msgs]

    def on_param_value(self, msg: MAVLinkMessage, now_s: float) -> list[Outgoing]:
        if not self.active or not self.identity.from_autopilot(msg) or not self.reader.on_param_value(msg, now_s):
            return []
        params = FailsafeParams.from_values(self.reader.values)
        self.silence.rearm(params)
        if params is None or self.reader.values.keys() != set(PARAM_NAMES):
            return []
        if not params.enable:
            log.info("ArduPilot's GCS failsafe is off (FS_GCS_ENABLE 0)")
            return []
        text = f"RB: GCS failsafe {params.enable} ({params.timeout_s:g} s): overrides pause for it"
        return self.reporter.statustext(mavlink.MAV_SEVERITY_INFO, text, now_s, key="gcs_failsafe.params")

    def on_statustext(self, msg: MAVLinkMessage) -> bool:
        """True if ArduPilot's "GCS Failsafe" (or "Radio Failsafe") ends a silence."""
        if not self.active or not self.identity.from_autopilot(msg):
            return False
        if str(msg.text).rstrip("\x00") not in AUTOPILOT_FAILSAFE_TEXTS:
            return False
        self._count("gcs_failsafe.autopilot")
        return self.silence.autopilot_acted()

    def on_gcs(self, msg: MAVLinkMessage, now_s: float) -> bool:
        """A HEARTBEAT or MANUAL_CONTROL from a ground station: True if it ends a silence."""
        if not self.active or msg.get_srcSystem() != self.identity.override_source_system:
            return False
        return self.silence.seen(now_s, FailsafeParams.from_values(self.reader.values))

    def silent(self, now_s: float, mode: int | None) -> bool:
        was = self.silence.phase
        now_silent = self.silence.silent(now_s, mode, FailsafeParams.from_values(self.reader.values))
        if now_silent and was is not Phase.SILENT:
            self._count("gcs_failsafe.silent")
        return now_silent

