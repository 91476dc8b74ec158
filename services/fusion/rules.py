"""Named rules that combine a tile into the map, one line each (after nav2 costmap_2d's
``updateWithMax``/``updateWithAddition``). They work in place on views of matching shape; masks
select the cells a rule applies to (``where=`` keeps them branch-free and fast)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
B = npt.NDArray[np.bool_]


def add_logodds_clamped(logodds: F32, update: F32, observed: B, low: float, high: float) -> None:
    """Bayesian update L ← clamp(L + ΔL, L_min, L_max) where observed (OctoMap's clamping)."""
    np.copyto(logodds, np.clip(logodds + update, low, high), where=observed)


def height_with_max(height: F32, tile_height: F32, observed: B) -> None:
    """Highest top seen over pairs: the seed's "pixel-wise minimum depth" stitching."""
    np.fmax(height, tile_height, out=height, where=observed)


def height_overwrite_where_free(height: F32, tile_height: F32, free: B) -> None:
    """A free observation shows the floor: an old object's top there is gone."""
    np.copyto(height, tile_height, where=free)
