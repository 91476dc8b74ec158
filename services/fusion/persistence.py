"""The map survives a restart: written atomically (temp file + rename), loaded at start."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np

from common.lattice import Window
from common.occupancy_map import occupancy_from_logodds
from services.fusion.grid import FusedGrid, GridParams

log = logging.getLogger("fusion.state")
STATE_FILE = "map_state.npz"


def save_grid(grid: FusedGrid, state_dir: Path) -> Path:
    state_dir.mkdir(parents=True, exist_ok=True)
    path = state_dir / STATE_FILE
    temp = state_dir / f".{STATE_FILE}.{os.getpid()}.tmp"
    with open(temp, "wb") as handle:
        np.savez(
            handle,
            version=grid.version,
            stamp_ns=grid.stamp_ns,
            resolution_m=grid.params.resolution_m,
            window=np.array([grid.window.i0, grid.window.j0, grid.window.cols, grid.window.rows]),
            logodds=grid.logodds,
            height_m=grid.height_m,
            known=grid.known,
            last_seen_s=grid.last_seen_s,
        )
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temp, path)
    return path


def load_grid(params: GridParams, state_dir: Path) -> FusedGrid | None:
    """The saved grid, or None if there is none; a corrupt or incompatible file is set aside."""
    path = state_dir / STATE_FILE
    if not path.exists():
        return None
    try:
        with np.load(path) as data:
            if float(data["resolution_m"]) != params.resolution_m:
                raise ValueError(
                    f"saved resolution {float(data['resolution_m'])} m ≠ {params.resolution_m} m"
                )
            i0, j0, cols, rows = (int(v) for v in data["window"])
            saved = Window(i0, j0, cols, rows)
            layers = {name: data[name] for name in ("logodds", "height_m", "known", "last_seen_s")}
            for name, array in layers.items():
                if array.shape != saved.shape:
                    raise ValueError(
                        f"layer {name} has shape {array.shape}, expected {saved.shape}"
                    )
            grid = FusedGrid(params)
            if params.bounds is None:
                grid.window = saved
                for name, array in layers.items():
                    setattr(grid, name, array.astype(getattr(grid, name).dtype))
            else:  # bounds changed since the save: keep what still lies inside them
                part = saved.intersect(grid.window)
                for name, array in layers.items():
                    getattr(grid, name)[part.slices_in(grid.window)] = array[part.slices_in(saved)]
            grid.occupancy = occupancy_from_logodds(grid.logodds, grid.known)
            grid.predicted = np.zeros(grid.window.shape, np.bool_)  # predictions are not saved
            grid.version = int(data["version"])
            grid.stamp_ns = int(data["stamp_ns"])
    except Exception as error:  # any unreadable file: keep it for inspection, start empty
        aside = path.with_name(f"{STATE_FILE}.corrupt-{int(time.time())}")
        path.rename(aside)
        log.error(
            "state file unusable, set aside", extra={"path": str(aside), "error": str(error)[:200]}
        )
        return None
    return grid
