"""Fusion process: tiles in from every pair, one log-odds map out through queryables and updates.

Threads and who owns what:
- Zenoh's callbacks only hand messages over (``Inbox``; queries to a ``QueryWorker``) and never block.
- The main thread owns the map (:class:`FusionState`): it decodes every message (one decode function
  per kind, ``services.fusion.intake``), integrates tiles, publishes ``map/updates`` and an immutable
  :class:`View` (a frozen copy-on-write map plus counters) after each change.
- Query workers answer ``map/latest``, ``map/health`` and ``map/objects`` from the newest View:
  they never touch the grid, and every query gets a reply (an answer or an error).
- The state writer (``services.fusion.persistence``) saves the chunks changed since its last save.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import queue
import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import zenoh

from common import keys
from common.codec import WIRE_ENCODING, encode
from common.lattice import Window
from common.lifecycle import stop_on_signals
from common.logs import RateLimitedLog, setup_logging
from common.messages import MAP_UPDATE_KIND, OBJECTS_KIND, MapUpdateHeader, ObjectsHeader
from common.occupancy_map import OccupancyMap
from common.settings import parse_settings, startup_error
from common.zenoh_session import open_session
from services.fusion.captures import CaptureGroups
from services.fusion.grid import (
    CellMasks,
    FrozenMap,
    FusedGrid,
    ServedAssembler,
    TileOutsideMap,
    compile_rules,
    update_parts,
)
from services.fusion.inbox import Delivery, Inbox
from services.fusion.intake import (
    AcceptedTile,
    Rejected,
    TileGate,
    decode_detections,
    decode_presence,
)
from services.fusion.map_check import MapCheck
from services.fusion.object_layers import serve_tracks
from services.fusion.objects import ObjectTracker
from services.fusion.persistence import StateOfAnotherMap, StateWriter, load_grid
from services.fusion.settings import FusionSettings
from services.fusion.snapshot import (
    CONTENT_TYPES,
    MapQuery,
    MapQueryError,
    MapSnapshot,
    parse_map_query,
)

log = logging.getLogger("fusion")
STATE_LOCK = ".lock"
"""The state directory's lock file (:func:`lock_state_dir`): it holds the owner's pid."""
IDLE_WAIT_S = 0.1
"""Longest the owner sleeps without a message: a stop, decay and saves are noticed this soon."""
DECAY_PERIOD_S = 1.0
INBOX_MESSAGES = 16384
"""Messages the inbox holds: a burst of small bad tiles is counted by reason, not as overload."""
INBOX_LARGEST_MESSAGES = 4
"""Its byte budget, in largest messages allowed (``--max-message-mb``): a few big tiles may wait
while one is fused; a stream the map cannot keep up with is dropped, not held in memory."""
SNAPSHOT_COST_SHARE = 0.2
QUERIED_RECENTLY_S = 2.0
STALE_LIMIT_S = 1.0
"""A query finding a snapshot older than this (and than two paces) waits for a new one."""
DEFAULT_QUERY = MapQuery()
QUERY_BACKLOG = 256
MAP_QUERY_THREADS = 2
"""map/latest replies are large (a whole map): while one is being sent, another is answered."""
"""Queries waiting for a worker; beyond it a query is answered "overloaded" at once."""


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
    rejected_by_pair: Mapping[str, int] = field(default_factory=dict)
    """Tiles and detections refused, by the pair whose key they came on."""
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
        self.rejected_by_pair: Counter[str] = Counter()
        self.last_tile_s: dict[str, float] = {}
        self.capture_to_fused_ms: dict[str, float] = {}
        self.processes: dict[str, set[str]] = {}
        """Each pair's depth processes alive (liveliness tokens ``depth/{pair}/alive/{instance}``)."""
        self.contributors: set[str] = set()
        self.tiles: CaptureGroups[tuple[str, AcceptedTile]] = CaptureGroups(
            wait_s=settings.capture_wait_s
        )
        """Admitted tiles (with their keys) waiting for the rest of their capture."""
        self.tracker = ObjectTracker(captures=CaptureGroups(wait_s=settings.capture_wait_s))
        self.objects_header = ObjectsHeader(version=0, stamp_ns=0, objects=[])
        self.outlined: CellMasks = []
        """The static objects' footprints the map agrees with, less their edge cells the frames
        call free (``serve_tracks``), as of the newest capture."""
        self.tops: CellMasks = []
        """The movers' tops no frame measured (``serve_tracks``), as of the newest capture …"""
        self.tops_until_s = 0.0
        """… shown until this monotonic time: a capture's ``sweep_max_s`` later, no capture since
        means the pairs stopped or died, and the movers have moved on."""
        self.last_capture_s = time.monotonic()
        """When the tracker last had a capture: with none for ``decay_after_s`` (every pair
        stopped or died), the tracks and outlines are forgotten as the cells' evidence is."""
        self.warn = RateLimitedLog(log)
        frozen, self.unsaved = grid.freeze()
        self.view = View(frozen)
        """Replaced, never changed: readers on other threads take the reference and keep it."""

    @property
    def alive(self) -> set[str]:
        return {pair for pair, instances in self.processes.items() if instances}

    def handle(self, delivery: Delivery) -> None:
        """One message from the inbox; a bad one is counted by reason, never raised. Whatever
        else fusing it raises (a bug, memory) is counted as ``internal`` and logged with the
        exception: the owner's loop, and with it the map, outlives any one message."""
        try:
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
        if kind != "presence":
            with contextlib.suppress(ValueError):  # a key of no pair: counted by reason only
                self.rejected_by_pair[keys.pair_of(key)] += 1
        self.warn.warning(
            f"{kind}_{reason}", f"{kind} rejected", reason=reason, on=key, error=detail[:200]
        )

    def _tile(self, delivery: Delivery) -> None:
        """A pair's tile: checked now, fused with the rest of its capture (:meth:`fuse_captures`)."""
        tile = self.gate.admit(delivery.payload, delivery.arrival_ns, delivery.key)
        self.gate.accepted(tile)
        pair = tile.header.pair
        self.last_tile_s[pair] = time.time()
        self.tiles.add(pair, tile.header.stamp_ns, [(delivery.key, tile)], time.monotonic())

    def fuse_captures(self, everything: bool = False) -> None:
        """Fuse the tiles of every complete capture (``everything``: all held, at shutdown)."""
        for _, tiles in self.tiles.ready(time.monotonic(), self.alive, everything):
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

    def _detections(self, delivery: Delivery) -> None:
        """One pair's objects of one frame: held until the rest of the capture arrives."""
        h = decode_detections(delivery.payload, delivery.key, delivery.arrival_ns, self.gate)
        self.tracker.add(h.pair, h.stamp_ns, list(h.detections), time.monotonic())

    def _presence(self, delivery: Delivery) -> None:
        presence = decode_presence(delivery.key, delivery.alive)
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
        log.info(
            "depth process joined" if presence.alive else "depth process left",
            extra={"pair": presence.pair, "instance": presence.instance},
        )

    def refresh_objects(self) -> ObjectsHeader | None:
        """Merge and track the captures that are complete; the predicted layer holds the static
        objects' footprints the frames agree with, less their edge cells the frames call free (the
        contested layer those, the other footprints, the cells within a centimetre outside every
        static one, and the moving and unsettled tracks' footprints now; the fringe layer the
        occupied cells just outside static ones), the movers' tops no frame measured and, with
        ``predict_movers``, the moving tracks' paths up to one frame interval past now (the map's
        visible time); returns the new object list if the tracks changed."""
        now_ns = time.time_ns()
        resolution_m = self.grid.params.resolution_m
        changed = self.tracker.flush(time.monotonic(), self.alive)
        check = MapCheck()
        expired = False
        if changed:  # once a capture: tracks and evidence both moved
            self.outlined, self.tops, check = serve_tracks(
                self.grid, self.tracker, self.settings.outline_static
            )
            self.tops_until_s = time.monotonic() + self.tracker.config.sweep_max_s
            self.last_capture_s = time.monotonic()
        elif self.tops and time.monotonic() > self.tops_until_s:
            self.tops, expired = [], True
        if (
            not changed
            and (self.outlined or self.tracker.tracks)
            and time.monotonic() - self.last_capture_s > self.grid.params.decay_after_s
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


def occupancy_map_of(
    view: View, with_layers: bool, assembler: ServedAssembler | None = None
) -> OccupancyMap:
    """The whole map of a View, assembled from its chunks (on a query thread, not the owner)."""
    frozen = view.frozen

    def layer(name: str) -> Any:
        return frozen.layer(name) if with_layers else None

    return OccupancyMap(
        occupancy=frozen.layer("served") if assembler is None else assembler.occupancy(frozen),
        resolution_m=frozen.resolution_m,
        i0=frozen.window.i0,
        j0=frozen.window.j0,
        version=frozen.version,
        stamp_ns=frozen.stamp_ns,
        pairs=list(view.pairs),
        epoch=frozen.epoch_ns,
        logodds=layer("logodds"),
        height_m=layer("height_m"),
        predicted=layer("predicted"),
        last_seen_s=layer("last_seen_s"),
    )


class SnapshotBuilder:
    """The ``map/latest`` snapshots, assembled from the newest View's chunks and encoded once
    however many clients ask, on a thread of their own, so a query does not wait for one. While
    clients ask (within QUERIED_RECENTLY_S), each map change makes a new one, no sooner than a pace
    after the last: the publish interval, or SNAPSHOT_COST_SHARE⁻¹ times what the last cost. So an
    unqueried map costs nothing, a huge map under a stream of tiles and of queries spends at most
    that share of the time on snapshots, and ``map/latest`` may be about a pace older than
    ``map/updates`` (followers replay the updates since). A query finding only a snapshot older
    than STALE_LIMIT_S (the first after a quiet spell) waits for a new one. Layered snapshots (a tool's,
    rarely asked) are made when asked, once per version."""

    def __init__(self, newest: Callable[[], View], min_interval_s: float) -> None:
        self._newest = newest
        self.min_interval_s = min_interval_s
        self._lock = threading.Lock()
        self._changed = threading.Event()
        self._closing = False
        self._queried_s = 0.0
        self._current: tuple[tuple[int, int], MapSnapshot, bytes, float] | None = None
        """(map version, snapshot, its plain msgpack answer, when it was made (monotonic s))."""
        self._layered: tuple[tuple[int, int], MapSnapshot] | None = None
        self._cost_s = 0.0
        self._assembler = ServedAssembler()
        self._thread = threading.Thread(target=self._run, name="fusion-snapshots", daemon=True)
        self._thread.start()

    def changed(self) -> None:
        """The owner published a new version."""
        self._changed.set()

    def _pace_s(self) -> float:
        return max(self.min_interval_s, self._cost_s / SNAPSHOT_COST_SHARE)

    def _usable(self) -> tuple[tuple[int, int], MapSnapshot, bytes, float] | None:
        now_s = time.monotonic()
        self._queried_s = now_s
        current = self._current
        if current is None or (
            current[0] != self._newest().frozen.key
            and now_s - current[3] >= max(STALE_LIMIT_S, 2 * self._pace_s())
        ):
            return None
        return current

    def plain(self) -> bytes | None:
        """Ready bytes for a plain ``map/latest`` (what robots ask), or None: ask :meth:`get`."""
        current = self._usable()
        return None if current is None else current[2]

    def get(self, with_layers: bool) -> MapSnapshot:
        if with_layers:
            with self._lock:
                view = self._newest()
                if self._layered is None or self._layered[0] != view.frozen.key:
                    self._layered = (view.frozen.key, MapSnapshot(occupancy_map_of(view, True)))
                return self._layered[1]
        current = self._usable()
        return current[1] if current is not None else self._build()

    def _build(self) -> MapSnapshot:
        with self._lock:
            view = self._newest()
            if self._current is not None and self._current[0] == view.frozen.key:
                return self._current[1]
            started = time.perf_counter()
            snapshot = MapSnapshot(occupancy_map_of(view, False, self._assembler))
            plain = snapshot.encoded(DEFAULT_QUERY)  # the answer most clients want, made once
            self._cost_s = time.perf_counter() - started
            self._current = (view.frozen.key, snapshot, plain, time.monotonic())
            return snapshot

    def _run(self) -> None:
        while True:
            self._changed.wait()
            if self._closing:
                return
            self._changed.clear()
            if time.monotonic() - self._queried_s > QUERIED_RECENTLY_S:
                continue  # nobody asks: the next query makes one
            self._build()
            time.sleep(self._pace_s())

    def close(self) -> None:
        self._closing = True
        self._changed.set()
        self._thread.join(5.0)


OBJECT_FORMATS = {"msgpack": WIRE_ENCODING, "json": "application/json"}


def objects_payload(header: ObjectsHeader, fmt: str) -> bytes:
    """``map/objects`` as msgpack (the codec's envelope) or, for people, plain JSON."""
    if fmt == "json":
        return json.dumps(header.model_dump(mode="json")).encode()
    return encode(OBJECTS_KIND, header)


def health_of(view: View, writer: StateWriter | None, dropped: Mapping[str, int]) -> dict[str, Any]:
    now = time.time()
    frozen = view.frozen
    window = frozen.window
    pairs = sorted(set(view.accepted) | set(view.processes) | set(view.rejected_by_pair))
    state: dict[str, Any] = {}
    if writer is not None:
        state = {
            "saved_version": writer.saved_version,
            "last_save_age_s": round(now - writer.saved_s, 3) if writer.saved_s else None,
            "save_errors": writer.errors,
        }
    return {
        "pairs": {
            p: {
                "alive": bool(view.processes.get(p)),
                "processes": list(view.processes.get(p, ())),
                "conflict": len(view.processes.get(p, ())) > 1,
                "tiles": view.accepted.get(p, 0),
                "last_tile_age_s": round(now - view.last_tile_s[p], 3)
                if p in view.last_tile_s
                else None,
                "capture_to_fused_ms": view.capture_to_fused_ms.get(p),
                "lagging": p in view.lagging,
                "rejected": view.rejected_by_pair.get(p, 0),
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
        },
        "state": state,
    }


def _with_overload(counts: Mapping[str, int], overload: int) -> dict[str, int]:
    return {**counts, "overload": overload} if overload else dict(counts)


class QueryWorker:
    """Answers one kind of query on threads of its own; Zenoh's callback only queues the query (a
    full backlog is answered "overloaded" at once). Every query gets a reply: an answer, or an
    error naming what went wrong."""

    def __init__(self, name: str, answer: Callable[[zenoh.Query], None], threads: int = 1) -> None:
        self.name = name
        self._answer = answer
        self._failures = RateLimitedLog(log)
        self._queue: queue.Queue[zenoh.Query | None] = queue.Queue(QUERY_BACKLOG)
        self._threads = [
            threading.Thread(target=self._run, name=f"fusion-{name}-{n}", daemon=True)
            for n in range(threads)
        ]
        for thread in self._threads:
            thread.start()

    def offer(self, query: zenoh.Query) -> None:
        try:
            self._queue.put_nowait(query)
        except queue.Full:
            query.reply_err(f"{self.name}: overloaded, try again")
            finish(query)

    def _run(self) -> None:
        while (query := self._queue.get()) is not None:
            try:
                self._answer(query)
            except MapQueryError as error:  # the asker's mistake: its reply says so, not our log
                query.reply_err(f"{self.name}: {type(error).__name__}: {error}")
            except Exception as error:  # one odd query must not end the worker, nor go unanswered
                self._failures.warning(
                    type(error).__name__, "query failed", on=self.name, error=repr(error)[:200]
                )
                query.reply_err(f"{self.name}: {type(error).__name__}: {error}")
            finally:
                finish(query)

    def close(self) -> None:
        for _ in self._threads:
            self._queue.put(None)
        for thread in self._threads:
            thread.join(5.0)


def query_parameters(query: zenoh.Query) -> dict[str, str]:
    return dict(query.parameters.__iter__())  # the stub types __iter__ as returning a list


def finish(query: zenoh.Query) -> None:
    """Finalise the query now (replies sent, the asker's get ends) rather than at garbage collection."""
    query.drop()  # type: ignore[no-untyped-call]


def lock_state_dir(state_dir: Path) -> IO[str]:
    """The state directory's lock, held while the process runs: two fusion services on one
    directory interleaved their saves in one log (and, on one namespace, answered ``map/latest``
    by turns from two epochs). A second one stops at start-up, naming the first's process."""
    handle = open(state_dir / STATE_LOCK, "a+")  # noqa: SIM115 (held until the process ends)
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.seek(0)
        holder = handle.read().strip() or "another process"
        handle.close()
        startup_error(f"--state-dir {state_dir}: in use by another fusion service ({holder})")
    handle.seek(0)
    handle.truncate()
    handle.write(f"pid {os.getpid()}\n")
    handle.flush()
    return handle


def check_state_dir(state_dir: Path) -> None:
    """A state directory that is a file, or cannot be written, stops start-up with one line:
    never "serves, then dies at the first save"."""
    where = f"--state-dir {state_dir}"
    if state_dir.exists() and not state_dir.is_dir():
        startup_error(f"{where}: is not a directory")
    try:
        state_dir.mkdir(parents=True, exist_ok=True)
        probe = state_dir / f".write-probe.{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        startup_error(f"{where}: not writable: {error.strerror or error}")


def main(settings: FusionSettings) -> None:
    setup_logging("fusion", settings.log_level)
    stop = stop_on_signals()  # before loading the state: a stop during a long load is clean
    params = settings.grid_params()
    check_state_dir(settings.state_dir)
    lock = lock_state_dir(settings.state_dir)
    compile_rules()
    try:
        grid = load_grid(params, settings.state_dir, time.time_ns())
    except StateOfAnotherMap as error:
        startup_error(f"--state-dir {settings.state_dir}: {error}")
    state = FusionState(settings, grid)
    if grid.version:
        log.info(
            "map restored",
            extra={"version": grid.version, "cols": grid.window.cols, "rows": grid.window.rows},
        )
    inbox = Inbox(INBOX_MESSAGES, INBOX_LARGEST_MESSAGES * state.gate.max_bytes)
    # Its first act, before anyone sees this epoch: saving it, so no later start goes below it.
    writer = StateWriter(settings.state_dir, start=state.view.frozen)
    snapshots = SnapshotBuilder(lambda: state.view, settings.publish_interval_s)

    def answer_map(query: zenoh.Query) -> None:
        try:
            request = parse_map_query(query_parameters(query))
        except ValueError as error:
            query.reply_err(f"map/latest: {error}")
            return
        snapshot = snapshots.get(bool(request.layers))
        query.reply(
            query.key_expr, snapshot.encoded(request), encoding=CONTENT_TYPES[request.format]
        )

    def on_map_query(query: zenoh.Query) -> None:
        """A plain map/latest gets its ready bytes at once (a reply, nothing to compute or wait
        for); any other asks a worker."""
        payload = snapshots.plain() if query.parameters.is_empty() else None
        if payload is not None:
            query.reply(query.key_expr, payload, encoding=CONTENT_TYPES[DEFAULT_QUERY.format])
            finish(query)
        else:
            map_worker.offer(query)

    def answer_objects(query: zenoh.Query) -> None:
        fmt = query_parameters(query).get("format", "msgpack")
        if fmt not in OBJECT_FORMATS:
            query.reply_err(f"map/objects: format {fmt!r} not one of {', '.join(OBJECT_FORMATS)}")
            return
        header = state.view.objects
        query.reply(query.key_expr, objects_payload(header, fmt), encoding=OBJECT_FORMATS[fmt])

    def answer_health(query: zenoh.Query) -> None:
        answer = health_of(state.view, writer, inbox.dropped_counts())
        query.reply(query.key_expr, json.dumps(answer), encoding="application/json")

    def hand_over(kind: str, droppable: bool = True) -> Callable[[zenoh.Sample], None]:
        def callback(sample: zenoh.Sample) -> None:
            inbox.offer(
                Delivery(
                    kind,
                    str(sample.key_expr),
                    time.time_ns(),
                    sample.payload.to_bytes(),
                    sample.kind == zenoh.SampleKind.PUT,
                ),
                droppable,
            )

        return callback

    workers = [
        map_worker := QueryWorker(keys.MAP_LATEST, answer_map, MAP_QUERY_THREADS),
        QueryWorker(keys.MAP_HEALTH, answer_health),
        QueryWorker(keys.MAP_OBJECTS, answer_objects),
    ]
    with open_session(settings) as session:
        declared: list[Any] = [
            session.declare_subscriber(keys.TILES_ALL, hand_over("tile")),
            session.declare_subscriber(keys.OBJECTS_ALL, hand_over("detections")),
            session.liveliness().declare_subscriber(
                keys.DEPTH_ALIVE_ALL, hand_over("presence", droppable=False), history=True
            ),
            session.declare_queryable(keys.MAP_LATEST, on_map_query),
            *(session.declare_queryable(w.name, w.offer) for w in workers if w is not map_worker),
        ]
        # DROP, as map/updates: a query of map/objects always gives the current list.
        objects_publisher = session.declare_publisher(
            keys.MAP_OBJECTS,
            encoding=WIRE_ENCODING,
            congestion_control=zenoh.CongestionControl.DROP,
        )
        # DROP: a robot on a slow link must never stall fusion; a follower that misses an update sees
        # the version gap and fetches map/latest instead.
        updates = session.declare_publisher(
            keys.MAP_UPDATES,
            encoding=WIRE_ENCODING,
            congestion_control=zenoh.CongestionControl.DROP,
        )
        log.info(
            "started",
            extra={
                "resolution_m": settings.resolution_m,
                "state_dir": str(settings.state_dir),
                "epoch": grid.epoch_ns,
            },
        )
        run(
            settings,
            state,
            inbox,
            writer,
            stop,
            updates.put,
            objects_publisher.put,
            snapshots.changed,
        )
        for entity in declared:
            entity.undeclare()
    for worker in workers:
        worker.close()
    snapshots.close()
    state.fuse_captures(everything=True)
    state.publish()
    writer.hand_over(state.view.frozen, state.unsaved)
    writer.close()
    if writer.saved_version < grid.version:
        log.warning(
            "stopped with changes unsaved",
            extra={
                "version": grid.version,
                "saved_version": writer.saved_version,
                "save_errors": writer.errors,
            },
        )
    else:
        log.info("stopped", extra={"version": grid.version, "saved_version": writer.saved_version})
    lock.close()


def run(
    settings: FusionSettings,
    state: FusionState,
    inbox: Inbox,
    writer: StateWriter,
    stop: threading.Event,
    put_update: Callable[[bytes], Any],
    put_objects: Callable[[bytes], Any],
    published: Callable[[], None],
) -> None:
    """The owner's loop: messages in, then (when due) updates out, decay, a save hand-over."""
    now = time.monotonic()
    last = {"publish": 0.0, "decay": now, "save": now, "summary": now}
    while not stop.is_set():
        pending = state.grid.version != state.view.frozen.version
        wait_s = IDLE_WAIT_S
        if pending:
            wait_s = max(0.0, settings.publish_interval_s - (time.monotonic() - last["publish"]))
        for delivery in inbox.take(min(wait_s, IDLE_WAIT_S)):
            state.handle(delivery)
        state.fuse_captures()
        objects = state.refresh_objects()
        if objects is not None:
            put_objects(objects_payload(objects, "msgpack"))
        now = time.monotonic()
        if now - last["decay"] >= DECAY_PERIOD_S:
            state.grid.decay(time.time(), now - last["decay"])
            last["decay"] = now
        if (
            state.grid.version != state.view.frozen.version
            and now - last["publish"] >= settings.publish_interval_s
        ):
            payloads = state.publish()
            last["publish"] = now
            for payload in payloads:
                put_update(payload)
            published()
        else:
            state.update_view()  # counters (rejections, liveliness) for health
        if now - last["save"] >= settings.save_interval_s and state.unsaved:
            writer.hand_over(state.view.frozen, state.unsaved)
            state.unsaved = set()
            last["save"] = now
        if now - last["summary"] >= settings.summary_s:
            view = state.view
            log.info(
                "summary",
                extra={
                    "version": view.frozen.version,
                    "tiles": sum(view.accepted.values()),
                    "rejected": sum(view.rejected.values()),
                    "alive": ",".join(sorted(state.alive)),
                },
            )
            last["summary"] = now


def cli(argv: Sequence[str] | None = None) -> None:
    main(
        parse_settings(
            FusionSettings,
            argv,
            "overgrid fusion",
            "Fuses every pair's tiles into one occupancy map.",
        )
    )
