"""Seeded fault injection on the datagram level, in simulated time.

One ``FaultyLink`` per direction. ``push(datagram, now_s)`` applies loss, duplication,
corruption, delay + jitter and reordering; ``pop_due(now_s)`` returns what the wire delivers
by then, in delivery order. With the default ``LinkFaults()`` every datagram is delivered
unchanged at once, so the lockstep stays exact.
"""

from __future__ import annotations

import heapq
import math
import random
from dataclasses import dataclass, field


@dataclass(frozen=True)
class LinkFaults:
    """Faults of one direction. Rates are probabilities per datagram."""

    loss_rate: float = 0.0
    duplicate_rate: float = 0.0
    reorder_rate: float = 0.0
    corrupt_rate: float = 0.0
    delay_s: float = 0.0
    jitter_s: float = 0.0
    reorder_delay_s: float = 0.05  # a reordered datagram is held this much longer

    def __post_init__(self) -> None:
        for name in ("loss_rate", "duplicate_rate", "reorder_rate", "corrupt_rate"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"{name} must be in [0, 1], got {value!r}")
        for name in ("delay_s", "jitter_s", "reorder_delay_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be >= 0, got {value!r}")

    @property
    def is_clean(self) -> bool:
        return self == LinkFaults()


@dataclass(frozen=True)
class FaultConfig:
    """Faults for both directions: ``inbound`` = towards the emulator, ``outbound`` = from it."""

    inbound: LinkFaults = field(default_factory=LinkFaults)
    outbound: LinkFaults = field(default_factory=LinkFaults)

    @classmethod
    def symmetric(cls, **kwargs: float) -> FaultConfig:
        """The same faults in both directions, e.g. ``FaultConfig.symmetric(loss_rate=0.1)``."""
        faults = LinkFaults(**kwargs)
        return cls(inbound=faults, outbound=faults)


@dataclass
class FaultCounters:
    pushed: int = 0
    dropped: int = 0
    duplicated: int = 0
    corrupted: int = 0
    reordered: int = 0
    delivered: int = 0


class FaultyLink:
    """A seeded, simulated-time wire for one direction."""

    def __init__(self, faults: LinkFaults, seed: int) -> None:
        self.faults = faults
        self._rng = random.Random(seed)
        self._queue: list[tuple[float, int, bytes]] = []
        self._seq = 0
        self.counters = FaultCounters()

    def push(self, datagram: bytes, now_s: float) -> None:
        f = self.faults
        self.counters.pushed += 1
        if f.is_clean:
            self._enqueue(now_s, datagram)
            return
        # Draw every random number in a fixed order so a seed replays exactly.
        lost = self._rng.random() < f.loss_rate
        copies = 2 if self._rng.random() < f.duplicate_rate else 1
        if lost:
            self.counters.dropped += 1
            return
        if copies == 2:
            self.counters.duplicated += 1
        for _ in range(copies):
            data = datagram
            if data and self._rng.random() < f.corrupt_rate:
                self.counters.corrupted += 1
                pos = self._rng.randrange(len(data))
                flip = self._rng.randrange(1, 256)
                data = data[:pos] + bytes([data[pos] ^ flip]) + data[pos + 1 :]
            deliver_s = now_s + f.delay_s + (self._rng.random() * f.jitter_s if f.jitter_s > 0 else 0.0)
            if self._rng.random() < f.reorder_rate:
                self.counters.reordered += 1
                deliver_s += f.reorder_delay_s
            self._enqueue(deliver_s, data)

    def _enqueue(self, deliver_s: float, data: bytes) -> None:
        heapq.heappush(self._queue, (deliver_s, self._seq, data))
        self._seq += 1

    def pop_due(self, now_s: float) -> list[bytes]:
        out: list[bytes] = []
        while self._queue and self._queue[0][0] <= now_s + 1e-12:
            out.append(heapq.heappop(self._queue)[2])
        self.counters.delivered += len(out)
        return out

    def clear(self) -> None:
        """Forget everything in flight (a link that went dead)."""
        self._queue.clear()

    def __len__(self) -> int:
        return len(self._queue)
