"""Real renders → real OpenCV stereo → tiles, checked against MuJoCo's depth buffer and the scene."""

import numpy as np
import numpy.typing as npt
import pytest

from common.camera import StereoCalibration
from common.lattice import cell_of
from services.camera_sim import truth
from services.camera_sim.render import SceneRenderer
from services.camera_sim.rig import RigSpec, layout_pairs
from services.camera_sim.scene import ObjectSpec, SceneSpec, generate_scene
from services.depth.inverse_model import build_tile
from services.depth.pipeline import DepthPipeline, FrameResult, PipelineConfig, view_edge
from services.depth.projection import project_to_world
from services.depth.stereo import Rectifier

BOX = ObjectSpec(
    name="box_k", shape="box", center_xy_m=(6.4, 4.6), yaw_rad=0.3, size_m=(1.0, 0.7, 0.9)
)


Frames = tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8], npt.NDArray[np.float32]]
"""Left and right grey images and the left camera's MuJoCo depth (m)."""

BoxScene = tuple[SceneSpec, StereoCalibration, npt.NDArray[np.float32], FrameResult]


def _render(
    scene: SceneSpec, pair_count: int = 1, pair_index: int = 0
) -> tuple[StereoCalibration, Frames]:
    calibrations = layout_pairs(RigSpec(pair_count=pair_count), scene.floor_size_m)
    calib = calibrations[pair_index]
    renderer = SceneRenderer(scene, calibrations)
    renderer.set_time(0.0)
    name = calib.pair
    frames = (
        renderer.render_gray(f"{name}_left", 640, 480),
        renderer.render_gray(f"{name}_right", 640, 480),
        renderer.render_depth(f"{name}_left", 640, 480),
    )
    renderer.close()
    return calib, frames


@pytest.fixture(scope="module")
def box_scene() -> BoxScene:
    scene = SceneSpec(objects=[BOX])
    calib, (left, right, depth) = _render(scene)
    result = DepthPipeline(calib, PipelineConfig()).process(left, right)
    return scene, calib, depth, result


def test_search_band_comes_from_the_geometry() -> None:
    calib = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0]
    rectifier = Rectifier.from_calibration(calib, downscale=1)
    d_min, n = rectifier.disparity_band(0.0, 2.0)
    floor_d = calib.left.focal_px * 0.5 / 6.0  # ≈ 46 px
    top_d = calib.left.focal_px * 0.5 / 4.0  # ≈ 69 px
    assert d_min <= floor_d < top_d <= d_min + n
    assert n % 16 == 0 and n <= 48  # a few dozen pixels, not 160


def test_floor_depth_error_against_mujoco_depth_buffer() -> None:
    calib, (left, right, depth_true) = _render(generate_scene(0), pair_count=4, pair_index=2)
    pipeline = DepthPipeline(calib, PipelineConfig())
    result = pipeline.process(left, right)
    s = pipeline.config.downscale
    truth_small = depth_true.reshape(240, s, 320, s).max(
        axis=(1, 3)
    )  # conservative: pure floor blocks
    disparity = result.disparity_px
    depth = pipeline.rectifier.focal_px * pipeline.rectifier.baseline_m / disparity
    floor = (truth_small > 5.99) & np.isfinite(depth)
    assert floor.mean() > 0.5
    assert np.median(np.abs(depth[floor] - truth_small[floor])) <= 0.03


def test_object_top_depth_error_against_mujoco_depth_buffer(box_scene: BoxScene) -> None:
    # A cardboard box's top: weak texture, where SGBM's own sub-pixel fit locks to whole pixels;
    # the chain's sub-pixel stage (tests/test_stereo.py) undoes that. (The generated scene's plain
    # crate has no texture at all: stereo cannot measure it, and tops there say nothing of this.)
    _scene, calib, depth_true, result = box_scene
    pipeline = DepthPipeline(calib, PipelineConfig())
    blocks = depth_true.reshape(240, 2, 320, 2)
    nearest, farthest = blocks.min(axis=(1, 3)), blocks.max(axis=(1, 3))
    depth = pipeline.rectifier.focal_px * pipeline.rectifier.baseline_m / result.disparity_px
    tops = (farthest < 5.85) & (farthest - nearest < 0.002) & np.isfinite(depth)  # flat, ≥ 15 cm
    assert tops.sum() > 1000
    # 0.56 cm measured; 1.04 cm without the sub-pixel stage, 1.51 cm with SGBM alone.
    assert np.median(np.abs(depth[tops] - farthest[tops])) <= 0.008


def test_tile_is_on_the_lattice(box_scene: BoxScene) -> None:
    _, _, _, result = box_scene
    tile = result.tile
    assert tile.logodds.shape == tile.window.shape == tile.count.shape == tile.height_m.shape
    # Every projected point falls in the cell the tile's window says it does.
    ij = cell_of(np.column_stack([result.points.x_m, result.points.y_m]), tile.resolution_m)
    inside = (ij[:, 0] >= tile.window.i0) & (ij[:, 0] < tile.window.i1)
    assert inside.mean() > 0.99
    assert np.all(np.isnan(tile.height_m[tile.count == 0]))
    assert np.all(tile.logodds[tile.count == 0] == 0)


def test_box_is_occupied_and_the_floor_around_it_free(box_scene: BoxScene) -> None:
    scene, _, _, result = box_scene
    tile = result.tile
    r = tile.resolution_m
    occupied_truth = truth.occupancy(scene.truth_objects(0.0), tile.window, r, (0.1, 2.0)).astype(
        bool
    )
    # Core: the box eroded by 2 cells; ring: 2–4 cells outside it (edge artefacts live in between).
    box_only = truth.footprint_mask(scene.truth_objects(0.0)[0], tile.window, r)
    core = box_only.copy()
    for axis in (0, 1):
        for shift in (2, -2):
            core &= np.roll(box_only, shift, axis=axis)
    ring = np.zeros_like(box_only)
    for axis in (0, 1):
        for shift in (4, -4):
            ring |= np.roll(box_only, shift, axis=axis)
    ring &= ~occupied_truth
    for axis in (0, 1):
        for shift in (2, -2):
            ring &= ~np.roll(box_only, shift, axis=axis)
    seen = tile.count > 0
    assert (tile.logodds[core & seen] > 0.5).mean() > 0.95
    # The floor 2–4 cells out reads free; a cell a quarter or more in the band there (the tail
    # of fattening and side faces) gives no evidence since the rim rule (free 0.90, 0.95 before).
    assert (tile.logodds[ring & seen] < 0).mean() > 0.85
    assert (tile.logodds[ring & seen] > 0).mean() < 0.08
    assert core.sum() > 100 and seen[core].mean() > 0.9
    tops = tile.height_m[core & seen]
    assert np.median(tops) == pytest.approx(BOX.size_m[2], abs=0.04)


def test_floor_far_from_objects_is_free(box_scene: BoxScene) -> None:
    _scene, _, _, result = box_scene
    tile = result.tile
    x, y = tile.window.cell_centers(tile.resolution_m)
    far = np.hypot(x - BOX.center_xy_m[0], y - BOX.center_xy_m[1]) > 1.5
    far &= (x > 0.5) & (x < 11.5) & (y > 0.5) & (y < 9.5) & (tile.count > 0)
    assert far.sum() > 5000
    assert (tile.logodds[far] < 0).mean() > 0.995


def test_wrong_image_size_is_a_clear_error(box_scene: BoxScene) -> None:
    _, calib, _, _ = box_scene
    pipeline = DepthPipeline(calib, PipelineConfig())
    small = np.zeros((240, 320), np.uint8)
    with pytest.raises(ValueError, match="320×240, calibration says 640×480"):
        pipeline.process(small, small)


def test_the_floor_behind_a_standing_pixel_is_hidden_and_no_other() -> None:
    """The hidden floor points are those of the pixels whose evidence stands in the band or above
    (and of the floor model's rule 10), matched to the points pixel for pixel: NaN, ±inf and
    non-positive disparities make no point and hide nothing; a floor reading hides nothing."""
    calib = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0]
    pipeline = DepthPipeline(calib, PipelineConfig())
    assert pipeline.floor_model is not None
    geometry = pipeline.floor_model.geometry
    evidence = np.full(geometry.floor_disparity_px.shape, np.nan, np.float32)
    standing, floor, departed = (40, 50), (40, 51), (60, 70)
    evidence[standing] = geometry.disparity_px(np.full_like(evidence, 0.5))[standing]
    evidence[floor] = geometry.floor_disparity_px[floor]
    evidence[40, 52], evidence[40, 53], evidence[40, 54], evidence[40, 55] = np.inf, -np.inf, -1, 0
    points = project_to_world(
        evidence,
        pipeline.rays_world,
        pipeline.rectifier.C_world,
        pipeline.rectifier.focal_px,
        pipeline.rectifier.baseline_m,
        pipeline.config.model,
        pipeline.config.downscale,
    )
    pipeline.floor_model.hidden[:] = False
    pipeline.floor_model.hidden[departed] = True
    hidden = pipeline._hidden_floor_xy(np.flatnonzero(np.isfinite(evidence)), points)
    floor_xy = pipeline.floor_xy_m
    expected = np.stack(
        [floor_xy[:, standing[0], standing[1]], floor_xy[:, departed[0], departed[1]]], 1
    )
    np.testing.assert_array_equal(hidden, expected)


def test_the_view_edge_is_the_border_of_what_the_matcher_measures() -> None:
    """5 % of the shorter side (12 px of 320 × 240) from the image's border, and on the left from
    the columns the matcher has no disparity for."""
    edge = view_edge((240, 320), 40)
    inside_rows, inside_cols = np.nonzero(~edge)
    assert (inside_rows.min(), inside_rows.max()) == (12, 227)
    assert (inside_cols.min(), inside_cols.max()) == (52, 307)
    assert (~edge).sum() == (228 - 12) * (308 - 52)


def test_a_side_face_no_longer_fills_the_cells_beside_a_box() -> None:
    """A tall box 2.5 m off the pair's nadir, so the camera sees one long side face over many
    pixels: the tile leaves the face's points out of the cells whose centre lies on the open
    side of it (build_tile's ``camera_m``, which the pipeline passes), so fewer cells just
    outside the box read occupied than when every point counts; none of the box's own cells
    turns free, and 97 % or more of those occupied stay so (the rest give no reading: their
    points lie behind the box's top along their rays, the top's scatter in front of a face's
    lower points, or the far edge's mixed pixels)."""
    box = ObjectSpec(
        name="box_f", shape="box", center_xy_m=(8.3, 6.3), yaw_rad=0.3, size_m=(1.0, 0.7, 1.2)
    )
    scene = SceneSpec(objects=[box])
    calib, (left, right, _depth) = _render(scene)
    pipeline = DepthPipeline(calib, PipelineConfig())
    result = pipeline.process(left, right)
    config = pipeline.config
    valid_px = np.flatnonzero(np.isfinite(result.evidence_disparity_px))
    hidden = pipeline._hidden_floor_xy(valid_px, result.points)
    every_point = build_tile(
        result.points, config.resolution_m, config.model, config.min_cell_pixels, hidden
    )
    tile = result.tile
    assert every_point.window == tile.window
    inside = truth.footprint_mask(scene.truth_objects(0.0)[0], tile.window, tile.resolution_m)
    beside = np.zeros_like(inside)  # the cells sharing a side with the box's cells
    for axis in (0, 1):
        for shift in (1, -1):
            beside |= np.roll(inside, shift, axis=axis)
    beside &= ~inside
    occupied_beside = int((tile.logodds[beside] > 0).sum())
    assert occupied_beside < int((every_point.logodds[beside] > 0).sum())
    occupied_before = every_point.logodds[inside] > 0
    assert not (occupied_before & (tile.logodds[inside] < 0)).any()
    assert (tile.logodds[inside] > 0).sum() >= 0.97 * occupied_before.sum()
    assert (tile.logodds[inside] < 0).sum() <= (every_point.logodds[inside] < 0).sum()
