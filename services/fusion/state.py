"""The map's owner (DESIGN.md, fusion): the fused grid, the tracker, the counters and the
immutable :class:`View` readers on other threads take. One thread (the service's main loop) owns
a :class:`FusionState`; nothing here touches Zenoh."""

from __future__ import annotations

import contextlib
import logging
import time
import traceback
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common import keys
from common.codec import encode
from common.lattice import Window
from common.logs import RateLimitedLog
from common.messages import MAP_UPDATE_KIND, MapUpdateHeader, ObjectsHeader
from services.fusion.captures import CaptureGroups
from services.fusion.grid import (
    CellMasks,
    FrozenMap,
    FusedGrid,
    TileOutsideMap,
    update_parts,
)
from services.fusion.inbox import Delivery
from services.fusion.intake import (
    FUTURE_TOLERANCE_S,
    AcceptedTile,
    Rejected,
    TileGate,
    decode_detections,
    decode_presence,
)
from services.fusion.map_check import MapCheck
from services.fusion.object_layers import serve_tracks
from services.fusion.objects import ObjectTracker
from services.fusion.params import GridParams
from services.fusion.persistence import StateWriter
from services.fusion.settings import FusionSettings

log = logging.getLogger("fusion")
CLOCK_STEP_MIN_S = FUTURE_TOLERANCE_S + 0.25
"""The map's newest capture this far ahead of this box's clock (a capture is taken at most
FUTURE_TOLERANCE_S ahead of it) means the clock stepped back since (``FusionState.check_clock``)."""
FORGET_AFTER_FRAMES = 4
"""The tracks end with no capture for ``decay_after_s`` or this many frame intervals, whichever
is longer: a pair replaying at one frame in 10 s keeps its tracks between frames."""


@dataclass(frozen=True)
class View:
    """What readers see: made by the owner after each change, never changed after."""

    frozen: FrozenMap
    pairs: tuple[str, ...] = ()
    accepted: Mapping[str, int] = field(default_factory=dict)
    rejected: Mapping[str, int] = field(default_factory=dict)
    detections_rejected: Mapping[str, int] = field(default_factory=dict)
    liveliness_rejected: Mapping[str, int] = field(default_factory=dict)
    last_tile_s: Mapping[str, float] = field(default_factory=dict)
    capture_to_fused_ms: Mapping[str, float] = field(default_factory=dict)
    processes: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    lagging: frozenset[str] = frozenset()
    """Pairs a capture is no longer held for (:class:`CaptureGroups`)."""
    rejected_by_pair: Mapping[tuple[str, str], int] = field(default_factory=dict)
    """Tiles and detections refused, by the pair whose key they came on."""
    detections_late: Mapping[str, int] = field(default_factory=dict)
    """Per pair, detections the tracker dropped as late (``ObjectTracker.late``)."""
    stale_after_s: float = GridParams().decay_after_s
    """A map with no newer capture than this is stale: the grid's ``decay_after_s``, after which
    it forgets what it saw."""
    objects: ObjectsHeader = field(
        default_factory=lambda: ObjectsHeader(version=0, stamp_ns=0, objects=[])
    )


class FusionState:
    """The map and its bookkeeping, owned by one thread (the service's main loop)."""

    def __init__(self, settings: FusionSettings, grid: FusedGrid) -> None:
        self.settings = settings
        self.grid = grid
        self.gate = TileGate(
            settings.resolution_m,
            settings.max_tile_age_s,
            int(settings.max_message_mb * 1024 * 1024),
            site=grid.params.site_window(),
            bounded=grid.params.bounds is not None,
        )
        self.accepted: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.detections_rejected: Counter[str] = Counter()
        self.liveliness_rejected: Counter[str] = Counter()
        self.rejected_by_pair: Counter[tuple[str, str]] = Counter()
        """By pair and kind (``tile``, ``detections``): health tells a pair's tiles refused from
        its object detections refused (a stall's stale detections read as refused tiles)."""
        self.last_tile_s: dict[str, float] = {}
        self.capture_to_fused_ms: dict[str, float] = {}
        self.processes: dict[str, set[str]] = {}
        """Each pair's depth processes alive (liveliness tokens ``depth/{pair}/alive/{instance}``)."""
        self.contributors: set[str] = set()
        wait_s, wait_max_s = settings.capture_wait_s, settings.max_tile_age_s
        self.tiles: CaptureGroups[tuple[str, AcceptedTile]] = CaptureGroups(
            wait_s=wait_s, wait_max_s=wait_max_s
        )
        """Admitted tiles (with their keys) waiting for the rest of their capture."""
        self.tracker = ObjectTracker(captures=CaptureGroups(wait_s=wait_s, wait_max_s=wait_max_s))
        self.objects_header = ObjectsHeader(epoch=grid.epoch_ns, version=0, stamp_ns=0, objects=[])
        self.outlined: CellMasks = []
        """The static objects' footprints the map agrees with, less their edge cells the frames
        call free (``serve_tracks``), as of the newest capture."""
        self.tops: CellMasks = []
        """The movers' tops no frame measured (``serve_tracks``), as of the newest capture, shown
        until ``sweep_max_s`` after it: no capture since means the pairs stopped or died, and the
        movers have moved on."""
        self.last_capture_s = time.monotonic()
        """When the tracker last had a capture: with none for ``decay_after_s`` (every pair
        stopped or died), the tracks and outlines are forgotten as the cells' evidence is."""
        self.warn = RateLimitedLog(log)
        self._objects_emptied = False
        self.fused_capture_ns: int | None = None
        """The newest capture whose tiles the map took (its group's stamp) …"""
        self.fused_pairs: set[str] = set()
        """… the pairs whose tiles it had …"""
        self.previous_capture_ns: int | None = None
        """… and the capture the map took before it."""
        self.unpublished_since_s: float | None = None
        """When the map first took a capture it has not published since (monotonic)."""
        self.check_clock(time.time_ns())  # a state saved on a box whose clock was ahead
        frozen, self.unsaved = grid.freeze()
        self.view = View(frozen, stale_after_s=grid.params.decay_after_s)
        """Replaced, never changed: readers on other threads take the reference and keep it."""

    @property
    def alive(self) -> set[str]:
        return {pair for pair, instances in self.processes.items() if instances}

    def check_clock(self, now_ns: int) -> None:
        """Whether this box's clock (``now_ns``) stepped back behind the map's newest capture:
        then the map's times move back with it, and what orders captures by stamp starts over
        (each pair's newest tile, the captures held, the tracks). A site whose clocks an NTP
        server set back by an hour had every tile refused as out of order for that hour, the
        objects frozen and nothing decaying; a state saved on a box whose clock was ahead, the
        same after a restart."""
        ahead_s = (self.grid.stamp_ns - now_ns) / 1e9
        if ahead_s <= CLOCK_STEP_MIN_S:
            return
        self.grid.shift_time(-ahead_s)
        self.gate.newest_stamp_ns.clear()
        held = sum(len(tiles) for tiles in self.tiles.pending.values())
        self.tiles = self.tiles.emptied()
        self.fused_capture_ns = self.previous_capture_ns = None
        self.tracker.restart()
        self._tracks_begin_anew()
        log.warning(
            "this box's clock is behind the map's newest capture: the clock stepped back; the "
            "map's times moved back with it, and the objects are tracked anew",
            extra={"step_s": round(ahead_s, 3), "held_tiles_dropped": held},
        )

    def handle(self, delivery: Delivery) -> None:
        """One message from the inbox; a bad one is counted by reason, never raised. Whatever
        else fusing it raises (a bug, memory) is counted as ``internal`` and logged with the
        exception: the owner's loop, and with it the map, outlives any one message."""
        try:
            self.check_clock(delivery.arrival_ns)
            if delivery.kind == "tile":
                self._tile(delivery)
            elif delivery.kind == "detections":
                self._detections(delivery)
            else:
                self._presence(delivery)
        except Rejected as rejection:
            self._count(delivery.kind, delivery.key, rejection.reason, str(rejection))
        except Exception as error:
            self._count(delivery.kind, delivery.key, "internal", _internal(error))

    def _count(self, kind: str, key: str, reason: str, detail: str) -> None:
        counters = {
            "tile": self.rejected,
            "detections": self.detections_rejected,
        }.get(kind, self.liveliness_rejected)
        counters[reason] += 1
        pair = None
        if kind != "presence":
            with contextlib.suppress(ValueError):  # a key of no pair: counted by reason only
                pair = keys.pair_of(key)
                self.rejected_by_pair[pair, kind] += 1
        self.warn.warning(
            self._warning_key(f"{kind}_{reason}", pair),
            f"{kind} rejected",
            reason=reason,
            on=key,
            error=detail[:200],
        )

    def _warning_key(self, what: str, pair: str | None) -> str:
        """A rate-limited warning's key: each known pair's said apart (a second pair's clock an
        hour off was never named under the first's); a flood on made-up pairs stays one line."""
        known = pair is not None and (pair in self.alive or pair in self.contributors)
        return f"{what}_{pair}" if known else what

    def _tile(self, delivery: Delivery) -> None:
        """A pair's tile: checked now, fused with the rest of its capture (:meth:`fuse_captures`)."""
        tile = self.gate.admit(delivery.payload, delivery.arrival_ns, delivery.key)
        self.gate.accepted(tile)
        pair = tile.header.pair
        self.last_tile_s[pair] = time.monotonic()
        self.tiles.add(pair, tile.header.stamp_ns, [(delivery.key, tile)], time.monotonic())

    def fuse_captures(self, everything: bool = False) -> None:
        """Fuse the tiles of every complete capture (``everything``: all held, at shutdown)."""
        now_s = time.monotonic()
        for group, tiles in self.tiles.ready(now_s, self.alive, everything):
            if tiles:
                self.previous_capture_ns, self.fused_capture_ns = self.fused_capture_ns, group
                self.fused_pairs = {pair for pair, _ in tiles}
                if self.unpublished_since_s is None:
                    self.unpublished_since_s = now_s
            for pair, (key, tile) in tiles:
                try:
                    self.grid.integrate_tile(tile, tile.header.stamp_ns)
                except TileOutsideMap as error:
                    self._count("tile", key, error.reason, str(error))
                    continue
                except Exception as error:
                    self._count("tile", key, "internal", _internal(error))
                    continue
                self.accepted[pair] += 1
                self.contributors.add(pair)
                self.capture_to_fused_ms[pair] = (time.time_ns() - tile.header.stamp_ns) / 1e6

    def objects_hold_s(self, now_s: float) -> float:
        """How much longer the map's newest capture waits for its objects before it goes out (0:
        it need not): while :meth:`_objects_awaited`, for at most ``capture_wait_s`` since the
        map first held a capture back. Published a capture ahead of its tracks, the map served
        free the floor a mover had just driven onto (the movers' layers still stood where it
        was) until its objects came tens of ms later: live, on a plain floor, such maps read
        1.3 % of the obstacles' cells free, 0.4 % once the objects came."""
        if self.unpublished_since_s is None or not self._objects_awaited():
            return 0.0
        return max(0.0, self.unpublished_since_s + self.settings.capture_wait_s - now_s)

    def say_if_objects_overdue(self) -> None:
        """Before a publish: a capture whose objects the hold waited for in vain is said."""
        if self.settings.capture_wait_s > 0 and self._objects_awaited():
            self.warn.warning(
                "objects_overdue",
                "a capture's objects did not come within the capture wait: its map went out "
                "without them (is a pair's depth process slow to measure objects? "
                "--capture-wait-s)",
                pairs=",".join(sorted(self.fused_pairs)),
            )

    def _objects_awaited(self) -> bool:
        """Whether objects of the newest capture the map took are still to come: the tracker has
        not taken that capture, and a live pair of it sent detections of the capture before (a
        pair that sends none, or stopped, or whose detections are refused, is not waited for)."""
        if self.fused_capture_ns is None or self.previous_capture_ns is None:
            return False
        captures, window_ns = self.tracker.captures, self.tiles.window_ns()
        if captures.released_ns >= self.fused_capture_ns - window_ns:
            return False
        since_ns = self.previous_capture_ns - window_ns
        return any(
            captures.newest_ns.get(pair, -1) >= since_ns for pair in self.fused_pairs & self.alive
        )

    def _detections(self, delivery: Delivery) -> None:
        """One pair's objects of one frame: held until the rest of the capture arrives."""
        h = decode_detections(delivery.payload, delivery.key, delivery.arrival_ns, self.gate)
        self.tracker.add(h.pair, h.stamp_ns, list(h.detections), time.monotonic(), h.camera_m)

    def _presence(self, delivery: Delivery) -> None:
        presence = decode_presence(delivery.key, delivery.alive)
        if not presence.alive and presence.instance not in self.processes.get(presence.pair, ()):
            return  # a process never seen leaving: nothing changes
        instances = self.processes.setdefault(presence.pair, set())
        if presence.alive:
            if instances - {presence.instance}:
                log.warning(
                    "a second depth process claims the pair",
                    extra={
                        "pair": presence.pair,
                        "processes": ",".join(sorted(instances | {presence.instance})),
                    },
                )
            instances.add(presence.instance)
        else:
            instances.discard(presence.instance)
        # The last process of a pair leaving is a pair the map no longer sees: a warning (every
        # pair gone at once, a router lost, was four info lines).
        level = logging.INFO if presence.alive or instances else logging.WARNING
        log.log(
            level,
            "depth process joined"
            if presence.alive
            else "depth process left"
            + ("" if instances else ": no process left for the pair, its cells will decay"),
            extra={"pair": presence.pair, "instance": presence.instance},
        )

    def refresh_objects(self) -> ObjectsHeader | None:
        """:meth:`_refresh_objects`, outliving whatever it raises (a bug, memory): counted as
        detections rejected ``internal`` and logged, and the tracks begin anew (a track that broke
        one capture would break each one after). The owner's loop, and with it the map, goes on
        (it died: a detection's yaw of 1e308 made a NaN size the object list refused)."""
        try:
            refreshed = self._refresh_objects()
        except Exception as error:
            self.detections_rejected["internal"] += 1
            self.tracker.forget()
            self.warn.warning(
                "objects_internal", "tracking failed: the tracks begin anew", error=_internal(error)
            )
            self._tracks_begin_anew()
            refreshed = None
        if self._objects_emptied:  # the empty list of tracks forgotten since the last call
            self._objects_emptied = False
            return self.objects_header if refreshed is None else refreshed
        return refreshed

    def _tracks_begin_anew(self) -> None:
        """What forgotten tracks served goes with them: their outlines and tops, and the list
        (published at the next :meth:`refresh_objects`: after a clock step, ``map/objects`` kept
        the old tracks, stamped an hour ahead)."""
        self.outlined, self.tops = [], []
        self.grid.set_predicted([])
        self.objects_header = ObjectsHeader(
            epoch=self.grid.epoch_ns,
            version=self.tracker.version,
            stamp_ns=self.tracker.stamp_ns,
            objects=[],
        )
        self._objects_emptied = True

    def _refresh_objects(self) -> ObjectsHeader | None:
        """Merge and track the captures that are complete; the predicted layer holds the static
        objects' footprints the frames agree with, less their edge cells the frames call free (the
        contested layer those, the other footprints, the cells within a centimetre outside every
        static one, and the moving and unsettled tracks' footprints now; the fringe layer the
        occupied cells just outside static ones), the movers' tops no frame measured and, with
        ``predict_movers``, the moving tracks' paths up to one frame interval past now (the map's
        visible time); returns the new object list if the tracks changed."""
        now_ns = time.time_ns()
        resolution_m = self.grid.params.resolution_m
        late_before = dict(self.tracker.late)
        changed = self.tracker.flush(time.monotonic(), self.alive)
        for pair, count in self.tracker.late.items():
            if count > late_before.get(pair, 0):
                self.warn.warning(
                    self._warning_key("detections_late", pair),
                    "detections came after a later capture was tracked: dropped (is the pair's "
                    "depth process or its clock behind the others'? --capture-wait-s)",
                    pair=pair,
                    dropped_total=count,
                )
        check = MapCheck()
        expired = False
        if changed:  # once a capture: tracks and evidence both moved
            self.outlined, self.tops, check = serve_tracks(
                self.grid, self.tracker, self.settings.outline_static
            )
            self.last_capture_s = time.monotonic()
        elif self.tops and time.monotonic() > self.last_capture_s + self.tracker.config.sweep_max_s:
            self.tops, expired = [], True
        if (
            not changed
            and (self.outlined or self.tracker.tracks)
            and time.monotonic() - self.last_capture_s
            > max(
                self.grid.params.decay_after_s,
                FORGET_AFTER_FRAMES * self.tracker.frame_interval_s,
            )
        ):
            # No capture for as long as a cell's evidence lasts: what was tracked may have been
            # moved. An outline served obstacles on a map whose every cell had decayed unknown.
            self.outlined, self.tops, expired = [], [], True
            self.tracker.forget()
            changed = True
        if self.settings.predict_movers:
            until_ns = now_ns + int(self.tracker.ahead_s() * 1e9)
            swept = self.tracker.sweep(resolution_m, self.grid.stamp_ns, until_ns)
            self.grid.set_predicted(self.outlined + self.tops + swept)
        elif changed or expired:
            self.grid.set_predicted(self.outlined + self.tops)
        if not changed:
            return None
        self.objects_header = ObjectsHeader(
            epoch=self.grid.epoch_ns,
            version=self.tracker.version,
            stamp_ns=self.tracker.stamp_ns,
            objects=self.tracker.objects(check.pieces, self.grid),
        )
        return self.objects_header

    def publish(self) -> list[bytes]:
        """Freeze the changes (copy-on-write of the changed chunks) for readers; returns the
        ``map/updates`` payloads of the changed cells: one per group of changed chunks
        (:func:`update_parts`), so their size follows the change, not its bounding box.

        The messages of one publish form a chain (previous_version → version, each continuing
        the last): a follower applies them in turn with nothing new to learn, and reaches the
        version ``map/latest`` serves after the last. The counter jumps ahead to make room for the
        chain when fewer tiles than messages came (versions only count up; they are not tiles)."""
        previous = self.view.frozen
        self.unpublished_since_s = None
        parts = [
            part.intersect(self.grid.window) for part in update_parts(self.grid.take_dirty_parts())
        ]
        parts = [part for part in parts if not part.empty]
        if self.grid.version != previous.version:
            self.grid.version = max(self.grid.version, previous.version + len(parts))
        frozen, changed = self.grid.freeze()
        self.unsaved |= changed
        self.update_view(frozen)
        if not parts or frozen.version == previous.version:
            return []
        payloads = []
        for k, part in enumerate(parts):
            version = frozen.version if k == len(parts) - 1 else previous.version + k + 1
            occupancy = self.grid.window_of("served", part)
            payloads.append(update_payload(frozen, part, previous.version + k, occupancy, version))
        return payloads

    def update_view(self, frozen: FrozenMap | None = None) -> None:
        """A new View with the counters as they are now."""
        self.view = View(
            frozen or self.view.frozen,
            tuple(sorted(self.contributors)),
            dict(self.accepted),
            dict(self.rejected),
            dict(self.detections_rejected),
            dict(self.liveliness_rejected),
            dict(self.last_tile_s),
            dict(self.capture_to_fused_ms),
            {pair: tuple(sorted(i)) for pair, i in self.processes.items()},
            frozenset(self.tiles.lagging),
            dict(self.rejected_by_pair),
            dict(self.tracker.late),
            self.grid.params.decay_after_s,
            self.objects_header,
        )


def _internal(error: Exception) -> str:
    """What an unexpected exception says, with where it was raised."""
    frames = traceback.extract_tb(error.__traceback__)
    where = f" at {Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else ""
    return f"{type(error).__name__}: {error}{where}"


def update_payload(
    frozen: FrozenMap,
    part: Window,
    previous_version: int,
    occupancy: np.ndarray,
    version: int | None = None,
) -> bytes:
    header = MapUpdateHeader(
        version=frozen.version if version is None else version,
        previous_version=previous_version,
        final_version=frozen.version,
        epoch=frozen.epoch_ns,
        stamp_ns=frozen.stamp_ns,
        resolution_m=frozen.resolution_m,
        i0=part.i0,
        j0=part.j0,
        cols=part.cols,
        rows=part.rows,
        map_i0=frozen.window.i0,
        map_j0=frozen.window.j0,
        map_cols=frozen.window.cols,
        map_rows=frozen.window.rows,
    )
    return encode(MAP_UPDATE_KIND, header, {"occupancy": np.ascontiguousarray(occupancy)})


def health_of(view: View, writer: StateWriter | None, dropped: Mapping[str, int]) -> dict[str, Any]:
    now = time.time()
    frozen = view.frozen
    window = frozen.window
    refused_pairs = {pair for pair, _ in view.rejected_by_pair}
    pairs = sorted(set(view.accepted) | set(view.processes) | refused_pairs)
    state: dict[str, Any] = {}
    if writer is not None:
        state = {
            "saved_version": writer.saved_version,
            "last_save_age_s": (
                round(time.monotonic() - writer.saved_s, 3) if writer.saved_s else None
            ),
            "save_errors": writer.errors,
        }
    return {
        "pairs": {
            p: {
                "alive": bool(view.processes.get(p)),
                "processes": list(view.processes.get(p, ())),
                "conflict": len(view.processes.get(p, ())) > 1,
                "tiles": view.accepted.get(p, 0),
                "last_tile_age_s": round(time.monotonic() - view.last_tile_s[p], 3)
                if p in view.last_tile_s
                else None,
                "capture_to_fused_ms": view.capture_to_fused_ms.get(p),
                "lagging": p in view.lagging,
                "rejected": view.rejected_by_pair.get((p, "tile"), 0),
                "detections_rejected": view.rejected_by_pair.get((p, "detections"), 0),
                "detections_late": view.detections_late.get(p, 0),
            }
            for p in pairs
        },
        "tiles_accepted": sum(view.accepted.values()),
        "tiles_rejected": _with_overload(view.rejected, dropped.get("tile", 0)),
        "detections_rejected": _with_overload(
            view.detections_rejected, dropped.get("detections", 0)
        ),
        "liveliness_rejected": dict(view.liveliness_rejected),
        "objects": len(view.objects.objects),
        "map": {
            "epoch": frozen.epoch_ns,
            "version": frozen.version,
            "cols": window.cols,
            "rows": window.rows,
            "resolution_m": frozen.resolution_m,
            "origin_m": list(window.origin_m(frozen.resolution_m)),
            "known_cells": frozen.known_cells(),
            "chunks": len(frozen.chunks),
            "capture_age_s": (
                round(max(0.0, now - frozen.stamp_ns / 1e9), 3) if frozen.stamp_ns else None
            ),
            "stale_after_s": view.stale_after_s,
        },
        "state": state,
    }


def _with_overload(counts: Mapping[str, int], overload: int) -> dict[str, int]:
    return {**counts, "overload": overload} if overload else dict(counts)
