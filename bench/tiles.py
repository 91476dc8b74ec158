"""Real tiles for the fusion benchmarks: rendered by camera_sim, turned into tiles by the depth
pipeline (default scene, default settings), so sizes and sparsity are those of the running system."""

from __future__ import annotations

import sys

from services.camera_sim.render import SceneRenderer
from services.camera_sim.rig import RigSpec, layout_pairs
from services.camera_sim.scene import generate_scene
from services.depth.inverse_model import Tile
from services.depth.pipeline import DepthPipeline, PipelineConfig


def rendered_tiles(instants: int = 2, pair_count: int = 4) -> list[tuple[str, Tile]]:
    scene = generate_scene(0)
    calibrations = layout_pairs(RigSpec(pair_count=pair_count), scene.floor_size_m)
    renderer = SceneRenderer(scene, calibrations)
    pipelines = {c.pair: DepthPipeline(c, PipelineConfig()) for c in calibrations}
    tiles = []
    print(f"rendering {instants * len(calibrations)} frames for tiles …", file=sys.stderr)
    for instant in range(instants):
        renderer.set_time(5.0 * instant)
        for calib in calibrations:
            w, h = calib.image_size
            left = renderer.render_gray(f"{calib.pair}_left", w, h)
            right = renderer.render_gray(f"{calib.pair}_right", w, h)
            tiles.append((calib.pair, pipelines[calib.pair].process(left, right).tile))
    renderer.close()
    return tiles
