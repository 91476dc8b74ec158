"""One capture's messages from every pair, taken together.

The pairs of a site are triggered together, but their messages arrive apart: a camera source that
renders its pairs in turn, or a slower depth process, delivers a capture's last pair a few hundred
ms after its first. Fused as they come, a map stamped with the newest capture would show the other
pairs' movers where their previous capture saw them (at 2 Hz and 2 m/s, a metre behind) while
claiming the newer time. Held until the capture is complete, every map and every tracker step
shows one instant.

Cameras on boxes whose clocks differ by tens of milliseconds, or not triggered together at all,
stamp one capture apart: a capture is every pair's frame within a share of the frame interval.
(Within a fixed 30 ms, clocks 35 ms apart split every capture in two, neither ever complete: each
waited out ``wait_s``, and capture → map went from 0.2 s to 1.2 s.)
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass, field
from typing import Generic, TypeVar

Item = TypeVar("Item")

WINDOW_SHARE = (0.4, 0.45)
"""Stamps of different pairs within the first share of the fastest live pair's frame interval are
one capture (``window_s`` at least, but never past the second share: under half an interval, so
no pair's next frame joins its last one's capture; at 30 Hz, 30 ms took two frames of one pair
into one capture, one in six)."""
STEPS_KEPT = 8
"""A pair's frame interval is the median of its last steps between stamps: a dropped frame (a
step of two intervals) or a repeated one (a step of nothing) does not move it."""
RELEASED_KEPT = 64
"""Captures released whose first arrival is remembered (:meth:`CaptureGroups.add`)."""


@dataclass
class CaptureGroups(Generic[Item]):
    """Items (tiles, detections) of each pair, grouped by capture stamp, released in stamp order
    once complete: every live pair delivered the capture or a later one (a pair's messages come
    in order: it has none of this one), or a later capture is complete (the missing pairs
    skipped it), or the wait passed (``wait_s``, or the window if longer: a slow replay's pairs
    seconds apart). A pair missing from a capture released by waiting is *lagging*: no capture
    waits for it again until it delivers one in time, or within the wait of the capture's first
    message (a pair alive whose messages are refused, or that is always later than the wait,
    must not hold every capture back by it). With no wait, nothing is held and no pair is
    lagging. Only the live pairs' stamps set the window: a pair that left, or a forged one, has
    no say."""

    window_s: float = 0.03
    """Stamps of different pairs this close together are one capture, unless under half a frame
    interval forbids it (WINDOW_SHARE: above 15 Hz the window is 0.45 of an interval)."""
    wait_s: float = 1.0
    """A capture incomplete this long is taken as it is (a pair died, or skipped it) …"""
    wait_max_s: float = math.inf
    """… or the window, if longer, up to this (fusion's ``max_tile_age_s``: a tile held longer
    is older than tiles it refuses)."""
    pending: dict[int, list[tuple[str, Item]]] = field(default_factory=dict)
    """Capture stamp → (pair, item) in arrival order."""
    pairs: dict[int, set[str]] = field(default_factory=dict)
    since_s: dict[int, float] = field(default_factory=dict)
    released_ns: int = -(2**62)
    """The newest capture released: a later message of it or an older one is released at once."""
    released_since_s: dict[int, float] = field(default_factory=dict)
    """The first arrival of the last RELEASED_KEPT captures released."""
    lagging: set[str] = field(default_factory=set)
    live: set[str] = field(default_factory=set)
    """The live pairs as :meth:`ready` was last told."""
    newest_ns: dict[str, int] = field(default_factory=dict)
    steps_ns: dict[str, deque[int]] = field(default_factory=dict)
    """Each live pair's newest stamp and last steps between its stamps (the frame interval)."""

    def emptied(self) -> CaptureGroups[Item]:
        """A new, empty one with the same window and wait."""
        return CaptureGroups(window_s=self.window_s, wait_s=self.wait_s, wait_max_s=self.wait_max_s)

    def add(self, pair: str, stamp_ns: int, items: list[Item], now_s: float) -> None:
        """One pair's items of one capture (an empty list still says the pair delivered it).
        ``now_s``: a monotonic clock's time, as :meth:`ready` is given."""
        self._step(pair, stamp_ns)
        window_ns = self.window_ns()
        group = next((g for g in self.pending if abs(g - stamp_ns) <= window_ns), stamp_ns)
        if self._late(group, window_ns):
            # Released already. A lagging pair whose message came within the wait of the
            # capture's first is waited for again: one that had stalled once and then delivered
            # a few ms after the others stayed lagging for good (its captures were always
            # released before it came), and the tracker dropped every detection of it.
            released = (
                since_s
                for g, since_s in self.released_since_s.items()
                if abs(g - stamp_ns) <= window_ns
            )
            if now_s - next(released, -math.inf) < self._wait_s(window_ns):
                self.lagging.discard(pair)
        else:  # in time for a capture: waited for again
            self.lagging.discard(pair)
        self.pending.setdefault(group, []).extend((pair, item) for item in items)
        self.pairs.setdefault(group, set()).add(pair)
        self.since_s.setdefault(group, now_s)

    def _step(self, pair: str, stamp_ns: int) -> None:
        """Remember a pair's stamp and its step from the one before."""
        last = self.newest_ns.get(pair)
        if last is not None and stamp_ns > last:
            self.steps_ns.setdefault(pair, deque(maxlen=STEPS_KEPT)).append(stamp_ns - last)
        if last is None or stamp_ns > last:
            self.newest_ns[pair] = stamp_ns

    def window_ns(self) -> float:
        """How close stamps of different pairs must be to be one capture (WINDOW_SHARE)."""
        intervals = [
            statistics.median(steps) for pair, steps in self.steps_ns.items() if pair in self.live
        ]
        if not intervals:
            return self.window_s * 1e9
        share, most = WINDOW_SHARE
        interval_ns = min(intervals)
        return min(max(self.window_s * 1e9, share * interval_ns), most * interval_ns)

    def _wait_s(self, window_ns: float) -> float:
        """How long an incomplete capture is held: ``wait_s``, or the window if longer, up to
        ``wait_max_s``."""
        if self.wait_s <= 0:
            return 0.0
        return max(self.wait_s, min(window_ns / 1e9, self.wait_max_s))

    def _late(self, group: int, window_ns: float) -> bool:
        """A capture released already (its stamp, or one within the window of it: a pair's
        clock a few ms off the others')."""
        return group <= self.released_ns + window_ns

    def ready(
        self, now_s: float, live_pairs: set[str], everything: bool = False
    ) -> list[tuple[int, list[tuple[str, Item]]]]:
        """The captures to take now, oldest first (``everything``: all pending, at shutdown)."""
        self.live = set(live_pairs)
        for gone in set(self.newest_ns) - self.live:  # a pair that left, or a forged one
            del self.newest_ns[gone]
            self.steps_ns.pop(gone, None)
        self.lagging &= self.live  # a pair gone lags no more (health showed it so for good)
        expected = live_pairs - self.lagging
        groups = sorted(self.pending)
        window_ns = self.window_ns()
        wait_s = self._wait_s(window_ns)
        # A pair delivered a capture, or one past it: its frames fall between captures (cameras
        # not triggered together), and it has none of this one to wait for.
        delivered = [
            self.pairs[g] | {p for p, newest in self.newest_ns.items() if newest > g + window_ns}
            for g in groups
        ]
        complete = [expected <= pairs for pairs in delivered]
        out = []
        for k, group in enumerate(groups):
            waited = now_s - self.since_s[group] >= wait_s
            if not (everything or self._late(group, window_ns) or any(complete[k:]) or waited):
                break  # captures are taken in order
            if waited and wait_s > 0 and not any(complete[k:]):
                self.lagging |= expected - delivered[k]
            out.append((group, self.pending.pop(group)))
            self.released_since_s[group] = self.since_s.pop(group)
            del self.pairs[group]
            self.released_ns = max(self.released_ns, group)
        while len(self.released_since_s) > RELEASED_KEPT:
            del self.released_since_s[min(self.released_since_s)]
        return out
