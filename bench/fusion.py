"""Fusion ingest benchmark: tiles per second on one core, ours vs OctoMap, same observations, same run.

Ours: decode + every intake check + clamped log-odds integration (``TileGate.admit`` then
``FusedGrid.integrate``), as the fusion service does per tile. OctoMap (pyoctomap): the same observed
cells of the same tiles, occupied cells as hits and free cells as misses (OctoMap's own sensor model),
batched with lazy evaluation and one ``updateInnerOccupancy`` per tile, in one voxel layer — the
cheapest way to give OctoMap a 2D update. Point arrays for OctoMap are prepared outside the timing.

    .venv/bin/python bench/fusion.py [--tiles 3000] [--octomap-tiles 60] [--rounds 3]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import statistics
import sys
import time

import cv2
import numpy as np
import pyoctomap

from bench.tiles import rendered_tiles
from common.codec import encode
from common.messages import TILE_KIND, TileHeader
from services.fusion.grid import FusedGrid, GridParams
from services.fusion.intake import TileGate

RESOLUTION_M = 0.05


def ours_rate(payloads: list[tuple[str, bytes]], count: int) -> float:
    grid = FusedGrid(GridParams(resolution_m=RESOLUTION_M))
    gate = TileGate(RESOLUTION_M, max_age_s=1e9, max_bytes=64 * 1024 * 1024)
    now_ns = time.time_ns()
    started = time.perf_counter()
    for k in range(count):
        gate.newest_stamp_ns.clear()  # replaying the same tiles: the order check still runs, and passes
        key, payload = payloads[k % len(payloads)]
        tile = gate.admit(payload, now_ns, key)
        grid.integrate_tile(tile, tile.header.stamp_ns)
    return count / (time.perf_counter() - started)


def octomap_rate(points: list[tuple[np.ndarray, np.ndarray]], count: int) -> float:
    tree = pyoctomap.OcTree(RESOLUTION_M)
    started = time.perf_counter()
    for k in range(count):
        occupied, free = points[k % len(points)]
        tree.updateNodes(occupied, True, True)
        tree.updateNodes(free, False, True)
        tree.updateInnerOccupancy()
    return count / (time.perf_counter() - started)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--tiles", type=int, default=3000, help="tiles per timed batch, ours")
    parser.add_argument(
        "--octomap-tiles", type=int, default=60, help="tiles per timed batch, OctoMap"
    )
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds")
    args = parser.parse_args()
    cv2.setNumThreads(1)

    tiles = rendered_tiles()
    payloads, points = [], []
    for seq, (pair, tile) in enumerate(tiles):
        w = tile.window
        header = TileHeader(
            pair=pair,
            seq=seq,
            stamp_ns=time.time_ns(),
            resolution_m=RESOLUTION_M,
            i0=w.i0,
            j0=w.j0,
            cols=w.cols,
            rows=w.rows,
        )
        payloads.append((f"depth/{pair}/tile", encode(TILE_KIND, header, tile.arrays())))
        x, y = w.cell_centers(RESOLUTION_M)
        observed = tile.count > 0
        z = np.full(x.shape, RESOLUTION_M / 2)
        xyz = np.stack([x, y, z], axis=-1)
        points.append(
            (xyz[observed & (tile.logodds > 0)].copy(), xyz[observed & (tile.logodds <= 0)].copy())
        )
    cells = statistics.mean(int((t.count > 0).sum()) for _, t in tiles)
    size = statistics.mean(t.window.cols * t.window.rows for _, t in tiles)
    print(
        f"{len(tiles)} distinct tiles, {size:.0f} cells each, {cells:.0f} observed", file=sys.stderr
    )

    ours, octo = [], []
    for round_index in range(args.rounds):  # alternate so machine noise hits both alike
        ours.append(ours_rate(payloads, args.tiles))
        octo.append(octomap_rate(points, args.octomap_tiles))
        print(
            f"round {round_index + 1}: ours {ours[-1]:.0f} tiles/s, octomap {octo[-1]:.1f} tiles/s",
            file=sys.stderr,
        )
    result = {
        "tiles_per_s": round(statistics.median(ours), 1),
        "octomap_tiles_per_s": round(statistics.median(octo), 2),
        "octomap_ratio": round(statistics.median(ours) / statistics.median(octo), 1),
        "cells_per_tile": round(size),
        "observed_cells_per_tile": round(cells),
    }
    print(f"ours    {result['tiles_per_s']:>10.1f} tiles/s")
    print(f"octomap {result['octomap_tiles_per_s']:>10.2f} tiles/s")
    print(f"ratio   {result['octomap_ratio']:>10.1f}×")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
