import time
import zlib
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from common.lattice import Window
from services.fusion import persistence
from services.fusion.grid import Chunk, FusedGrid, GridParams
from services.fusion.persistence import (
    CHUNK_LOG,
    StateOfAnotherMap,
    StateWriter,
    load_grid,
    read_log,
    save_now,
)
from services.fusion.settings import FusionSettings
from services.fusion.state import FusionState

LAYERS = ("logodds", "height_m", "known", "last_seen_s", "occupancy")


def _grid(count: int = 5, seed: int = 0) -> FusedGrid:
    grid = FusedGrid(GridParams())
    rng = np.random.default_rng(seed)
    for k in range(count):
        w = Window(int(rng.integers(-50, 50)), int(rng.integers(-50, 50)), 30, 20)
        grid.integrate(
            w,
            rng.normal(size=w.shape).astype(np.float32),
            rng.random(w.shape).astype(np.float32),
            rng.integers(0, 4, size=w.shape).astype(np.uint16),
            10**9 * (k + 1),
        )
    return grid


def _same(restored: FusedGrid, grid: FusedGrid) -> None:
    assert (restored.window, restored.version, restored.stamp_ns) == (
        grid.window,
        grid.version,
        grid.stamp_ns,
    )
    for name in LAYERS:
        np.testing.assert_array_equal(restored.layer(name), grid.layer(name))


def test_restart_restores_the_map_bit_for_bit_with_a_new_epoch(tmp_path: Path) -> None:
    grid = _grid()
    save_now(grid, tmp_path)
    restored = load_grid(GridParams(), tmp_path, epoch_ns=42)
    _same(restored, grid)
    assert restored.epoch_ns == 42
    assert not list(tmp_path.glob(".*tmp"))  # the compacted log was renamed into place


def test_saves_append_the_changed_chunks_and_a_torn_tail_is_dropped(tmp_path: Path) -> None:
    grid = _grid()
    big = Window(-256, -256, 512, 512)  # 64 chunks
    grid.integrate(
        big,
        np.full(big.shape, -0.5, np.float32),
        np.zeros(big.shape, np.float32),
        np.ones(big.shape, np.uint16),
        10**9 * 9,
    )
    writer = StateWriter(tmp_path)
    frozen, changed = grid.freeze()
    writer.hand_over(frozen, changed)  # the first save after a start: the whole map
    writer.close()
    size_full = (tmp_path / CHUNK_LOG).stat().st_size
    writer = StateWriter(tmp_path)
    writer._needs_full = False  # as a running writer, past its first save
    grid.integrate(
        Window(0, 0, 4, 4),
        np.full((4, 4), 1.0, np.float32),
        np.zeros((4, 4), np.float32),
        np.ones((4, 4), np.uint16),
        10**10,
    )
    frozen, changed = grid.freeze()
    assert changed == {(0, 0)}
    writer.hand_over(frozen, changed)
    writer.close()
    appended = (tmp_path / CHUNK_LOG).stat().st_size - size_full
    assert 0 < appended < size_full / 5  # one chunk of 70, not the map
    _same(load_grid(GridParams(), tmp_path, 1), grid)
    # A crash in the middle of the next record: everything before it survives.
    with open(tmp_path / CHUNK_LOG, "ab") as handle:
        handle.write(b"OGC1\x00\x10\x00\x00partial")
    _same(load_grid(GridParams(), tmp_path, 1), grid)


def test_corrupt_state_is_set_aside_not_fatal(tmp_path: Path) -> None:
    (tmp_path / CHUNK_LOG).write_bytes(b"not a state log")
    grid = load_grid(GridParams(), tmp_path, 1)
    assert grid.version == 0 and not grid.chunks
    assert not (tmp_path / CHUNK_LOG).exists()
    assert len(list(tmp_path.glob(f"{CHUNK_LOG}.corrupt-*"))) == 1


def _rewritten(path: Path, change: Any) -> None:
    """The log's one record with ``change`` applied to its decoded payload, checksum recomputed:
    a well-formed record of bad content."""
    data = path.read_bytes()
    _, length, _ = persistence.RECORD_HEAD.unpack_from(data)
    payload = msgpack.unpackb(data[persistence.RECORD_HEAD.size :], raw=False, strict_map_key=False)
    assert len(data) == persistence.RECORD_HEAD.size + length  # one record
    change(payload)
    packed = msgpack.packb(payload, use_bin_type=True)
    head = persistence.RECORD_HEAD.pack(persistence.RECORD_MAGIC, len(packed), zlib.crc32(packed))
    path.write_bytes(head + packed)


def _nan_logodds(payload: dict[str, Any]) -> None:
    _, _, layers = payload["chunks"][0]
    logodds = np.frombuffer(zlib.decompress(layers["logodds"]), np.float32).copy()
    logodds[7] = np.nan
    layers["logodds"] = zlib.compress(logodds.tobytes())


@pytest.mark.parametrize(
    "change",
    [
        _nan_logodds,
        lambda payload: payload.update(version=2**64 - 1),
        lambda payload: payload.update(epoch_ns=2**63),
        lambda payload: payload.update(stamp_ns=-1),
    ],
    ids=["nan-logodds", "version", "epoch", "stamp"],
)
def test_a_record_of_bad_values_is_set_aside_like_a_corrupt_one(
    tmp_path: Path, change: Any
) -> None:
    """Its checksum holds, its values do not: fusion failed at start-up (NaN log-odds) or on
    its first message (a version no message can carry) instead of starting empty."""
    save_now(_grid(count=1), tmp_path)
    _rewritten(tmp_path / CHUNK_LOG, change)
    grid = load_grid(GridParams(), tmp_path, 1)
    assert grid.version == 0 and not grid.chunks
    assert len(list(tmp_path.glob(f"{CHUNK_LOG}.corrupt-*"))) == 1


def test_state_of_another_resolution_stops_start_up_and_stays(tmp_path: Path) -> None:
    """It was set aside as corrupt and the service started empty: a restart at the old
    resolution then found the map gone."""
    grid = _grid()
    save_now(grid, tmp_path)
    with pytest.raises(StateOfAnotherMap, match=r"holds a map of 0\.05 m cells.*0\.1 m"):
        load_grid(GridParams(resolution_m=0.1), tmp_path, 1)
    _same(load_grid(GridParams(), tmp_path, 1), grid)


def test_a_save_that_fails_midway_is_cut_off_and_the_next_rewrites_the_log(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A full disk tore one appended record; the writer appended after it and reported those
    saves, which loading never reached (it stops at the torn record): a restart lost them."""
    grid = _grid()
    save_now(grid, tmp_path)
    writer = StateWriter(tmp_path)
    writer._needs_full = False  # as a running writer, past its first save
    real = persistence.encode_records

    def disk_full(frozen: Any, keys: Any, full: bool) -> Any:
        for record in real(frozen, keys, full):
            yield record[: len(record) // 2]
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(persistence, "encode_records", disk_full)
    _fuse(grid, Window(0, 0, 4, 4), 1.0, 10**10)
    writer.hand_over(*grid.freeze())
    deadline = time.monotonic() + 10
    while writer.errors == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert writer.errors == 1 and writer.saved_version < grid.version
    assert not read_log(tmp_path / CHUNK_LOG, 0.05).torn  # the half record is cut off
    monkeypatch.setattr(persistence, "encode_records", real)  # the disk has room again
    _fuse(grid, Window(300, 300, 4, 4), 2.0, 2 * 10**10)
    writer.hand_over(*grid.freeze())
    writer.close()
    assert writer.saved_version == grid.version
    _same(load_grid(GridParams(), tmp_path, 1), grid)


def test_state_beyond_new_bounds_keeps_what_lies_inside(tmp_path: Path) -> None:
    grid = _grid()
    save_now(grid, tmp_path)
    bounds = Window(0, 0, 40, 40)
    restored = load_grid(GridParams(bounds=bounds), tmp_path, 1)
    assert restored.window == bounds
    inside = bounds.slices_in(grid.window)
    np.testing.assert_array_equal(restored.layer("logodds"), grid.layer("logodds")[inside])


def _fuse(grid: FusedGrid, window: Window, value: float, stamp_ns: int) -> None:
    grid.integrate(
        window,
        np.full(window.shape, value, np.float32),
        np.zeros(window.shape, np.float32),
        np.ones(window.shape, np.uint16),
        stamp_ns,
    )


def test_the_epoch_is_saved_and_a_start_never_goes_below_it(tmp_path: Path) -> None:
    """A clock stepped back at a restart made the new epoch lower than the last: followers then
    took the new map for an old one."""
    grid = FusedGrid(GridParams(), epoch_ns=5_000)
    frozen, _ = grid.freeze()
    StateWriter(tmp_path, start=frozen).close()  # a start with nothing to save: the epoch is
    assert load_grid(GridParams(), tmp_path, epoch_ns=4_000).epoch_ns == 5_001
    assert load_grid(GridParams(), tmp_path, epoch_ns=9_000).epoch_ns == 9_000


def test_a_torn_tail_is_cut_off_so_later_appends_are_read(tmp_path: Path) -> None:
    grid = _grid()
    save_now(grid, tmp_path)
    with open(tmp_path / CHUNK_LOG, "ab") as handle:
        handle.write(b"OGC1\x00\x10\x00\x00partial")
    restored = load_grid(GridParams(), tmp_path, 1)
    writer = StateWriter(tmp_path, start=restored.freeze()[0])
    writer._needs_full = False  # appends, as a running writer past its first save
    _fuse(restored, Window(500, 500, 4, 4), 1.0, 10**11)
    writer.hand_over(*restored.freeze())
    writer.close()
    again = load_grid(GridParams(), tmp_path, 2)
    _same(again, restored)
    assert not read_log(tmp_path / CHUNK_LOG, 0.05).torn


def test_a_compaction_keeps_appending_what_is_handed_over_meanwhile(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Compacting a large map takes seconds: the changes of those seconds go to the live log
    between its records (a crash then loses no more than at any other time), and into the new
    log before it replaces the old."""
    grid = FusedGrid(GridParams())
    _fuse(grid, Window(0, 0, 64 * 10, 64 * 8), -0.5, 10**9)  # 80 chunks: two records
    save_now(grid, tmp_path)
    first, _ = grid.freeze()
    _fuse(grid, Window(2000, 2000, 4, 4), 2.0, 2 * 10**9)
    later, changed = grid.freeze()
    writer = StateWriter(tmp_path)  # its first save compacts
    live_during_compaction: list[set[tuple[int, int]]] = []
    real = persistence.encode_records

    def watched(frozen: Any, keys: Any, full: bool) -> Any:
        for n, record in enumerate(real(frozen, keys, full)):
            if full and n == 0:  # handed over while the compaction's first record is made
                writer.hand_over(later, changed)
            if full and n == 1:  # the compaction goes on: is that hand-over saved already?
                live_during_compaction.append(set(read_log(writer.path, 0.05).chunks))
            yield record

    monkeypatch.setattr(persistence, "encode_records", watched)
    writer.hand_over(first, set(first.chunks))
    writer.close()
    assert changed <= live_during_compaction[0]
    assert writer.saved_version == later.version
    _same(load_grid(GridParams(), tmp_path, 1), grid)


def test_a_saved_map_with_a_stray_far_chunk_keeps_the_real_map(tmp_path: Path) -> None:
    """A 1×1 tile at cell 2**62, saved by an older fusion: the saved map then exceeded
    --max-cells and the whole state was set aside as corrupt."""
    grid = _grid()
    stray = (2**56, 2**56)
    grid.chunks[stray] = Chunk()
    grid.chunks[stray].known[0, 0] = True
    grid.changed.add(stray)
    save_now(grid, tmp_path)
    restored = load_grid(GridParams(), tmp_path, 1)
    assert stray not in restored.chunks and set(restored.chunks) == set(grid.chunks) - {stray}
    for name in LAYERS:
        np.testing.assert_array_equal(restored.layer(name), grid.window_of(name, restored.window))
    assert not list(tmp_path.glob(f"{CHUNK_LOG}.corrupt-*"))


def test_layers_are_deflated_only_where_it_pays() -> None:
    """Noise barely shrinks, for most of a save's CPU; repeated values (the clamp, NaN heights,
    a tile's stamp) shrink many-fold. Both read back bit for bit (``_same`` above)."""
    noise = np.random.default_rng(0).uniform(-1, 1, (64, 64)).astype(np.float32)
    floor = np.full((64, 64), -1.5, np.float32)
    assert len(persistence._packed(noise)) > noise.nbytes  # stored
    assert len(persistence._packed(floor)) < floor.nbytes / 50  # deflated


def test_a_saved_top_no_tile_may_bring_now_is_read_back_unknown(tmp_path: Path) -> None:
    """A map saved before tiles' heights were checked served a top of 3e38 m after the upgrade,
    and the max rule kept it as long as the cell was observed."""
    grid = FusedGrid(GridParams())
    window = Window(0, 0, 3, 1)
    heights = np.array([[3e38, 1.2, -3e38]], np.float32)
    grid.integrate(
        window, np.ones(window.shape, np.float32), heights, np.ones((1, 3), np.uint16), 1
    )
    save_now(grid, tmp_path)
    restored = load_grid(GridParams(), tmp_path, epoch_ns=1).window_of("height_m", window)
    assert np.isnan(restored[0, 0]) and restored[0, 1] == pytest.approx(1.2)
    assert np.isnan(restored[0, 2])


def test_a_state_saved_ahead_of_this_boxs_clock_decays_from_now(tmp_path: Path) -> None:
    """Restored on a box whose clock is an hour behind the one that saved it, an obstacle stayed
    at 92 through every decay pass for that hour, and the map's stamp claimed a capture an hour
    in the future."""
    hour_ns = 3600 * 10**9
    now_ns = time.time_ns()
    grid = FusedGrid(GridParams())
    _fuse(grid, Window(0, 0, 4, 4), 2.0, now_ns + hour_ns)
    save_now(grid, tmp_path)
    state = FusionState(FusionSettings(), load_grid(GridParams(), tmp_path, epoch_ns=1))
    restored = state.grid
    assert abs(restored.stamp_ns - now_ns) < 10**9
    assert abs(float(restored.layer("last_seen_s")[0, 0]) - now_ns / 1e9) < 1.0
    later_s = now_ns / 1e9 + restored.params.decay_after_s + 30.0
    for step in range(30):
        restored.decay(later_s + step, 1.0)
    assert restored.layer("occupancy")[0, 0] == -1  # decayed to unknown, as on one clock
