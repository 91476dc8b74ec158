"""The hand-over from Zenoh's callbacks to the one thread that owns the map.

Why not zenoh-python's ``FifoChannel``: pushing into a full one blocks the Zenoh thread that
delivers (its documentation says so), and one stalled consumer would then stall every delivery;
``RingChannel`` drops without telling. This inbox never blocks the caller and counts what it drops
(reason ``overload``), bounded both in messages and in bytes (a tile may be tens of MB).
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Delivery:
    """One message as a callback received it: which kind, on which key, when, and its bytes."""

    kind: str
    key: str
    arrival_ns: int
    payload: bytes
    alive: bool = True
    """For liveliness: the token appeared (PUT) or went (DELETE)."""


class Inbox:
    def __init__(self, max_messages: int, max_bytes: int) -> None:
        self.max_messages = max_messages
        self.max_bytes = max_bytes
        self._queue: deque[Delivery] = deque()
        self._bytes = 0
        self._ready = threading.Condition()
        self.dropped: Counter[str] = Counter()
        """Deliveries dropped because the inbox was full, by kind (written under the lock)."""

    def offer(self, delivery: Delivery, droppable: bool = True) -> bool:
        """Queue ``delivery`` unless the inbox is full (then count it dropped); never blocks.
        A delivery that is not ``droppable`` (liveliness: a few bytes, and losing one would leave a
        pair alive forever) is always queued. One message is taken whatever its size, so a tile
        larger than the byte budget is not refused for ever."""
        size = len(delivery.payload)
        with self._ready:
            full = len(self._queue) >= self.max_messages or (
                self._queue and self._bytes + size > self.max_bytes
            )
            if full and droppable:
                self.dropped[delivery.kind] += 1
                return False
            self._queue.append(delivery)
            self._bytes += size
            self._ready.notify()
            return True

    def take(self, timeout_s: float) -> list[Delivery]:
        """Everything queued, waiting up to ``timeout_s`` for the first."""
        with self._ready:
            if not self._queue:
                self._ready.wait(timeout_s)
            taken = list(self._queue)
            self._queue.clear()
            self._bytes = 0
            return taken

    def wake(self) -> None:
        with self._ready:
            self._ready.notify_all()

    def dropped_counts(self) -> dict[str, Any]:
        with self._ready:
            return dict(self.dropped)
