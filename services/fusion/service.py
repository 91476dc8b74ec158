"""Fusion process: tiles in from every pair, one log-odds map out through queryables and updates.

Threads and who owns what:
- Zenoh's callbacks only hand messages over (``Inbox``; queries to a ``QueryWorker``) and never block.
- The main thread owns the map (``services.fusion.state.FusionState``): it decodes every message
  (one decode function per kind, ``services.fusion.intake``), integrates tiles, publishes
  ``map/updates`` and an immutable ``View`` (a frozen copy-on-write map plus counters) after each
  change.
- Query workers answer ``map/latest``, ``map/health`` and ``map/objects`` from the newest View:
  they never touch the grid, and every query gets a reply (an answer or an error).
- The state writer (``services.fusion.persistence``) saves the chunks changed since its last save.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import queue
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any

import zenoh

from common import keys
from common.codec import WIRE_ENCODING, encode
from common.lifecycle import stop_on_signals
from common.logs import RateLimitedLog, setup_logging
from common.messages import OBJECTS_KIND, ObjectsHeader
from common.settings import parse_settings, startup_error
from common.zenoh_session import open_session
from services.fusion.grid import compile_rules
from services.fusion.inbox import Delivery, Inbox
from services.fusion.persistence import StateOfAnotherMap, StateWriter, load_grid
from services.fusion.settings import FusionSettings
from services.fusion.snapshot import (
    CONTENT_TYPES,
    DEFAULT_QUERY,
    MapQueryError,
    SnapshotBuilder,
    parse_map_query,
)
from services.fusion.state import FusionState, health_of

log = logging.getLogger("fusion")
STATE_LOCK = ".lock"
"""The state directory's lock file (:func:`lock_state_dir`): it holds the owner's pid."""
IDLE_WAIT_S = 0.1
"""Longest the owner sleeps without a message: a stop, decay and saves are noticed this soon."""
DECAY_PERIOD_S = 1.0
STALL_S = 2.0
"""A pass of the owner's loop this long after the one before: the process did not run (stopped,
a paused VM, swapped out). Its cells are then old by that much with no camera at fault, so
decay waits ``decay_after_s`` for the pairs' next tiles (a 20 s stop turned the whole map
unknown at the first pass after it)."""
INBOX_MESSAGES = 16384
"""Messages the inbox holds: a burst of small bad tiles is counted by reason, not as overload."""
INBOX_LARGEST_MESSAGES = 4
"""Its byte budget, in largest messages allowed (``--max-message-mb``): a few big tiles may wait
while one is fused; a stream the map cannot keep up with is dropped, not held in memory."""
QUERY_BACKLOG = 256
"""Queries waiting for a worker; beyond it a query is answered "overloaded" at once."""
MAP_QUERY_THREADS = 2
"""map/latest replies are large (a whole map): while one is being sent, another is answered."""
OBJECT_FORMATS = {"msgpack": WIRE_ENCODING, "json": "application/json"}


def objects_payload(header: ObjectsHeader, fmt: str) -> bytes:
    """``map/objects`` as msgpack (the codec's envelope) or, for people, plain JSON."""
    if fmt == "json":
        return json.dumps(header.model_dump(mode="json")).encode()
    return encode(OBJECTS_KIND, header)


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
    """The state directory's lock, held until the process ends: two fusion services on one
    directory interleaved their saves in one log (and, on one namespace, answered ``map/latest``
    by turns from two epochs). A second one stops at start-up, naming the first's process."""
    handle = open(state_dir / STATE_LOCK, "a+")  # noqa: SIM115 (held until the process ends)
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
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
    _lock = lock_state_dir(settings.state_dir)  # held until the process ends (never closed)
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

    # Every answer on the queryable's own key, never the query's: a get of map/* took one reply of
    # the three, keyed map/*.
    def answer_map(query: zenoh.Query) -> None:
        try:
            request = parse_map_query(query_parameters(query))
        except ValueError as error:
            query.reply_err(f"map/latest: {error}")
            return
        snapshot = snapshots.get(bool(request.layers))
        query.reply(
            keys.MAP_LATEST, snapshot.encoded(request), encoding=CONTENT_TYPES[request.format]
        )

    def on_map_query(query: zenoh.Query) -> None:
        """A plain map/latest gets its ready bytes at once (a reply, nothing to compute or wait
        for); any other asks a worker: images for people their own, so a robot's region does
        not wait behind them (it waited 1–2.5 s behind 50 clients' PNGs)."""
        payload = snapshots.plain() if query.parameters.is_empty() else None
        if payload is not None:
            query.reply(keys.MAP_LATEST, payload, encoding=CONTENT_TYPES[DEFAULT_QUERY.format])
            finish(query)
        elif query_parameters(query).get("format", DEFAULT_QUERY.format) != DEFAULT_QUERY.format:
            image_worker.offer(query)
        else:
            map_worker.offer(query)

    def answer_objects(query: zenoh.Query) -> None:
        fmt = query_parameters(query).get("format", "msgpack")
        if fmt not in OBJECT_FORMATS:
            query.reply_err(f"map/objects: format {fmt!r} not one of {', '.join(OBJECT_FORMATS)}")
            return
        header = state.view.objects
        query.reply(keys.MAP_OBJECTS, objects_payload(header, fmt), encoding=OBJECT_FORMATS[fmt])

    def answer_health(query: zenoh.Query) -> None:
        answer = health_of(state.view, writer, inbox.dropped_counts())
        query.reply(keys.MAP_HEALTH, json.dumps(answer), encoding="application/json")

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
        image_worker := QueryWorker(keys.MAP_LATEST, answer_map),
        QueryWorker(keys.MAP_HEALTH, answer_health),
        QueryWorker(keys.MAP_OBJECTS, answer_objects),
    ]
    with open_session(settings, wait_for_router=True) as session:
        declared: list[Any] = [
            session.declare_subscriber(keys.TILES_ALL, hand_over("tile")),
            session.declare_subscriber(keys.OBJECTS_ALL, hand_over("detections")),
            session.liveliness().declare_subscriber(
                keys.DEPTH_ALIVE_ALL, hand_over("presence", droppable=False), history=True
            ),
            session.declare_queryable(keys.MAP_LATEST, on_map_query),
            *(
                session.declare_queryable(w.name, w.offer)
                for w in workers
                if w not in (map_worker, image_worker)
            ),
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
    last = {"publish": 0.0, "decay": now, "save": now, "summary": now, "pass": now}
    decay_resumes = now
    while not stop.is_set():
        pending = state.grid.version != state.view.frozen.version
        wait_s = IDLE_WAIT_S
        if pending:  # held for a capture's objects: until they come (they wake it) or the hold ends
            held_s = state.objects_hold_s(time.monotonic())
            since_s = time.monotonic() - last["publish"]
            wait_s = held_s if held_s > 0 else max(0.0, settings.publish_interval_s - since_s)
        for delivery in inbox.take(min(wait_s, IDLE_WAIT_S)):
            state.handle(delivery)
        state.fuse_captures()
        objects = state.refresh_objects()
        if objects is not None:
            put_objects(objects_payload(objects, "msgpack"))
        now = time.monotonic()
        if now - last["pass"] > STALL_S:
            log.warning(
                "fusion did not run for a while (stopped, a paused VM, swapped out?): decay "
                "waits for the pairs' next tiles",
                extra={"stalled_s": round(now - last["pass"], 1)},
            )
            decay_resumes = now + state.grid.params.decay_after_s
        last["pass"] = now
        if now < decay_resumes:
            last["decay"] = now
        elif now - last["decay"] >= DECAY_PERIOD_S:
            state.grid.decay(time.time(), now - last["decay"])
            last["decay"] = now
        if (
            state.grid.version != state.view.frozen.version
            and now - last["publish"] >= settings.publish_interval_s
            and state.objects_hold_s(now) == 0  # a capture goes out with its objects
        ):
            state.say_if_objects_overdue()
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
