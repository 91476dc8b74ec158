"""Named rules that combine a tile into the map, one line each (after nav2 costmap_2d's
``updateWithMax``/``updateWithAddition``). They work in place on views of matching shape."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
B = npt.NDArray[np.bool_]


def add_logodds_clamped(logodds: F32, update: F32, observed: B, low: float, high: float) -> None:
    """Bayesian update L ← clamp(L + ΔL, L_min, L_max) where observed (OctoMap's clamping)."""
    logodds[observed] = np.clip(logodds[observed] + update[observed], low, high)


def height_with_max(height: F32, tile_height: F32, observed: B) -> None:
    """Highest top seen over pairs: the seed's "pixel-wise minimum depth" stitching."""
    height[observed] = np.fmax(height[observed], tile_height[observed])


def height_overwrite_where_free(height: F32, tile_height: F32, free: B) -> None:
    """A free observation shows the floor: an old object's top there is gone."""
    height[free] = tile_height[free]
