"""Real MuJoCo renders (EGL on CPU) agree with the scene geometry and the published calibration."""

from collections.abc import Iterator

import numpy as np
import pytest

from common.camera import StereoCalibration
from services.camera_sim.render import SceneRenderer
from services.camera_sim.rig import RigSpec, layout_pairs
from services.camera_sim.scene import MarkingSpec, ObjectSpec, SceneSpec, generate_scene

Rendered = tuple[SceneSpec, list[StereoCalibration], SceneRenderer]

BOX = ObjectSpec(name="box_a", shape="box", center_xy_m=(3.3, 2.7), size_m=(1.0, 0.8, 1.25))


@pytest.fixture(scope="module")
def rendered() -> Iterator[Rendered]:
    scene = SceneSpec(objects=[BOX])
    calibrations = layout_pairs(RigSpec(), scene.floor_size_m)
    renderer = SceneRenderer(scene, calibrations)
    renderer.set_time(0.0)
    yield scene, calibrations, renderer
    renderer.close()


def test_floor_depth_matches_camera_height(rendered: Rendered) -> None:
    _, calibrations, renderer = rendered
    calib = calibrations[0]
    depth = renderer.render_depth("p0_left", 640, 480)
    u, v, z = calib.left.project([(1.0, 4.5, 0.0)])[0]  # bare floor, in view
    assert z == pytest.approx(6.0)
    assert depth[round(v), round(u)] == pytest.approx(6.0, abs=2e-3)


def test_box_top_appears_at_its_height_where_the_calibration_projects_it(
    rendered: Rendered,
) -> None:
    _, calibrations, renderer = rendered
    calib = calibrations[0]
    depth = renderer.render_depth("p0_left", 640, 480)
    top = 1.25
    for corner_sign in (
        (0.4, 0.3),
        (-0.4, -0.3),
        (0.4, -0.3),
    ):  # inside the top face, near its corners
        point = (BOX.center_xy_m[0] + corner_sign[0], BOX.center_xy_m[1] + corner_sign[1], top)
        u, v, _z = calib.left.project([point])[0]
        assert depth[round(v), round(u)] == pytest.approx(6.0 - top, abs=2e-3)
    # Just outside the box's footprint, the floor (or the box's side) is seen, not the top.
    u, v, _ = calib.left.project([(BOX.center_xy_m[0] + 0.56, BOX.center_xy_m[1], top)])[0]
    assert depth[round(v), round(u)] > 6.0 - top + 0.05


def test_right_camera_sees_the_same_box_shifted_by_the_disparity(rendered: Rendered) -> None:
    _, calibrations, renderer = rendered
    calib = calibrations[0]
    point = (BOX.center_xy_m[0], BOX.center_xy_m[1], 1.25)
    u_left, v_left, z = calib.left.project([point])[0]
    u_right, v_right, _ = calib.right.project([point])[0]
    assert v_left == pytest.approx(v_right)
    assert u_left - u_right == pytest.approx(calib.left.focal_px * calib.baseline_m / z)
    depth_right = renderer.render_depth("p0_right", 640, 480)
    assert depth_right[round(v_right), round(u_right)] == pytest.approx(6.0 - 1.25, abs=2e-3)


def test_floors_have_the_texture_their_names_promise() -> None:
    calibrations = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))
    stds = {}
    for floor in ("speckle", "concrete", "plain"):
        renderer = SceneRenderer(SceneSpec(floor=floor), calibrations)
        renderer.set_time(0.0)
        image = renderer.render_gray("p0_left", 640, 480).astype(np.float64)
        patch = image[200:280, 280:360]
        # Texture at the scale stereo matches on: what is left after removing the slow shading.
        fine = patch[1:, 1:] - (patch[:-1, 1:] + patch[1:, :-1]) / 2
        stds[floor] = float(fine.std())
        renderer.close()
    assert stds["speckle"] > 10.0
    assert 0.8 < stds["concrete"] < stds["speckle"] / 4  # weak, but not none
    assert stds["plain"] < 0.5
    assert SceneSpec(floor="textured").floor == "speckle"  # the old name still loads


@pytest.mark.parametrize("floor_size_m", [(12.0, 10.0), (9.0, 7.0)])
def test_markings_are_painted_flat_where_the_scene_puts_them(
    floor_size_m: tuple[float, float],
) -> None:
    # Off the pair's centre (a texture mapped the wrong way round would miss it).
    centre_xy_m = (floor_size_m[0] / 2 - 1.3, floor_size_m[1] / 2 + 0.9)
    line = MarkingSpec(center_xy_m=centre_xy_m, size_m=(1.6, 0.08), yaw_rad=0.5)
    scene = SceneSpec(floor_size_m=floor_size_m, floor="plain", markings=[line])
    calib = layout_pairs(RigSpec(pair_count=1), floor_size_m)[0]
    depths = []
    for markings in ([line], []):
        renderer = SceneRenderer(scene.model_copy(update={"markings": markings}), [calib])
        renderer.set_time(0.0)
        if markings:
            rgb = renderer.render_rgb("p0_left", 640, 480).astype(np.float64)
        depths.append(renderer.render_depth("p0_left", 640, 480))
        renderer.close()
    depth = depths[0]
    # Flat: the paint adds no geometry (a 1 mm box moved the depth of every pixel it covered).
    assert float(np.abs(depths[0] - depths[1]).max()) < 1e-4
    yellowness = rgb[:, :, 0] - rgb[:, :, 2]
    across = np.array([-np.sin(line.yaw_rad), np.cos(line.yaw_rad)])
    for along_m in (-0.6, 0.0, 0.6):
        centre = np.asarray(line.center_xy_m) + along_m * np.array(
            [np.cos(line.yaw_rad), np.sin(line.yaw_rad)]
        )
        u, v, z = calib.left.project([(*centre, 0.0)])[0]
        assert yellowness[round(v), round(u)] > 100  # paint, where the scene puts it
        assert depth[round(v), round(u)] == pytest.approx(z, abs=2e-3)  # flat: the floor's depth
        for side in (-1, 1):  # 3 cm past each edge: bare floor
            u, v, _ = calib.left.project([(*(centre + side * 0.07 * across), 0.0)])[0]
            assert abs(yellowness[round(v), round(u)]) < 10


def test_movers_follow_their_path_as_a_pure_function_of_time() -> None:
    scene = generate_scene(3)
    mover = scene.movers[0]
    a = mover.state_at(1234.5)
    assert a == mover.state_at(1234.5)
    (x0, y0), (vx, vy) = mover.state_at(100.0)
    (x1, y1), _ = mover.state_at(100.1)
    assert np.hypot(x1 - x0, y1 - y0) == pytest.approx(mover.speed_mps * 0.1, rel=1e-3)
    assert np.hypot(vx, vy) == pytest.approx(mover.speed_mps)


def test_generated_scene_respects_the_brief() -> None:
    scene = generate_scene(0)
    tops = [o.size_m[2] for o in scene.objects]
    assert len(scene.objects) >= 10 and len(scene.movers) >= 2
    assert all(0.14 <= t <= 2.0 for t in tops)
    assert {o.shape for o in scene.objects} == {"box", "cylinder", "shelf", "pallet"}
    assert any(o.plain for o in scene.objects)  # at least one object with no texture at all
    assert {round(m.speed_mps, 1) for m in scene.movers} == {1.2, 2.0}  # a person, a forklift
    assert scene.markings  # lane lines
    assert all(o.plain for o in generate_scene(0, plain_objects=True).objects)


def test_pair_footprints_cover_the_floor() -> None:
    calibrations = layout_pairs(RigSpec(), (12.0, 10.0))
    xs, ys = np.meshgrid(np.linspace(0.05, 11.95, 60), np.linspace(0.05, 9.95, 50))
    floor = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    seen = np.zeros(len(floor), dtype=bool)
    for calib in calibrations:
        for camera in (calib.left, calib.right):
            u, v, _ = camera.project(floor).T
            seen |= (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    assert seen.all()
