"""The shell around the pure core: read links, call the core, forward and write, keep time.

`Runner.step(now_s)` is one non-blocking pass (drain every link, handle each frame, tick when
a deadline is due); `Runner.run()` repeats it against the wall clock, sleeping in select()
until a frame arrives or the next deadline. Tests drive `step` with a simulated clock, so
the same code runs in lockstep with the sitl emulator.

Routing: frames from the autopilot go to every ground station; frames from a ground station
go to the autopilot and the other ground stations, unless the core consumed them (velocity
requests meant for the bridge). Forwarded frames are written as received: source ids,
sequence numbers and signatures intact.
"""

from __future__ import annotations

import logging
import math
import os
import select
import struct
import time
from collections.abc import Callable, Sequence
from typing import BinaryIO

from rover_bridge.app.composition import BridgeCore
from rover_bridge.app.deadlines import Deadlines, output_of, schedules
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.links import Endpoint
from rover_bridge.mavlink.signing import carries_signature
from rover_bridge.mavlink.wire import Incoming, Link, Outgoing

log = logging.getLogger("rover_bridge.app.loop")

# What packing a message with an out-of-range field raises (pymavlink's struct packing).
PACK_ERRORS = (struct.error, OverflowError, ValueError, TypeError)

# Longest select() sleep: bounds how late a stop request or a missed deadline can be noticed.
MAX_SLEEP_S = 0.05
# Frames `run()` takes from one link per pass. Between passes it reads the clock again and serves
# due deadlines, so a flooding link delays the control output by at most this many frames (instead
# of its whole backlog) and cannot starve the other links.
RUN_BATCH = 16
# The most autopilot frames a batch may let pile up in the kernel's receive buffer (a few hundred
# small datagrams fit): at a rate that would pile up more, the link is not batched at all (it wakes
# the loop for every read, as without a batch), so a flood is never dropped for a batch; the busy
# loop then reads it in every pass anyway. The rate is smoothed over AP_RATE_TAU_S.
AP_BATCH_MAX_FRAMES = 64
AP_RATE_TAU_S = 0.1
# While waiting for the autopilot to confirm the stop: how long one wait may last, and how far past
# the core's own timeout the shell gives up if the core never settles (a bug must not hang the exit).
STOP_POLL_S = 0.01
STOP_WAIT_MARGIN_S = 0.2


class TlogWriter:
    """Standard .tlog: each frame preceded by its wall-clock time as big-endian uint64 microseconds."""

    def __init__(self, stream: BinaryIO, wall_clock: Callable[[], float] = time.time) -> None:
        self.stream = stream
        self.wall_clock = wall_clock
        self.frames = 0

    def write(self, frame: bytes) -> None:
        self.stream.write(struct.pack(">Q", int(self.wall_clock() * 1e6)) + frame)
        self.frames += 1

    def close(self) -> None:
        self.stream.flush()
        self.stream.close()


class Runner:
    def __init__(self, core: BridgeCore, autopilot: Endpoint, gcs: Sequence[Endpoint] = (),
                 tlog: TlogWriter | None = None) -> None:
        self.core = core
        self.autopilot = autopilot
        self.gcs = list(gcs)
        self.tlog = tlog
        self.forwarded = 0
        self.consumed = 0
        self.ticks = 0
        self.early_ticks = 0
        self.backlog = False
        self.next_deadline_s = 0.0
        self.passes = 0
        self.pack_errors = 0
        self._emergency_frames = b""
        self._emergency_key: tuple[int | None, int] | None = None
        # The autopilot's telemetry is read in batches (mavlink.autopilot_batch_ms): after a read its
        # link is not watched until the batch time has passed; every wake-up still reads it. Only where
        # the kernel stamps each datagram: the estimator runs on the autopilot's own stamps but maps its
        # clock by arrival times, and a frame's read time is its arrival time only when it is read at once.
        batch_ms = core.profile.mavlink.autopilot_batch_ms
        self._ap_batch_s = batch_ms * 1e-3 if autopilot.receive_stamped else 0.0
        if batch_ms > 0.0 and not autopilot.receive_stamped:
            log.info("%s: no kernel receive times on this link: read as frames arrive (autopilot_batch_ms "
                     "applies to udpin links)", autopilot.url)
        self._ap_read_s = -1e9
        self._ap_rate_hz = 0.0  # the autopilot link's recent frame rate (AP_RATE_TAU_S), as of _ap_rate_s
        self._ap_rate_s = 0.0
        self._stopped = False
        # Autopilot frames go to every GCS; a GCS's frames to the autopilot and the other GCSs.
        self._endpoints = [self.autopilot, *self.gcs]
        self._forward_to = {ep: [o for o in (self.gcs if ep.role is Link.AUTOPILOT else self.endpoints) if o is not ep]
                            for ep in self.endpoints}
        self._woken = False  # the last wait returned because of the wake-up fd (a signal): drain it
        # The autopilot's frames go to the core at their kernel receive times, where the link has them
        # (listening UDP): the estimator maps the autopilot's clock by the least arrival latency, and a
        # frame read late (a batch, a busy machine) must not count its wait as latency. Only `run`
        # turns it on: it owns the real clocks; tests stepping a simulated clock keep now_s.
        self.receive_times = False
        self._wall_clock: Callable[[], float] = time.time
        self._last_s = -math.inf  # the latest time the core was given: arrival times never go back past it
        # Deadlines and budgets of the periodic outputs (rover_bridge.app.deadlines): `run` writes the frames'
        # times by its clock; a test stepping a simulated clock has them sent at the pass's time.
        self.timing = Deadlines(core.profile, schedules(core.profile))
        self._sent_clock: Callable[[], float] | None = None
        self._pass_s = 0.0

    @property
    def endpoints(self) -> list[Endpoint]:
        return self._endpoints

    def step(self, now_s: float, max_frames: int | None = None, ready: Sequence[Endpoint] | None = None) -> None:
        """Drain every link (at most `max_frames` from each; only the `ready` ones if given), handle
        every frame, then tick if a deadline is due. Never blocks. `backlog` tells whether a link may
        have more frames waiting; `next_deadline_s` is the core's next deadline after this pass."""
        self.backlog = False
        self._pass_s = now_s
        self.timing.pass_began(now_s)
        for ep in self.endpoints if ready is None else ready:
            ep.decode_only(self.core.reads(ep.role))  # what the core reads may change (its gyro source)
            msgs = ep.read() if max_frames is None else ep.read(max_frames)
            if msgs and ep is self.autopilot:
                self._ap_read_s = now_s  # a silent link is not batched: it stays watched
                decay = math.exp(-max(0.0, now_s - self._ap_rate_s) / AP_RATE_TAU_S)
                self._ap_rate_hz = self._ap_rate_hz * decay + len(msgs) / AP_RATE_TAU_S
                self._ap_rate_s = now_s
            if max_frames is not None and len(msgs) >= max_frames:
                self.backlog = True  # more may be queued, possibly in the framer where select() cannot see it
            if self.receive_times and ep is self.autopilot and ep.rx_wall_s:
                wall_s, t = self._wall_clock(), self._last_s
                for msg, received in zip(msgs, ep.rx_wall_s, strict=True):
                    if type(msg) is not bytes:  # forwarded bytes need no time
                        t = arrival_time(now_s, wall_s, received, t)
                    self._on_message(ep, msg, t)
                continue
            for msg in msgs:
                self._on_message(ep, msg, now_s)
        self._last_s = now_s
        for ep in self.endpoints:
            ep.flush()  # this pass's forwarded frames, in as few writes as fit
        deadline = self.core.next_deadline_s(now_s)
        ticked = now_s >= deadline
        if ticked:
            self.ticks += 1
            self.send_all(self.core.tick(now_s))
        if now_s >= self.core.next_early_s(now_s):
            # Awake anyway: an output that may leave early goes now rather than waking the loop later.
            self.early_ticks += 1
            self.send_all(self.core.early_tick(now_s))
            ticked = True
        self.next_deadline_s = self.core.next_deadline_s(now_s) if ticked else deadline
        self._report_timing(now_s)

    def _report_timing(self, now_s: float) -> None:
        """Late outputs to the ground station when they start and stop; the periodic log line."""
        for severity, key, text in self.timing.poll(now_s):
            self.send_all(self.core.reporter.statustext(severity, text, now_s, key=key))
        line = self.timing.log_line(now_s)
        if line is not None:
            log.log(logging.WARNING if line[0] else logging.INFO, "%s", line[1])

    def _on_message(self, ep: Endpoint, msg: MAVLinkMessage | bytes, now_s: float) -> None:
        if type(msg) is bytes:  # no core reads it: log and forward the bytes
            frame = msg
            if self.tlog is not None:
                self.tlog.write(frame)
            for other in self._forward_to[ep]:
                other.queue_frame(frame)
            self.forwarded += len(self._forward_to[ep])
            return
        assert not isinstance(msg, bytes)  # for mypy: type() narrows nothing
        frame = bytes(msg.get_msgbuf())  # one copy, shared by the log and every forward
        if self.tlog is not None:
            self.tlog.write(frame)
        reaction = self.core.handle(Incoming(ep.role, msg, signed_ok=_signed_ok(ep, msg)), now_s)
        if reaction.consumed:
            self.consumed += 1
        else:
            for other in self._forward_to[ep]:
                other.queue_frame(frame)
            self.forwarded += len(self._forward_to[ep])
        if reaction.out:
            self.send_all(reaction.out)

    def send_all(self, out: Sequence[Outgoing]) -> None:
        """Send the core's messages. The periodic outputs among them are accounted (rover_bridge.app.deadlines)
        until the stop begins, each once however many frames it takes, at its first frame."""
        accounted: tuple[str, ...] = ()
        for item in out:
            dests = [self.autopilot] if item.dest is Link.AUTOPILOT else self.gcs
            name = None if self._stopped else output_of(item.msg)
            for ep in dests:
                # The time read just before the write: on loopback a write wakes the reader, which may take the
                # CPU before the write returns (a busy machine: for milliseconds), so a time read after it could
                # count a frame late that left on time. A test stepping a simulated clock: the pass's time.
                clock = self._sent_clock
                written_s = self._pass_s if name is None or clock is None else clock()
                try:
                    frame = ep.send(item.msg, item.src_system, item.src_component)
                except PACK_ERRORS as exc:
                    # The core clamps what it packs from outside values; this is the net under that: one
                    # message lost and counted, never an exception out of the loop.
                    self.pack_errors += 1
                    log.error("could not pack %s: %s", item.msg.get_type(), exc)
                    break
                if name is not None and name not in accounted:
                    self.timing.sent(name, written_s)
                    accounted += (name,)
                name = None
                if self.tlog is not None and ep is dests[0]:
                    self.tlog.write(frame)

    def wait(self, clock: Callable[[], float], extra_fds: Sequence[int] = ()) -> list[Endpoint]:
        """Sleep until a link is readable, an extra fd (signal wake-up) is, or the next deadline.
        Returns the links worth reading now: the readable ones, and the autopilot's on every wake-up
        (unless it is neither readable nor batched); every link if it did not sleep."""
        now = clock()
        timeout = min(MAX_SLEEP_S, self.next_deadline_s - now)
        batch = self._ap_batch_s
        if self._ap_rate_hz * batch > AP_BATCH_MAX_FRAMES:
            batch = 0.0
        resting = now < self._ap_read_s + batch
        if resting:
            timeout = min(timeout, self._ap_read_s + batch - now)
        if timeout <= 0.0:
            return self.endpoints
        links = [(ep, ep.fileno()) for ep in self.endpoints]  # a reconnected TCP link has a new fd
        fds = [fd for ep, fd in links if fd is not None and not (resting and ep is self.autopilot)]
        readable, _, _ = select.select(fds + list(extra_fds) if extra_fds else fds, [], [], timeout)
        self._woken = bool(extra_fds) and any(fd in readable for fd in extra_fds)
        if not readable:
            # A deadline is due (a periodic output): read every link first, so that a request that arrived
            # while the select returned is answered before the output goes, not after it.
            return self.endpoints
        # The resting autopilot link is read on every wake-up (its batch); a link without a file
        # descriptor cannot be waited on, so it is read on every pass.
        return [ep for ep, fd in links if fd is None or fd in readable or (resting and ep is self.autopilot)]

    def run(self, should_stop: Callable[[], bool], clock: Callable[[], float] = time.monotonic,
            wake_fd: int | None = None, on_pass: Callable[[float], None] | None = None) -> None:
        """Serve until `should_stop()`; the caller then calls `stop_safely` (also on exceptions).
        `on_pass(now)` runs after every pass (the watchdog pings and the stop guard's liveness)."""
        extra = [wake_fd] if wake_fd is not None else []
        ready: list[Endpoint] | None = None
        self.receive_times = clock is time.monotonic
        self._sent_clock = clock
        while not should_stop():
            self.passes += 1
            now = clock()
            self.step(now, RUN_BATCH, ready)
            self._refresh_emergency_frames()
            if on_pass is not None:
                on_pass(now)
            ready = None if self.backlog else self.wait(clock, extra)
            if wake_fd is not None and self._woken:
                _drain(wake_fd)

    @property
    def emergency_frames(self) -> bytes:
        """The stop, packed for the autopilot link (rover_bridge.app.guard sends it if the loop is stuck)."""
        return self._emergency_frames

    def _refresh_emergency_frames(self) -> None:
        ident = self.core.identity
        key = (ident.vehicle_system_id, ident.autopilot_component_id)
        if key == self._emergency_key:
            return
        self._emergency_key = key
        frames = []
        for item in self.core.command.emergency_stop():
            mav = mavlink.MAVLink(None, srcSystem=item.src_system, srcComponent=item.src_component)
            frames.append(bytes(item.msg.pack(mav)))
        self._emergency_frames = b"".join(frames)

    def begin_stop(self, now_s: float) -> None:
        """Send the core's safe-stop sequence (neutral, release, the probe that confirms them). The
        links stay open: `step` goes on handling the autopilot's answer. Safe to call twice."""
        if self._stopped:
            return
        self._stopped = True
        self.send_all(self.core.shutdown(now_s))

    def stop_safely(self, clock: Callable[[], float] = time.monotonic) -> bool | None:
        """Stop the rover and wait, bounded, for the autopilot's proof; returns core.stop_confirmed.

        Over a stream link (TCP) bytes sent just before the link closes may never be parsed by the
        autopilot, so the link stays open until the core has its answer (or its timeout,
        safety.stop_confirm_timeout_s). Only the autopilot link is read meanwhile (telemetry is still
        forwarded); an error while waiting is logged and the wait goes on: the stop is already out.
        """
        try:
            self.begin_stop(clock())
            start = clock()
            # The core times the wait; this bound only guards against a core that never settles.
            give_up = start + self.core.profile.safety.stop_confirm_timeout_s + STOP_WAIT_MARGIN_S
            ready: list[Endpoint] | None = [self.autopilot]
            errors = 0
            while not self.core.stop_settled and (now := clock()) < give_up:
                try:
                    self.step(now, RUN_BATCH, ready)
                except Exception:  # the stop is out; keep listening for its proof
                    errors += 1
                    if errors == 1:
                        log.exception("error while waiting for the stop to be confirmed")
                ready = self._wait_autopilot(clock)
            return self.core.stop_confirmed
        finally:
            if self.tlog is not None:
                self.tlog.close()
                self.tlog = None  # frames after the stop are not recorded

    def _wait_autopilot(self, clock: Callable[[], float]) -> list[Endpoint]:
        timeout = max(0.0, min(STOP_POLL_S, self.next_deadline_s - clock()))
        fd = self.autopilot.fileno()
        if fd is not None and timeout > 0.0:
            select.select([fd], [], [], timeout)
        return [self.autopilot]

    def close(self) -> None:
        for ep in self.endpoints:
            ep.close()
        if self.tlog is not None:  # a runner stopped without stop_safely (tests step it themselves)
            self.tlog.close()
            self.tlog = None


def arrival_time(now_s: float, wall_s: float, received_wall_s: float, floor_s: float) -> float:
    """When a frame arrived on the caller's time line (now_s is wall_s there): now_s less the frame's age
    by the realtime clock, kept within [floor_s, now_s]. floor_s is the time given to the core last, so a
    realtime step (NTP), a missing stamp (0.0) or a stamp from before the last pass cannot move it back."""
    t = now_s - (wall_s - received_wall_s) if received_wall_s > 0.0 else now_s
    return now_s if t > now_s else (floor_s if t < floor_s else t)


def _signed_ok(ep: Endpoint, msg: MAVLinkMessage) -> bool:
    """True only when the frame carried a signature that this link's verifier accepted.

    pymavlink sets `_signed` from the signature check alone (a badly signed frame let through by the
    allow-unsigned callback keeps False); the flag test guards against anything else setting it.
    """
    signing = getattr(ep.conn.mav, "signing", None)
    if signing is None or signing.secret_key is None or ep.role is not Link.GCS:
        return False
    return getattr(msg, "_signed", False) is True and carries_signature(msg)


def _drain(fd: int) -> None:
    try:
        while os.read(fd, 512):
            pass
    except (BlockingIOError, InterruptedError):
        pass
