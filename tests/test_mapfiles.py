import warnings
from pathlib import Path

import numpy as np
import pytest

from common.mapfiles import (
    PGM_FREE,
    PGM_OCCUPIED,
    PGM_UNKNOWN,
    free_cells,
    occupied_cells,
    picture,
    read_map_server,
    write_map,
)
from common.occupancy_map import UNKNOWN, OccupancyMap, occupancy_from_logodds
from common.png import decode_png


def _map() -> OccupancyMap:
    occupancy = np.full((4, 6), UNKNOWN, np.int8)
    occupancy[0, 0] = 100  # origin cell (lowest y) occupied
    occupancy[0, 1] = 0
    occupancy[3, 5] = 10  # top-right free
    occupancy[2, 2] = 50  # in between
    return OccupancyMap(
        occupancy=occupancy, resolution_m=0.05, i0=-20, j0=40, version=3, stamp_ns=5
    )


def test_nav2_pgm_yaml_round_trip(tmp_path: Path) -> None:
    paths = write_map(_map(), tmp_path / "map.yaml")
    assert [p.name for p in paths] == ["map.yaml", "map.pgm"]
    meta, image = read_map_server(tmp_path / "map.yaml")
    assert meta == {
        "image": "map.pgm",
        "mode": "trinary",
        "resolution": 0.05,
        "origin": [-1.0, 2.0, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    assert image.shape == (4, 6)
    # Rows flipped: the PGM's bottom row is the map's origin row.
    assert image[3, 0] == PGM_OCCUPIED and image[3, 1] == PGM_FREE
    assert image[0, 5] == PGM_FREE
    assert image[1, 2] == PGM_UNKNOWN  # 50 is neither free nor occupied: trinary unknown
    assert (image == PGM_UNKNOWN).sum() == 21


def test_png_picture_is_y_up_and_readable(tmp_path: Path) -> None:
    write_map(_map(), tmp_path / "map.png")
    image = decode_png((tmp_path / "map.png").read_bytes())
    assert image.ndim == 3 and image.shape[1] >= 800
    scale = image.shape[1] // 6
    assert tuple(image[-1 - scale // 2, scale // 2]) == (
        20,
        20,
        20,
    )  # origin cell bottom-left, occupied
    assert picture(_map()).shape == image.shape


def test_npz_and_unknown_suffix(tmp_path: Path) -> None:
    write_map(_map(), tmp_path / "map.npz")
    with np.load(tmp_path / "map.npz") as data:
        np.testing.assert_array_equal(data["occupancy"], _map().occupancy)
        assert tuple(data["origin_m"]) == (-1.0, 2.0)
    with pytest.raises(ValueError, match="unknown map file type"):
        write_map(_map(), tmp_path / "map.bmp")


def test_occupancy_convention_and_crop() -> None:
    logodds = np.array([[0.0, 3.5], [-2.0, 0.0]], np.float32)
    known = np.array([[False, True], [True, True]])
    occupancy = occupancy_from_logodds(logodds, known)
    assert occupancy.tolist() == [[-1, 97], [12, 50]]
    m = _map()
    part = m.crop((-1.0, 2.0, -0.9, 2.1))
    assert part.window.cols == 2 and part.window.rows == 2 and part.occupancy[0, 0] == 100
    assert m.value_at(-0.99, 2.01) == 100 and m.value_at(100.0, 100.0) == UNKNOWN
    with warnings.catch_warnings():  # numpy's "invalid value encountered in cast" was printed
        warnings.simplefilter("error")
        assert m.value_at(float("nan"), 2.0) == UNKNOWN
    # A region holding the whole map, however large, is the whole map (1e308 m overflowed the
    # cell index: "does not overlap the map", and numpy's warning on fusion's stderr).
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        whole = m.crop((-1e308, -1e308, 1e308, 1e308))
        assert whole.window == m.window
        assert m.crop((1e300, 1e300, 1e308, 1e308)).occupancy.size == 0


def test_msgpack_round_trip() -> None:
    m = _map()
    back = OccupancyMap.from_msgpack(m.to_msgpack())
    np.testing.assert_array_equal(back.occupancy, m.occupancy)
    assert (back.i0, back.j0, back.version, back.resolution_m) == (
        m.i0,
        m.j0,
        m.version,
        m.resolution_m,
    )


def test_map_server_loads_each_pixel_as_the_map_says(tmp_path: Path) -> None:
    """map_server's reading of a trinary PGM (nav2 map_io: occupancy 1 − value/255, occupied
    above occupied_thresh, free below free_thresh): at free_thresh 0.25 every unknown pixel
    (0.196) loaded as free."""
    write_map(_map(), tmp_path / "map.yaml")
    meta, image = read_map_server(tmp_path / "map.yaml")
    occ = 1.0 - image / 255.0
    occupied_thresh, free_thresh = (
        float(str(meta["occupied_thresh"])),
        float(str(meta["free_thresh"])),
    )
    loaded = np.where(occ > occupied_thresh, 100, np.where(occ < free_thresh, 0, UNKNOWN))
    loaded = loaded[::-1]  # back to the map's row order
    expected = np.full(_map().occupancy.shape, UNKNOWN)
    expected[free_cells(_map().occupancy)] = 0
    expected[occupied_cells(_map().occupancy)] = 100
    np.testing.assert_array_equal(loaded, expected)
