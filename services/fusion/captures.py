"""One capture's messages from every pair, taken together.

The pairs of a site are triggered together, but their messages arrive apart: a camera source that
renders its pairs in turn, or a slower depth process, delivers a capture's last pair a few hundred
ms after its first. Fused as they come, a map stamped with the newest capture would show the other
pairs' movers where their previous capture saw them (at 2 Hz and 2 m/s, a metre behind) while
claiming the newer time. Held until the capture is complete, every map and every tracker step
shows one instant.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Generic, TypeVar

Item = TypeVar("Item")


@dataclass
class CaptureGroups(Generic[Item]):
    """Items (tiles, detections) of each pair, grouped by capture stamp, released in stamp order
    once complete: every live pair delivered the capture (or a later one is complete: the missing
    pairs skipped it), or ``wait_s`` passed. A pair missing from a capture released by waiting is
    *lagging*: no capture waits for it again until it delivers one in time (a pair alive whose
    messages are refused, or that is always later than ``wait_s``, must not hold every capture
    back by ``wait_s``). With no wait, nothing is held and no pair is lagging."""

    window_s: float = 0.03
    """Stamps of different pairs this close together are one capture."""
    wait_s: float = 1.0
    """A capture incomplete this long is taken as it is (a pair died, or skipped it)."""
    pending: dict[int, list[tuple[str, Item]]] = field(default_factory=dict)
    """Capture stamp → (pair, item) in arrival order."""
    pairs: dict[int, set[str]] = field(default_factory=dict)
    since_s: dict[int, float] = field(default_factory=dict)
    released_ns: int = -(2**62)
    """The newest capture released: a later message of it or an older one is released at once."""
    lagging: set[str] = field(default_factory=set)

    def add(self, pair: str, stamp_ns: int, items: list[Item], now_s: float) -> None:
        """One pair's items of one capture (an empty list still says the pair delivered it).
        ``now_s``: a monotonic clock's time, as :meth:`ready` is given."""
        window_ns = self.window_s * 1e9
        group = next((g for g in self.pending if abs(g - stamp_ns) <= window_ns), stamp_ns)
        self.pending.setdefault(group, []).extend((pair, item) for item in items)
        self.pairs.setdefault(group, set()).add(pair)
        self.since_s.setdefault(group, now_s)
        if not self._late(group):  # in time for a capture: waited for again
            self.lagging.discard(pair)

    def _late(self, group: int) -> bool:
        """A capture released already (its stamp, or one within the window of it: a pair's
        clock a few ms off the others')."""
        return group <= self.released_ns + self.window_s * 1e9

    def ready(
        self, now_s: float, live_pairs: set[str], everything: bool = False
    ) -> list[tuple[int, list[tuple[str, Item]]]]:
        """The captures to take now, oldest first (``everything``: all pending, at shutdown)."""
        expected = live_pairs - self.lagging
        groups = sorted(self.pending)
        complete = [expected <= self.pairs[g] for g in groups]
        out = []
        for k, group in enumerate(groups):
            waited = now_s - self.since_s[group] >= self.wait_s
            if not (everything or self._late(group) or any(complete[k:]) or waited):
                break  # captures are taken in order
            if waited and self.wait_s > 0 and not any(complete[k:]):
                self.lagging |= expected - self.pairs[group]
            out.append((group, self.pending.pop(group)))
            del self.pairs[group], self.since_s[group]
            self.released_ns = max(self.released_ns, group)
        return out
