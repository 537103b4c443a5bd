"""The autopilot's parameters the bridge acts on, read as the autopilot says them (pure).

PARAM_REQUEST_READ at the first heartbeat and when the heartbeat comes back after a gap or a reboot (`restart`);
a PARAM_VALUE for them is taken at any time (a GCS's PARAM_SET must act at once), and one that changes a value,
or comes unasked, is asked for again: a single frame (a corrupted or forged one) lasts only until the
autopilot's answer replaces it, and a value the autopilot does not say again in PARAM_ATTEMPTS requests is
dropped. Used by the GCS failsafe watch (FS_GCS_*) and by simple avoidance (AVOID_*).
"""

from __future__ import annotations

import math

from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink

PARAM_RETRY_S = 2.0
PARAM_ATTEMPTS = 3  # an autopilot with no such parameters (PX4) answers nothing: stop asking
PARAM_CONFIRM_S = 0.1  # a changed value is asked for again no sooner than this after the last request


class ParamReader:
    """PARAM_REQUEST_READ for `names` until each is answered (a few attempts); PARAM_VALUEs taken any time, and
    asked for again when one changes a value or comes unasked, until two in a row agree (module doc)."""

    def __init__(self, names: tuple[str, ...]) -> None:
        self.names = names
        self.values: dict[str, float] = {}
        self._attempts = 0
        self._next_s: float | None = None
        self._asked_s = -math.inf
        self._unconfirmed: set[str] = set()  # taken from a PARAM_VALUE that changed the value: asked for again
        self._all = False  # `refresh`: ask for every name once more, keeping the values meanwhile

    def confirmed(self, name: str) -> float | None:
        """The value the autopilot has said (an answer to a request, or said twice); None while unknown or while
        a lone unasked PARAM_VALUE that changed it waits for the autopilot's word."""
        return None if name in self._unconfirmed else self.values.get(name)

    def restart(self, now_s: float) -> None:
        """Ask again from now (a first heartbeat, or the autopilot back after a gap or a reboot)."""
        self.values.clear()
        self._unconfirmed.clear()
        self._attempts, self._next_s = 0, now_s

    def refresh(self, now_s: float) -> None:
        """Ask for every name again, keeping the values until the answers replace them (the autopilot may have
        changed one without saying so, e.g. a command that switches the fence on)."""
        self._all, self._attempts, self._next_s = True, 0, now_s

    def due(self, now_s: float) -> bool:
        return self._next_s is not None and now_s >= self._next_s

    def requests(self, now_s: float, target_system: int, target_component: int) -> list[MAVLinkMessage]:
        missing = [name for name in self.names
                   if self._all or name not in self.values or name in self._unconfirmed]
        self._all = False
        if not missing or self._attempts >= PARAM_ATTEMPTS:
            for name in self._unconfirmed:  # not the autopilot's word: it did not say it again when asked
                del self.values[name]
            self._unconfirmed.clear()
            self._next_s = None
            return []
        self._attempts += 1
        self._next_s = now_s + PARAM_RETRY_S
        self._asked_s = now_s
        return [mavlink.MAVLink_param_request_read_message(target_system, target_component, name.encode(), -1)
                for name in missing]

    def on_param_value(self, msg: MAVLinkMessage, now_s: float) -> bool:
        """Take a PARAM_VALUE; True if it was one of ours and changed nothing unusable."""
        name = msg.param_id
        if isinstance(name, bytes):
            name = name.decode("ascii", "replace")
        name = str(name).rstrip("\x00")
        value = float(msg.param_value)
        if name not in self.names or not math.isfinite(value):
            return False
        old = self.values.get(name)
        self.values[name] = value
        if old == value:
            self._unconfirmed.discard(name)  # said twice: the autopilot's (an answer, or its repeat)
        elif old is not None or self._next_s is None:
            # Changed, or unasked: one frame, maybe a corrupted or forged one. The autopilot's answer replaces it.
            self._unconfirmed.add(name)
            self._attempts = 0
            soon = max(now_s, self._asked_s + PARAM_CONFIRM_S)
            self._next_s = soon if self._next_s is None else min(self._next_s, soon)
        return True
