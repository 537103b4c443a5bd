"""The stop at exit, and its proof (pure): neutral, release, then a TIMESYNC probe the autopilot answers.

Sent is not done: over a stream link (TCP: SITL's SERIAL0, mavlink-router) ArduPilot parses its input on its
main loop, and bytes a client sends just before it closes are never parsed as its own, so a stop that is not
confirmed may not have happened (rc_override: 3 s more driving; servo: no end). The autopilot answers the
probe while parsing (GCS_Common.cpp handle_timesync, ts1 echoed), after the stop, so its answer proves the
stop; until then (at most safety.stop_confirm_timeout_s) the stop is resent every STOP_RESEND_S and the shell
keeps the link open. Nothing but the stop is sent afterwards.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from rover_bridge.command.outputs import OutputMap, WheelPwm
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.wire import Incoming, Link, Outgoing

log = logging.getLogger("rover_bridge.command")

# ts1 carries this tag plus the attempt number, so the answer is recognisably ours.
STOP_PROBE_TAG = 0x5242_5354 << 32  # "RBST"
STOP_RESEND_S = 0.1
EMERGENCY_PROBE_TS1 = STOP_PROBE_TAG + 0xFFFF_FFFF  # the stop guard's probe (never a normal attempt number)


class StopConfirmation:
    """The stop messages, their resends and the probe's answer (module doc)."""

    def __init__(self, outputs: OutputMap, identity: Identity, timeout_s: float,
                 count: Callable[[str], None]) -> None:
        self.outputs = outputs
        self.identity = identity
        self.timeout_s = timeout_s
        self._count = count
        self.began_s = 0.0
        self.sent_s = 0.0
        self.attempts = 0
        self.confirmed: bool | None = None  # None until answered or timed out (or nothing to stop)

    def begin(self, now_s: float) -> list[Outgoing]:
        self.began_s = now_s
        return self.messages(now_s)

    def messages(self, now_s: float) -> list[Outgoing]:
        """Neutral, release (rc_override), the probe with the next attempt number."""
        self.attempts += 1
        msgs = self._neutral_and_release()
        msgs.append(mavlink.MAVLink_timesync_message(tc1=0, ts1=STOP_PROBE_TAG + self.attempts))
        self.sent_s = now_s
        self._count("stop.sent")
        return [self.to_autopilot(m) for m in msgs]

    def emergency(self) -> list[Outgoing]:
        """As another thread sends it when the loop is stuck: the probe is EMERGENCY_PROBE_TS1."""
        msgs = self._neutral_and_release()
        msgs.append(mavlink.MAVLink_timesync_message(tc1=0, ts1=EMERGENCY_PROBE_TS1))
        return [self.to_autopilot(m) for m in msgs]

    def _neutral_and_release(self) -> list[MAVLinkMessage]:
        vehicle = self.identity.vehicle_system_id
        assert vehicle is not None
        target = (vehicle, self.identity.autopilot_component_id)
        msgs = self.outputs.command(self.outputs.neutral, *target)
        if self.outputs.mode == "rc_override":
            msgs += self.outputs.release(*target)
        return msgs

    @property
    def neutral(self) -> WheelPwm:
        return self.outputs.neutral

    def timed_out(self, now_s: float) -> bool:
        if now_s < self.began_s + self.timeout_s:
            return False
        self.confirmed = False
        self._count("stop.unconfirmed")
        log.error("the autopilot did not confirm the stop within %.2f s: it may still drive the wheels "
                  "(rc_override: until RC_OVERRIDE_TIME; servo: until something else moves them)", self.timeout_s)
        return True

    def resend_due(self, now_s: float) -> bool:
        return now_s >= self.sent_s + STOP_RESEND_S

    def deadline_s(self) -> float:
        return min(self.sent_s + STOP_RESEND_S, self.began_s + self.timeout_s)

    def answered(self, inc: Incoming, now_s: float) -> bool:
        """A TIMESYNC reply (tc1 != 0) from the autopilot echoing one of our probes: the stop is proven."""
        msg = inc.msg
        if inc.link is not Link.AUTOPILOT or msg.get_type() != "TIMESYNC":
            return False
        try:
            ours = int(msg.tc1) != 0 and 0 < int(msg.ts1) - STOP_PROBE_TAG <= self.attempts
        except (TypeError, ValueError):
            return False
        if not ours:
            return False
        self.confirmed = True
        self._count("stop.confirmed")
        log.info("stop confirmed by the autopilot after %.0f ms", 1000.0 * (now_s - self.began_s))
        return True

    def to_autopilot(self, msg: MAVLinkMessage) -> Outgoing:
        # ArduPilot obeys overrides only from its GCS id (MAV_GCS_SYSID): see output.override_source_system.
        return Outgoing(Link.AUTOPILOT, msg, self.identity.override_source_system, self.identity.component_id)
