from pathlib import Path

import numpy as np

from common.lattice import Window
from services.fusion.grid import FusedGrid, GridParams
from services.fusion.persistence import CHUNK_LOG, StateWriter, load_grid, save_now

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


def test_state_of_another_resolution_is_set_aside(tmp_path: Path) -> None:
    save_now(_grid(), tmp_path)
    assert not load_grid(GridParams(resolution_m=0.1), tmp_path, 1).chunks


def test_state_beyond_new_bounds_keeps_what_lies_inside(tmp_path: Path) -> None:
    grid = _grid()
    save_now(grid, tmp_path)
    bounds = Window(0, 0, 40, 40)
    restored = load_grid(GridParams(bounds=bounds), tmp_path, 1)
    assert restored.window == bounds
    inside = bounds.slices_in(grid.window)
    np.testing.assert_array_equal(restored.layer("logodds"), grid.layer("logodds")[inside])
