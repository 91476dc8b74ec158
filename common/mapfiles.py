"""Map files a person or nav2 reads: map_server PGM + YAML, a PNG picture, and NPZ arrays."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import yaml

from common.occupancy_map import OccupancyMap
from common.png import encode_png

# nav2 map_server "trinary" mode pixel values and thresholds.
PGM_OCCUPIED = 0
PGM_FREE = 254
PGM_UNKNOWN = 205
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.25
OCCUPIED_MIN = round(OCCUPIED_THRESH * 100)
FREE_MAX = round(FREE_THRESH * 100)
"""The thresholds on nav_msgs occupancy (0..100): occupied from OCCUPIED_MIN, free up to FREE_MAX."""
FILE_FREE_THRESH = 0.196
"""``free_thresh`` in map.yaml: the cells are sorted by FREE_THRESH before they are written, and
the file's thresholds need only tell its three pixel values apart. map_server reads a pixel's
occupancy as 1 − value/255 and calls it free below ``free_thresh``: the unknown pixel is
1 − 205/255 = 0.19608, so at 0.25 every unknown cell loaded as free (ROS 1's map_saver wrote
0.196 for this reason)."""


def free_cells(occupancy: npt.NDArray[np.int8]) -> npt.NDArray[np.bool_]:
    """The cells a nav_msgs occupancy calls free (known, and at most FREE_MAX)."""
    free: npt.NDArray[np.bool_] = (occupancy >= 0) & (occupancy <= FREE_MAX)
    return free


def occupied_cells(occupancy: npt.NDArray[np.int8]) -> npt.NDArray[np.bool_]:
    """The cells a nav_msgs occupancy calls occupied (at least OCCUPIED_MIN)."""
    occupied: npt.NDArray[np.bool_] = occupancy >= OCCUPIED_MIN
    return occupied


MAP_FILE_SUFFIXES = (".yaml", ".yml", ".pgm", ".png", ".npz")
"""What :func:`write_map` writes, by the file's suffix."""

PICTURE_COLORS = {
    "free": (255, 255, 255),
    "occupied": (20, 20, 20),
    "unknown": (180, 180, 190),
    "scale": (220, 30, 30),
    "truth": (30, 110, 230),
}


def trinary(occupancy: npt.NDArray[np.int8]) -> npt.NDArray[np.uint8]:
    """map_server trinary values, rows as stored (origin row first)."""
    image = np.full(occupancy.shape, PGM_UNKNOWN, np.uint8)
    image[free_cells(occupancy)] = PGM_FREE
    image[occupied_cells(occupancy)] = PGM_OCCUPIED
    return image


def pgm_bytes(occupancy_map: OccupancyMap) -> bytes:
    """Binary PGM; rows flipped so the image's bottom row is the origin, as map_server expects."""
    image = trinary(occupancy_map.occupancy)[::-1]
    rows, cols = image.shape
    return f"P5\n{cols} {rows}\n255\n".encode() + np.ascontiguousarray(image).tobytes()


def map_yaml(occupancy_map: OccupancyMap, image_name: str) -> str:
    x0, y0 = occupancy_map.origin_m
    return yaml.safe_dump(
        {
            "image": image_name,
            "mode": "trinary",
            "resolution": occupancy_map.resolution_m,
            "origin": [x0, y0, 0.0],
            "negate": 0,
            "occupied_thresh": OCCUPIED_THRESH,
            "free_thresh": FILE_FREE_THRESH,
        },
        sort_keys=False,
    )


def write_map_server(occupancy_map: OccupancyMap, yaml_path: Path) -> tuple[Path, Path]:
    """Write ``NAME.yaml`` and ``NAME.pgm`` beside it; returns both paths."""
    pgm_path = yaml_path.with_suffix(".pgm")
    pgm_path.write_bytes(pgm_bytes(occupancy_map))
    yaml_path.write_text(map_yaml(occupancy_map, pgm_path.name))
    return yaml_path, pgm_path


def read_map_server(yaml_path: Path) -> tuple[dict[str, object], npt.NDArray[np.uint8]]:
    """The YAML fields and the PGM image (rows as in the file: top row first)."""
    meta = yaml.safe_load(yaml_path.read_text())
    data = (yaml_path.parent / str(meta["image"])).read_bytes()
    magic, size, maxval, pixels = data.split(b"\n", 3)
    if magic != b"P5" or maxval != b"255":
        raise ValueError(f"{meta['image']} is not an 8-bit binary PGM")
    cols, rows = (int(v) for v in size.split())
    return meta, np.frombuffer(pixels, np.uint8).reshape(rows, cols)


def _outline(mask: npt.NDArray[np.bool_]) -> npt.NDArray[np.bool_]:
    """Pixels of ``mask`` with a 4-neighbour outside it: a one-pixel contour."""
    padded = np.pad(mask, 1)
    inner = padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]
    return mask & ~inner


def picture(
    occupancy_map: OccupancyMap,
    min_width_px: int = 800,
    truth: npt.NDArray[np.bool_] | None = None,
) -> npt.NDArray[np.uint8]:
    """RGB picture: free white, occupied black, unknown grey, y up, with a 1 m scale bar; the
    outlines of ``truth`` (cells on the map's window that are truly occupied) drawn over it."""
    occ = occupancy_map.occupancy
    rgb = np.empty((*occ.shape, 3), np.uint8)
    rgb[:] = PICTURE_COLORS["unknown"]
    rgb[free_cells(occ)] = PICTURE_COLORS["free"]
    between = (occ > FREE_MAX) & (occ < OCCUPIED_MIN)
    rgb[between] = (150, 150, 150)
    rgb[occ >= OCCUPIED_MIN] = PICTURE_COLORS["occupied"]
    scale = max(1, -(-min_width_px // max(occ.shape[1], 1)))
    big = np.repeat(np.repeat(rgb[::-1], scale, axis=0), scale, axis=1)
    if truth is not None:
        big_truth = np.repeat(np.repeat(truth[::-1], scale, axis=0), scale, axis=1)
        contour = _outline(big_truth)
        if scale >= 4:  # two pixels wide where there is room, so it reads at a glance
            contour |= _outline(big_truth & ~contour)
        big[contour] = PICTURE_COLORS["truth"]
    px_per_m = scale / occupancy_map.resolution_m
    bar_len = round(px_per_m)
    margin = max(4, scale)
    if big.shape[1] > bar_len + 2 * margin and big.shape[0] > 4 * margin:
        y = big.shape[0] - 2 * margin
        red = PICTURE_COLORS["scale"]
        big[y : y + max(2, scale // 2), margin : margin + bar_len] = red  # 1 m scale bar
        big[y - 3 * margin // 2 : y, margin : margin + 2] = red
        big[y - 3 * margin // 2 : y, margin + bar_len - 2 : margin + bar_len] = red
    return big


def png_bytes(occupancy_map: OccupancyMap, truth: npt.NDArray[np.bool_] | None = None) -> bytes:
    return encode_png(picture(occupancy_map, truth=truth))


def write_npz(occupancy_map: OccupancyMap, path: Path) -> None:
    arrays: dict[str, Any] = {
        "occupancy": occupancy_map.occupancy,
        "resolution_m": occupancy_map.resolution_m,
        "origin_m": np.array(occupancy_map.origin_m),
        "version": occupancy_map.version,
        "stamp_ns": occupancy_map.stamp_ns,
    }
    for name, layer in (("logodds", occupancy_map.logodds), ("height_m", occupancy_map.height_m)):
        if layer is not None:
            arrays[name] = layer
    np.savez_compressed(path, **arrays)


def map_file_suffix(path: Path) -> str:
    """The suffix that says how ``path`` is written; a ValueError names the ones there are."""
    suffix = path.suffix.lower()
    if suffix not in MAP_FILE_SUFFIXES:
        raise ValueError(f"unknown map file type {suffix!r}: use {', '.join(MAP_FILE_SUFFIXES)}")
    return suffix


def write_map(
    occupancy_map: OccupancyMap, path: Path, truth: npt.NDArray[np.bool_] | None = None
) -> list[Path]:
    """Write by suffix: .yaml (+ .pgm), .pgm (+ .yaml), .png (with ``truth`` outlined) or .npz."""
    suffix = map_file_suffix(path)
    if occupancy_map.occupancy.size == 0:
        raise ValueError("the map has no cells yet (no tile fused): nothing to write")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix in (".yaml", ".yml", ".pgm"):
        return list(write_map_server(occupancy_map, path.with_suffix(".yaml")))
    if suffix == ".png":
        path.write_bytes(png_bytes(occupancy_map, truth))
        return [path]
    write_npz(occupancy_map, path)
    return [path]
