"""Asking the autopilot for the estimator's streams, and checking that they come (pure).

After the autopilot's first heartbeat, after a heartbeat gap (link back or reboot) and after a
detected reboot, WHEEL_DISTANCE and the gyro message are asked for at [estimator] stream_rate_hz
with MAV_CMD_SET_MESSAGE_INTERVAL, one request outstanding at a time so that each COMMAND_ACK is
unambiguous. On DENIED / UNSUPPORTED / FAILED, or no ACK after STREAM_ACK_ATTEMPTS tries, the
message's group is asked for with REQUEST_DATA_STREAM instead (EXTRA1 for WHEEL_DISTANCE and
ATTITUDE, RAW_SENSORS for the IMU messages; ArduPilot 4.7 refuses the interval for
WHEEL_DISTANCE). Arrival rates are measured over RATE_WINDOW_S; a stream below SLOW_FRACTION of the
requested rate is asked for again and reported (STATUSTEXT, at most every SLOW_REPORT_INTERVAL_S).

A stream marked `if_missing` (the autopilot's position, which navigation wants at a couple of Hz) is
watched first and asked for only when it does not already arrive at its rate: a ground station that
asked for it faster (a map at 10 Hz) must not be slowed down by the bridge's request, since
SET_MESSAGE_INTERVAL is per link, not per client, and the last request wins.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import NOTHING, Link, Outgoing, Reaction

STREAM_ACK_TIMEOUT_S = 1.0
STREAM_ACK_ATTEMPTS = 3
STREAM_RESTART_HOLDOFF_S = 2.0  # several reboot signs close together restart the requests once
HEARTBEAT_GAP_S = 3.0
RATE_WINDOW_S = 5.0
RATE_GRACE_S = 2.0  # let a freshly requested stream speed up before measuring it
SLOW_FRACTION = 0.7
SLOW_REPORT_INTERVAL_S = 30.0

ACK_FAILURES = {mavlink.MAV_RESULT_DENIED, mavlink.MAV_RESULT_UNSUPPORTED, mavlink.MAV_RESULT_FAILED}


@dataclass
class Stream:
    """One requested message: where its request stands and how fast it arrives."""

    name: str
    msg_id: int
    group: int
    state: str = "idle"  # idle | queued | awaiting_ack | requested
    attempts: int = 0
    sent_s: float = 0.0
    window_start_s: float | None = None
    arrivals: int = 0
    last_slow_report_s: float = -math.inf
    measured_hz: float | None = None
    rate_hz: float | None = None  # None: the requests' common rate ([estimator] stream_rate_hz)
    check_rate: bool = True  # False for a stream the autopilot may rightly not send (no position yet)
    if_missing: bool = False  # watched first, asked for only if it does not come (module doc)
    wanted: bool = True  # False: not asked for until `want` (a stream needed only from some moment on)


class StreamRequests:
    """The requests for the estimator's streams and their fallbacks (see the module docstring)."""

    def __init__(self, streams: list[Stream], rate_hz: float, identity: Identity, reporter: Reporter) -> None:
        self.streams = streams
        self.rate_hz = rate_hz
        self.identity = identity
        self.reporter = reporter
        self.counters = {"stream_requests": 0, "stream_fallbacks": 0, "stream_slow": 0, "stream_restarts": 0}
        self._last_hb_s: float | None = None
        self._last_restart_s = -math.inf

    def add(self, stream: Stream) -> None:
        """One more message to ask for, with the same fallbacks (the composition's, for the command flow)."""
        self.streams.append(stream)

    def want(self, name: str, now_s: float) -> list[Outgoing]:
        """Start asking for a stream added unwanted; from then on it is asked for again after every restart."""
        for s in self.streams:
            if s.name == name and not s.wanted:
                s.wanted = True
                if self._last_hb_s is not None:
                    s.state, s.attempts, s.window_start_s, s.arrivals = "queued", 0, None, 0
                    return self.pump(now_s)
        return []

    # ------------------------------------------------------------------ events
    def on_heartbeat(self, now_s: float) -> list[Outgoing]:
        """The autopilot's heartbeat: the first one, or one after a gap, (re)starts the requests."""
        gap = self._last_hb_s is None or now_s - self._last_hb_s > HEARTBEAT_GAP_S
        self._last_hb_s = now_s
        if gap:
            self.restart(now_s)
            return self.pump(now_s)
        return []

    def restart(self, now_s: float) -> None:
        """Ask for every stream again (a reboot, a heartbeat gap); signs close together count once."""
        if now_s - self._last_restart_s < STREAM_RESTART_HOLDOFF_S:
            return
        self._last_restart_s = now_s
        self.counters["stream_restarts"] += 1
        for s in self.streams:
            if not s.wanted:
                continue
            s.state, s.attempts, s.window_start_s, s.arrivals = "queued", 0, None, 0
            if s.if_missing:
                s.state, s.window_start_s = "watching", now_s

    def arrival(self, name: str, now_s: float) -> None:
        """One message of stream `name` arrived (counted once its rate window is open)."""
        for s in self.streams:
            if s.name == name and s.window_start_s is not None and now_s > s.window_start_s:
                s.arrivals += 1

    def handle_ack(self, msg: MAVLinkMessage, now_s: float) -> Reaction:
        """A COMMAND_ACK from the autopilot: ours (SET_MESSAGE_INTERVAL to our component) is consumed."""
        if msg.command != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return NOTHING
        if getattr(msg, "target_component", 0) not in (0, self.identity.component_id):
            return NOTHING  # someone else's request
        pending = next((s for s in self.streams if s.state == "awaiting_ack"), None)
        if pending is None:
            return NOTHING
        out: list[Outgoing] = []
        if msg.result == mavlink.MAV_RESULT_ACCEPTED:
            pending.state = "requested"
            pending.window_start_s, pending.arrivals = now_s + RATE_GRACE_S, 0
        elif msg.result in ACK_FAILURES:
            out += self._fallback(pending, now_s)
        else:  # TEMPORARILY_REJECTED, IN_PROGRESS: ask again after the timeout
            return Reaction(consumed=True)
        out += self.pump(now_s)
        return Reaction(consumed=True, out=tuple(out))

    # ------------------------------------------------------------------ time
    def pump(self, now_s: float) -> list[Outgoing]:
        """Send the next SET_MESSAGE_INTERVAL (one outstanding at a time); handle ACK timeouts."""
        out: list[Outgoing] = []
        for s in self.streams:
            if s.state == "awaiting_ack":
                if now_s < s.sent_s + STREAM_ACK_TIMEOUT_S:  # the form next_deadline_s uses (float rounding)
                    return out
                if s.attempts >= STREAM_ACK_ATTEMPTS:
                    out += self._fallback(s, now_s)
                    continue
                out.append(self._interval_request(s, now_s))
                return out
        for s in self.streams:
            if s.state == "queued":
                out.append(self._interval_request(s, now_s))
                return out
        return out

    def check_rates(self, now_s: float) -> list[Outgoing]:
        """Close every full rate window; ask again for (and report) a stream that arrives too slowly."""
        out: list[Outgoing] = []
        for s in self.streams:
            if s.window_start_s is None or now_s < s.window_start_s + RATE_WINDOW_S:
                continue
            wanted = s.rate_hz or self.rate_hz
            hz = s.arrivals / (now_s - s.window_start_s)
            s.measured_hz = hz
            s.window_start_s, s.arrivals = now_s, 0
            if s.state == "watching":
                if hz < SLOW_FRACTION * wanted:  # not coming (fast enough): now ask for it
                    s.state, s.window_start_s = "queued", None
                    out += self.pump(now_s)
                continue
            if hz >= SLOW_FRACTION * wanted or not s.check_rate:
                continue
            self.counters["stream_slow"] += 1
            out.append(self._data_stream_request(s.group, s.rate_hz))  # ask again: a GCS may have lowered it
            if now_s - s.last_slow_report_s >= SLOW_REPORT_INTERVAL_S:
                s.last_slow_report_s = now_s
                out += self.reporter.statustext(
                    mavlink.MAV_SEVERITY_WARNING,
                    f"{s.name} {hz:.1f} Hz, need {SLOW_FRACTION * wanted:.0f}",
                    now_s,
                    key=f"slow {s.name}",
                )
        return out

    def next_deadline_s(self, now_s: float) -> float:
        """When pump or check_rates next has something to do (mirrors them exactly; inf: nothing), in one
        pass: it runs on every turn of the loop."""
        # One request outstanding at a time, so a queued stream waits for the pending ACK's timeout,
        # not "now" (which would spin the loop until the ACK came).
        pending = math.inf
        queued = False
        first = math.inf
        for s in self.streams:
            state = s.state
            if state == "awaiting_ack":
                if pending == math.inf:
                    pending = s.sent_s + STREAM_ACK_TIMEOUT_S
            elif state == "queued":
                queued = True
            start = s.window_start_s
            if start is not None and (s.check_rate or state == "watching") and start + RATE_WINDOW_S < first:
                first = start + RATE_WINDOW_S
        if pending != math.inf:
            return min(pending, first)
        return min(now_s, first) if queued else first

    # ------------------------------------------------------------------ messages
    def _target(self) -> tuple[int, int]:
        return self.identity.vehicle_system_id or 1, self.identity.autopilot_component_id

    def _to_autopilot(self, msg: MAVLinkMessage) -> Outgoing:
        return Outgoing(Link.AUTOPILOT, msg, self.identity.own_system_id, self.identity.component_id)

    def _interval_request(self, s: Stream, now_s: float) -> Outgoing:
        s.state, s.sent_s = "awaiting_ack", now_s
        s.attempts += 1
        self.counters["stream_requests"] += 1
        sysid, compid = self._target()
        msg = mavlink.MAVLink_command_long_message(
            target_system=sysid, target_component=compid, command=mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
            confirmation=s.attempts - 1, param1=float(s.msg_id), param2=float(1e6 / (s.rate_hz or self.rate_hz)),
            param3=0.0, param4=0.0, param5=0.0, param6=0.0, param7=0.0)
        return self._to_autopilot(msg)

    def _fallback(self, s: Stream, now_s: float) -> list[Outgoing]:
        s.state = "requested"
        s.window_start_s, s.arrivals = now_s + RATE_GRACE_S, 0
        self.counters["stream_fallbacks"] += 1
        return [self._data_stream_request(s.group, s.rate_hz)]

    def _data_stream_request(self, group: int, rate_hz: float | None = None) -> Outgoing:
        sysid, compid = self._target()
        msg = mavlink.MAVLink_request_data_stream_message(
            target_system=sysid, target_component=compid, req_stream_id=group,
            req_message_rate=max(1, round(rate_hz or self.rate_hz)), start_stop=1)
        return self._to_autopilot(msg)
