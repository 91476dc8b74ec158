import numpy as np

from common.lattice import Window
from services.fusion.grid import FusedGrid, GridParams
from services.fusion.persistence import STATE_FILE, load_grid, save_grid


def _grid() -> FusedGrid:
    grid = FusedGrid(GridParams())
    rng = np.random.default_rng(0)
    for k in range(5):
        w = Window(int(rng.integers(-50, 50)), int(rng.integers(-50, 50)), 30, 20)
        grid.integrate(
            w,
            rng.normal(size=w.shape).astype(np.float32),
            rng.random(w.shape).astype(np.float32),
            rng.integers(0, 4, size=w.shape).astype(np.uint16),
            10**9 * (k + 1),
        )
    return grid


def test_restart_restores_the_map_bit_for_bit(tmp_path) -> None:
    grid = _grid()
    save_grid(grid, tmp_path)
    restored = load_grid(GridParams(), tmp_path)
    assert restored is not None
    assert (
        restored.window == grid.window
        and restored.version == grid.version
        and restored.stamp_ns == grid.stamp_ns
    )
    for name in ("logodds", "height_m", "known", "last_seen_s"):
        np.testing.assert_array_equal(getattr(restored, name), getattr(grid, name))
    assert not list(tmp_path.glob(".*tmp"))  # the temp file was renamed into place


def test_corrupt_state_is_set_aside_not_fatal(tmp_path) -> None:
    (tmp_path / STATE_FILE).write_bytes(b"not a numpy file")
    assert load_grid(GridParams(), tmp_path) is None
    assert not (tmp_path / STATE_FILE).exists()
    assert len(list(tmp_path.glob(f"{STATE_FILE}.corrupt-*"))) == 1


def test_state_of_another_resolution_is_set_aside(tmp_path) -> None:
    save_grid(_grid(), tmp_path)
    assert load_grid(GridParams(resolution_m=0.1), tmp_path) is None
