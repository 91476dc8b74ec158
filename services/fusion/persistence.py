"""The map survives a restart, and a crash loses at most one save interval.

On disk: one append-only log of records, each the chunks changed since the previous record
(``CHUNK_LOG``). Why a log and not a file per chunk or one whole-map file: a save then costs the
chunks that changed (not the map's size) and one ``fsync`` (not one per chunk file), and a record is
atomic by its checksum — a crash mid-write leaves a torn last record, which loading drops (and cuts
off the file, so later records follow good ones), keeping everything before it. When the log has
grown to several times the map (and at the first save after a start), the writer compacts it:
every chunk, written to a temporary file and renamed over the log (atomic). A compaction of a large
map takes seconds, so between its records the writer goes on appending the newest changes to the
live log: a crash during a compaction loses no more than one at any other time; the changes made
meanwhile are written into the new log too before it replaces the old.

Each record also carries the map's epoch (the start time of the fusion that wrote it): a start takes
max(saved epoch + 1, now) and saves it at once, so the (epoch, counter) version never goes back, even
across a clock step back.

The writer is a thread of its own fed with :class:`FrozenMap` copies, so no save ever runs on the
tile intake's path.
"""

from __future__ import annotations

import contextlib
import logging
import os
import struct
import threading
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import numpy.typing as npt

from common.logs import RateLimitedLog
from services.fusion.grid import (
    CHUNK_CELLS,
    EVIDENCE_LAYERS,
    LAYER_FILLS,
    ChunkKey,
    FrozenMap,
    FusedGrid,
    GridParams,
)
from services.fusion.intake import HEIGHT_RANGE_M

log = logging.getLogger("fusion.state")
CHUNK_LOG = "map_chunks.log"
RECORD_MAGIC = b"OGC1"
RECORD_HEAD = struct.Struct("<4sII")
"""magic, payload length, CRC-32 of the payload."""
COMPACT_WHEN_LOG_IS = 4.0
"""Compact once the log is this many times its last compacted size (the map's, roughly)."""
COMPACT_MIN_BYTES = 8 * 1024 * 1024
ZLIB_LEVEL = 1
COMPRESS_WHEN_REPEATS = 0.25
"""Deflate a chunk's layer when at least this share of its cells repeat their neighbour's value;
store it otherwise (see ``_compressible``)."""
WRITER_NICENESS = 10
"""Niceness of the writer thread: compressing a whole map (the first save after a start, a
compaction) takes seconds of CPU, which must not come out of the tile intake's share."""
SAVE_FAILURE_LOG_S = 30.0
"""At most one line per this many seconds while saves keep failing (with the count)."""
RECORD_CHUNKS = 64
"""Chunks per record (about 1 MB of layers)."""
LAYER_DTYPES = {name: np.dtype(dtype) for name, dtype, _ in LAYER_FILLS}


class StateUnusable(ValueError):
    """A state log that cannot be read at all (its first record is bad), or of another map."""


class StateOfAnotherMap(StateUnusable):
    """A good log of a map of another resolution or chunk size: not this service's to set aside
    (a restart at the old resolution would find it gone), so start-up stops instead."""


def encode_records(frozen: FrozenMap, keys: set[ChunkKey], full: bool) -> Iterator[bytes]:
    """Log records of the chunks ``keys``, at most RECORD_CHUNKS each: each carries the map's
    counters and its chunks' evidence layers; with ``full``, the first says "forget the rest".
    Small records keep each step of a whole-map save short, so the thread that owns the map is
    never held up for long (the GIL passes between them)."""
    present = sorted(key for key in keys if key in frozen.chunks)
    for start in range(0, max(len(present), 1), RECORD_CHUNKS):
        chunks = [
            [key[0], key[1], {n: _packed(frozen.chunks[key].layers[n]) for n in EVIDENCE_LAYERS}]
            for key in present[start : start + RECORD_CHUNKS]
        ]
        payload: bytes = msgpack.packb(
            {
                "resolution_m": frozen.resolution_m,
                "chunk_cells": CHUNK_CELLS,
                "version": frozen.version,
                "stamp_ns": frozen.stamp_ns,
                "epoch_ns": frozen.epoch_ns,
                "full": full and start == 0,
                "chunks": chunks,
            },
            use_bin_type=True,
        )
        yield RECORD_HEAD.pack(RECORD_MAGIC, len(payload), zlib.crc32(payload)) + payload


def _packed(layer: npt.NDArray[Any]) -> bytes:
    """A layer as a zlib stream: deflated when that pays, stored (level 0) when not; either
    reads back the same way."""
    contiguous = np.ascontiguousarray(layer)
    return zlib.compress(contiguous.data, ZLIB_LEVEL if _compressible(contiguous) else 0)


def _compressible(layer: npt.NDArray[Any]) -> bool:
    """Whether deflating a layer pays: one of repeated values (free floor at the clamp, NaN
    heights of unseen cells, a tile's one stamp) shrinks many-fold, a noisy one by a few percent
    for about 0.6 ms of CPU per chunk — on a 2-core box the writer's whole-map saves then took
    seconds out of the tile intake's share (and contended for the GIL). Neighbouring equal bit
    patterns (NaN equals NaN) are a cheap proxy for what deflate finds."""
    if layer.dtype.itemsize == 1:
        return True
    bits = layer.view(f"u{layer.dtype.itemsize}").ravel()
    return int(np.count_nonzero(bits[1:] == bits[:-1])) >= COMPRESS_WHEN_REPEATS * bits.size


@dataclass
class SavedState:
    version: int = 0
    stamp_ns: int = 0
    epoch_ns: int = 0
    """The newest epoch any record was written in."""
    chunks: dict[ChunkKey, dict[str, npt.NDArray[Any]]] = field(default_factory=dict)
    records: int = 0
    torn: bool = False
    """The log ended in a record cut short (a crash while writing it): dropped."""
    good_bytes: int = 0
    """Length of the log's whole records: where a torn tail starts."""


def read_log(path: Path, resolution_m: float) -> SavedState:
    """Every whole record of the log, applied in order; StateUnusable if not even the first is."""
    data = path.read_bytes()
    state = SavedState()
    offset = 0
    while offset < len(data):
        record = _record_at(data, offset)
        if record is None:
            if state.records == 0:
                raise StateUnusable(f"{path}: not a map state log (first record unreadable)")
            state.torn = True
            break
        payload, offset = record
        _apply(state, payload, resolution_m, path)
        state.good_bytes = offset
    return state


def _record_at(data: bytes, offset: int) -> tuple[Any, int] | None:
    if offset + RECORD_HEAD.size > len(data):
        return None
    magic, length, crc = RECORD_HEAD.unpack_from(data, offset)
    start = offset + RECORD_HEAD.size
    payload = data[start : start + length]
    if magic != RECORD_MAGIC or len(payload) != length or zlib.crc32(payload) != crc:
        return None
    try:
        return msgpack.unpackb(payload, raw=False, strict_map_key=False), start + length
    except Exception:  # a checksum match on bad msgpack: treat it as torn
        return None


def _apply(state: SavedState, record: Any, resolution_m: float, path: Path) -> None:
    try:
        if float(record["resolution_m"]) != resolution_m:
            raise StateOfAnotherMap(
                f"{path.parent} holds a map of {record['resolution_m']} m cells, this service's "
                f"are {resolution_m} m: run with that resolution, or another --state-dir"
            )
        if record["chunk_cells"] != CHUNK_CELLS:
            raise StateOfAnotherMap(
                f"{path}: chunks of {record['chunk_cells']} cells, not {CHUNK_CELLS}"
            )
        if record["full"]:
            state.chunks.clear()
        shape = (CHUNK_CELLS, CHUNK_CELLS)
        for ci, cj, layers in record["chunks"]:
            chunk = {
                name: np.frombuffer(zlib.decompress(layers[name]), LAYER_DTYPES[name])
                .reshape(shape)
                .copy()
                for name in EVIDENCE_LAYERS
            }
            if not np.isfinite(chunk["logodds"]).all():
                raise StateUnusable(f"{path}: chunk ({ci}, {cj}) holds non-finite log-odds")
            # Tops no tile may bring now (a map saved before tiles' heights were checked, 3e38 m):
            # unknown, not kept by the max rule for as long as the cell is observed.
            lowest_m, highest_m = HEIGHT_RANGE_M
            height = chunk["height_m"]
            height[(height < lowest_m) | (height > highest_m)] = np.nan
            state.chunks[(int(ci), int(cj))] = chunk
        state.version = _counter(record["version"], "version", path)
        state.stamp_ns = _counter(record["stamp_ns"], "stamp_ns", path)
        state.epoch_ns = max(state.epoch_ns, _counter(record.get("epoch_ns", 0), "epoch_ns", path))
        state.records += 1
    except StateUnusable:
        raise
    except Exception as error:  # a well-formed record of the wrong content
        raise StateUnusable(f"{path}: bad record: {type(error).__name__}: {error}") from None


def _counter(value: Any, name: str, path: Path) -> int:
    """A saved version or time: an integer the messages can carry (signed 64 bits, not negative);
    one beyond them let fusion start and then fail on its first message."""
    number = int(value)
    if not 0 <= number < 2**63:
        raise StateUnusable(f"{path}: {name} {number} is out of range")
    return number


def load_grid(params: GridParams, state_dir: Path, epoch_ns: int) -> FusedGrid:
    """The saved map with a new epoch (``epoch_ns``, or one past the saved epoch if the clock is
    behind it), or an empty one. A log that cannot be used is set aside for inspection (renamed
    ``….corrupt-<time>``) with an error logged, and the map starts empty; the state directory was
    checked writable before (see the service), so the rename can be made. A good log of another
    resolution raises :class:`StateOfAnotherMap`. Chunks beyond today's limits (bounds, extent,
    cell limit) are left out, not the whole state."""
    path = state_dir / CHUNK_LOG
    if not path.exists():
        return FusedGrid(params, epoch_ns)
    try:
        state = read_log(path, params.resolution_m)
        grid = FusedGrid(params, max(epoch_ns, state.epoch_ns + 1))
        dropped = grid.restore(state.chunks)
        if state.torn:  # cut it off: records appended after it must follow a good one
            os.truncate(path, state.good_bytes)
    except StateOfAnotherMap:
        raise
    except (StateUnusable, ValueError, OSError) as error:
        aside = path.with_name(f"{CHUNK_LOG}.corrupt-{int(time.time())}")
        path.rename(aside)
        log.error(
            "state unusable, set aside", extra={"path": str(aside), "error": str(error)[:200]}
        )
        return FusedGrid(params, max(epoch_ns, _epoch_of(aside, params.resolution_m) + 1))
    if state.torn:
        log.warning("state log ended in a torn record: dropped", extra={"records": state.records})
    if dropped:
        log.warning(
            "saved chunks beyond the map's limits left out",
            extra={"dropped": dropped, "kept": len(grid.chunks)},
        )
    grid.version, grid.stamp_ns = state.version, state.stamp_ns
    return grid


def _epoch_of(path: Path, resolution_m: float) -> int:
    """The epoch a log set aside was written in, if it can be read at all (else 0)."""
    try:
        return read_log(path, resolution_m).epoch_ns
    except (StateUnusable, OSError):
        return 0


class StateWriter:
    """The thread that writes saves. The map's owner hands it frozen maps and the chunks changed
    since its last hand-over; when it is still busy, hand-overs merge (the newest map holds every
    chunk's newest copy), so the owner never waits. ``start``: the map at start, whose epoch (and
    counters) is appended at once, on the caller's thread, before the service answers anyone."""

    def __init__(self, state_dir: Path, start: FrozenMap | None = None) -> None:
        self.path = state_dir / CHUNK_LOG
        self._wake = threading.Condition()
        self._frozen: FrozenMap | None = None
        self._keys: set[ChunkKey] = set()
        self._closing = False
        self._compacted_bytes = 0
        self._needs_full = True
        """The first save after a start rewrites the log (starts compact)."""
        self.saved_version = -1
        self.saved_s = 0.0
        self.errors = 0
        self._failures = RateLimitedLog(log, SAVE_FAILURE_LOG_S)
        if start is not None:
            try:
                self._append(start, set())
            except Exception as error:
                self._failed(error)
        self._thread = threading.Thread(target=self._run, name="fusion-state", daemon=True)
        self._thread.start()

    def hand_over(self, frozen: FrozenMap, changed: set[ChunkKey]) -> None:
        with self._wake:
            self._frozen = frozen
            self._keys |= changed
            self._wake.notify()

    def close(self, timeout_s: float = 10.0) -> None:
        """Write what was handed over, then stop."""
        with self._wake:
            self._closing = True
            self._wake.notify()
        self._thread.join(timeout_s)

    def _run(self) -> None:
        # Linux nices threads one by one: the map's owner wins the CPU when both want it
        # (elsewhere the writer keeps the process's priority; saves stay off the intake path).
        with contextlib.suppress(AttributeError, OSError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WRITER_NICENESS)
        while True:
            with self._wake:
                while self._frozen is None and not self._closing:
                    self._wake.wait()
                closing = self._closing
            taken = self._take()
            if taken is not None:
                self._save(*taken)
            if closing and taken is None:
                return

    def _take(self) -> tuple[FrozenMap, set[ChunkKey]] | None:
        """What was handed over since the last take, if anything."""
        with self._wake:
            if self._frozen is None:
                return None
            taken = (self._frozen, self._keys)
            self._frozen, self._keys = None, set()
            return taken

    def _save(self, frozen: FrozenMap, keys: set[ChunkKey]) -> None:
        """One save; whatever fails (disk, a bug) is logged and counted, and its chunks are
        tried again with the next hand-over: the writer, and fusion, go on."""
        try:
            if self._needs_full or self._log_bytes() > max(
                COMPACT_MIN_BYTES, COMPACT_WHEN_LOG_IS * self._compacted_bytes
            ):
                self._compact(frozen, keys)
            else:
                self._append(frozen, keys)
                self._saved(frozen)
        except Exception as error:
            self._retry(keys)
            self._failed(error)

    def _append(self, frozen: FrozenMap, keys: set[ChunkKey]) -> None:
        """Appends ``keys``' records; one that fails (a full disk) is cut off again, or, if even
        that fails, nothing more is appended until a compaction rewrites the log: a record written
        after a torn one is never read (loading stops at the torn one), yet counted as saved."""
        start = self._log_bytes()
        try:
            with open(self.path, "ab") as handle:
                for record in encode_records(frozen, keys, full=False):
                    handle.write(record)
                handle.flush()
                os.fsync(handle.fileno())
        except BaseException:
            try:
                os.truncate(self.path, start)
            except OSError:
                self._needs_full = True
            raise

    def _compact(self, frozen: FrozenMap, keys: set[ChunkKey]) -> None:
        """Rewrite the log as ``frozen``'s chunks; between records, what is handed over
        meanwhile is appended to the live log (so the crash-loss bound holds during a compaction
        of any size) and, at the end, written into the new log as well."""
        temp = self.path.with_name(f".{CHUNK_LOG}.{os.getpid()}.tmp")
        since: set[ChunkKey] = set()
        newest = frozen
        try:
            with open(temp, "wb") as handle:
                for record in encode_records(frozen, set(frozen.chunks), full=True):
                    handle.write(record)
                    taken = self._take()
                    if taken is not None:
                        newest, since = taken[0], since | taken[1]
                        try:
                            self._append(*taken)
                            self._saved(newest)
                        except Exception as error:  # the new log will hold them; count it
                            self._failed(error)
                for record in encode_records(newest, since, full=False) if since else ():
                    handle.write(record)
                handle.flush()
                os.fsync(handle.fileno())
                size = handle.tell()
        except BaseException:
            self._retry(since)
            with contextlib.suppress(OSError):
                temp.unlink()
            raise
        os.replace(temp, self.path)
        directory = os.open(self.path.parent, os.O_RDONLY)
        try:
            os.fsync(directory)  # the rename itself survives a power cut
        finally:
            os.close(directory)
        self._compacted_bytes = size
        self._needs_full = False
        self._saved(newest)

    def _saved(self, frozen: FrozenMap) -> None:
        self.saved_version = max(self.saved_version, frozen.version)
        self.saved_s = time.monotonic()

    def _retry(self, keys: set[ChunkKey]) -> None:
        with self._wake:  # these chunks again with the next hand-over
            self._keys |= keys

    def _failed(self, error: Exception) -> None:
        self.errors += 1
        self._failures.warning(  # a full disk fails every save: one line per period
            "save",
            "state save failed",
            path=str(self.path),
            error=f"{type(error).__name__}: {error}"[:200],
            errors=self.errors,
        )

    def _log_bytes(self) -> int:
        try:
            return self.path.stat().st_size
        except FileNotFoundError:
            return 0


def save_now(grid: FusedGrid, state_dir: Path) -> Path:
    """Write the whole map at once (tools and tests; the service uses :class:`StateWriter`)."""
    writer = StateWriter(state_dir)
    frozen, _ = grid.freeze()
    writer.hand_over(frozen, set(frozen.chunks))
    writer.close()
    return writer.path
